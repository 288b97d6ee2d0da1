"""Fit engine: recover material parameters from a target image (optimistix).

``fitter.fit.fit(target, scene, material, ...) -> FitResult``; the module is
callable as ``fitter.fit(...)`` too (``fitter._modules``).
"""

from .._modules import make_callable
from ._drivers import fit as fit, fit_batch as fit_batch
from ._problem import LOSSES as LOSSES
from ._setup import FitError as FitError, select_pixels as select_pixels
from ._solvers import SOLVERS as SOLVERS
from .result import FitResult as FitResult

make_callable(__name__, fit)

"""Fit engine: recover material parameters from a target image (optimistix).

``fitter.fit.fit(target, scene, material, ...) -> FitResult``; the module is
callable as ``fitter.fit(...)`` too, through the package's re-export.
"""

from ._drivers import fit as fit, fit_batch as fit_batch
from ._setup import FitError as FitError, select_pixels as select_pixels
from ._problem import LOSSES as LOSSES
from ._solvers import SOLVERS as SOLVERS
from .result import FitResult as FitResult


class _CallableModule(__import__("types").ModuleType):
    """Lets ``fitter.fit(...)`` call the function while ``fitter.fit.SOLVERS`` etc. still work."""

    def __call__(self, *args, **kwargs) -> FitResult:
        return fit(*args, **kwargs)


__import__("sys").modules[__name__].__class__ = _CallableModule

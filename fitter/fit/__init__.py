"""Fit engine: recover material parameters from a target image (optimistix).

``fitter.fit.fit(target, scene, material, ...) -> FitResult``; the module is
callable as ``fitter.fit(...)`` too (``fitter._modules``). The engine (JAX)
loads on first use, optimistix only to trace a solve (a solve whose trace is
cached on disk runs without it); ``SOLVERS`` and ``LOSSES`` need neither.
"""

import importlib as _importlib

from .._modules import make_callable
from ._names import LOSSES as LOSSES, SOLVERS as SOLVERS

#: Public name -> module that defines it.
_LAZY = {"fit": "._drivers", "fit_batch": "._drivers", "FitError": "._setup",
         "select_pixels": "._setup", "FitResult": ".result"}


def __getattr__(name):
    if name not in _LAZY:
        raise AttributeError(f"module 'fitter.fit' has no attribute {name!r}")
    value = getattr(_importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value
    return value


def _fit(*args, **kwargs):
    return __getattr__("fit")(*args, **kwargs)


make_callable(__name__, _fit)

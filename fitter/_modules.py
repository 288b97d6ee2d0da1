"""Modules that are also functions: ``fitter.fit(...)`` and ``fitter.render(...)``.

The package exports the functions ``fit`` and ``render`` under the names of
the modules that define them; Python binds a submodule to its package's
attribute on import, so the module itself must be callable.
"""

import sys
import types
from typing import Callable


def make_callable(module_name: str, function: Callable) -> None:
    """Let ``module_name`` be called as ``function`` (its other names still work)."""

    class CallableModule(types.ModuleType):
        __call__ = staticmethod(function)

    sys.modules[module_name].__class__ = CallableModule

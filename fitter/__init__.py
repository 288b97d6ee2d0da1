"""fitter: recover sphere material parameters from images, with a JAX forward model.

Importing ``fitter`` is cheap: the names below are loaded on first use, so the
CLI's ``--help`` and config errors do not wait for JAX. Fits default to
float64: JAX is switched to 64-bit before it is first imported (or at once,
if the caller imported it already). Mitsuba and OpenImageIO are imported only
by the code paths that need them.
"""

import importlib as _importlib
import os as _os
import sys as _sys

if "jax" in _sys.modules:
    _sys.modules["jax"].config.update("jax_enable_x64", True)
else:
    _os.environ["JAX_ENABLE_X64"] = "1"

__version__ = "0.1.0"

#: Public name -> (module, attribute); ``fitter.fit`` is the callable module.
_LAZY = {
    "LOBES": (".bsdf", "LOBES"),
    "Material": (".material", "Material"),
    "MaterialError": (".material", "MaterialError"),
    "FitterError": (".errors", "FitterError"),
    "Renderer": (".render", "Renderer"),
    "render": (".render", "render"),
    "fit": (".fit", None),
    "FitResult": (".fit", "FitResult"),
    "fit_batch": (".fit", "fit_batch"),
    "Camera": (".scene", "Camera"),
    "DirectionalLight": (".scene", "DirectionalLight"),
    "Environment": (".scene", "Environment"),
    "PointLight": (".scene", "PointLight"),
    "Scene": (".scene", "Scene"),
    "Sphere": (".scene", "Sphere"),
}

__all__ = sorted(_LAZY) + ["__version__"]
#: Subpackages and modules the documentation reaches as ``fitter.<name>`` (e.g.
#: ``fitter.mitsuba.render``), imported on first use like the names above.
_SUBMODULES = ("batch", "compilation_cache", "config", "imageio", "metrics", "mitsuba")


def __getattr__(name):
    if name in _SUBMODULES:
        return _importlib.import_module(f".{name}", __name__)  # (the import binds it)
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'fitter' has no attribute {name!r}") from None
    mod = _importlib.import_module(module, __name__)
    value = mod if attr is None else getattr(mod, attr)
    globals()[name] = value
    return value


def __dir__():
    return __all__ + list(_SUBMODULES)

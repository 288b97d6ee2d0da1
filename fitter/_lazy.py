"""``jax`` and ``jax.numpy`` imported on first use.

The lobe modules describe their parameters (names, boxes, docs) at import and
use JAX only inside their formulas; through these proxies, reading a config or
printing an error does not wait about a second for JAX to load.
"""

import importlib
import types


class LazyModule(types.ModuleType):
    """Stands for the module ``name``; the first attribute access imports it."""

    def __getattr__(self, attr):
        return getattr(importlib.import_module(self.__name__), attr)


jax = LazyModule("jax")
jnp = LazyModule("jax.numpy")

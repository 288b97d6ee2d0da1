"""Work a fit starts on threads beside its own (imports, constant tables), and
the rule that no thread of a fit outlives it (``settled``)."""

from __future__ import annotations

import contextlib
import functools
import threading

from .. import skystencil
from ..compilation_cache import active_dir
from ..envlight import lit_by_environment
from ..material import Material
from . import _compile, _discretisation, _profile


#: Threads importing the solver library (``import_ahead``).
_IMPORTS: list = []


def import_ahead(scene=None, material=None) -> None:
    """Import optimistix (0.3 s, which tracing the solve needs) on a thread,
    beside the set-up's NumPy and the start search's XLA compile, and, where the
    environment lights an opaque lobe, make the sky stencil's constant tables
    there (``skystencil.warm``: 0.15 s of NumPy the set-up would wait for, or
    their files' loading where a cache folder holds them,
    ``compilation_cache.cached_arrays``); optimistix not when the traces may
    come from disk (``_cache``), which run without it."""
    import sys

    sky = (scene is not None and isinstance(material, Material)
           and lit_by_environment(scene, material))
    solver = "optimistix" not in sys.modules and not active_dir()
    if not (sky or solver):
        return

    def load():
        try:
            if sky:  # first: the set-up asks for them before the trace needs optimistix
                skystencil.warm()
            if solver:
                import optimistix  # noqa: F401
        except Exception:  # noqa: BLE001 (made again, and any error raised, where needed)
            pass

    _IMPORTS.append(threading.Thread(target=load, name="fitter-import", daemon=True))
    _IMPORTS[-1].start()


def settled(f):
    """``f`` that leaves no thread of its own running (``import_ahead``,
    ``compile_ahead``, ``_discretisation.prefetch``) nor a profile subset made
    ahead (``_profile.ahead``) when it returns or raises an error (an interrupt
    is not held up for them)."""
    def settle():
        for thread in list(_IMPORTS):  # (fits on other threads may settle them too)
            thread.join()
            with contextlib.suppress(ValueError):
                _IMPORTS.remove(thread)
        _compile.wait()
        _discretisation.wait()
        _profile.forget()

    @functools.wraps(f)
    def g(*args, **kwargs):
        try:
            out = f(*args, **kwargs)
        except Exception:
            settle()
            raise
        settle()
        return out

    return g

"""Executables of ``render_active`` for the fit's checks, by structure and shapes.

The stated errors' renders (``_discretisation``: the finer model's geometries,
the fitted geometry's sky terms) run once per fit on geometries of their own
shapes; each gets one executable, kept for the next fits of this process (the
last ``KEEP``) and whose trace the persistent cache keeps
(``_cache.compile_cached``).
"""

from __future__ import annotations

import jax
import numpy as np

from .._keep import hold
from .._math import single as to_single, to_device
from ..compilation_cache import FAST_COMPILE
from ..render import render_active
from ._cache import compile_cached

#: Executables of ``render`` in this process, by structure and shapes (the last ``KEEP``).
EXECUTABLES: dict = {}
KEEP = 8


def on_device(a, single: bool = False):
    """``a`` on the device: a host float array as float64 (``single``: float32),
    other host arrays and device arrays as they are."""
    if isinstance(a, jax.Array):
        return a
    return to_device(a, (np.float32 if single else np.float64)
                     if np.asarray(a).dtype.kind == "f" else None)


def args_and_key(params, geo, env, sphere, material, env_type, single: bool = False):
    """(``render``'s arguments on the device, its executable's key)."""
    args = jax.tree_util.tree_map(on_device, (params, geo, env, sphere))
    shapes = jax.tree_util.tree_map(lambda a: (a.shape, str(a.dtype)), args)
    return args, repr(("discretisation_render", material, env_type, str(shapes))
                      + (("float32",) if single else ()))


def compile_render(args, material, env_type, key, single: bool = False):
    """``render_active`` of ``material`` (P, 3), or of each of a tuple of
    materials (k, P, 3): one executable, one compile. ``single``: in float32
    (the arguments cast inside)."""
    def active(p, g, e, s):
        if single:
            p, g, e, s = to_single((p, g, e, s))
        if isinstance(material, tuple):
            return jax.numpy.stack([render_active(p, g, e, s, material=m, env_type=env_type)
                                    for m in material])
        return render_active(p, g, e, s, material=material, env_type=env_type)

    return compile_cached(active, args, key, FAST_COMPILE)


def keep(key, exe) -> None:
    """Keep ``exe`` under ``key`` (``EXECUTABLES``), the oldest beyond ``KEEP`` dropped."""
    hold(EXECUTABLES, key, exe, KEEP)


def render(params, geo, env, sphere, material, env_type, single: bool = False) -> np.ndarray:
    """``render_active`` (P, 3) as float64 NumPy (of a tuple of materials, (k, P,
    3), as ``compile_render``), through one executable per structure and shapes:
    a repeated ``fitter fit`` loads its trace instead of tracing the renderer
    (0.1 s); ``_discretisation.prefetch`` may have compiled it ahead. Host arrays
    go to the device as float64 (``to_device``: no copy kernel per shape); device
    arrays as they are. ``single``: as ``compile_render``'s."""
    args, key = args_and_key(params, geo, env, sphere, material, env_type, single)
    exe = EXECUTABLES.get(key)
    if exe is None:
        exe = compile_render(args, material, env_type, key, single)
    keep(key, exe)
    return np.asarray(exe(*args), dtype=np.float64)

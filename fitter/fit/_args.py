"""The arguments of ``fit`` and ``fit_batch``, checked before any work.

The rules are the config's: scalar options through ``fitter.checks.FIT_RULES``
(what ``[fit]`` is read with), the scene through ``fitter.scene.check_scene``,
parameter values through ``Material.full_params``. A failure is a
``FitterError`` naming the argument (``FitError``) or the key (``SceneError``,
``MaterialError``), in the config's words without the file name.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from .. import checks
from ..errors import FitterError
from ..scene import Scene, SceneError, check_scene


class FitError(FitterError):
    """A fit that cannot be set up (message says what to change)."""


def option(name: str, value):
    """``value`` of the fit option ``name`` by its rule in ``checks.FIT_RULES``."""
    try:
        return checks.fit_option(name, value)
    except checks.Problem as exc:
        raise FitError(f"{name}: {exc}") from None


def optional(name: str, value):
    """``option`` for an option whose ``None`` means "the default"."""
    return None if value is None else option(name, value)


def text(name: str, value) -> str:
    """A non-empty string argument (a folder name)."""
    try:
        return checks.string(value)
    except checks.Problem as exc:
        raise FitError(f"{name}: {exc}") from None


def scene_of(scene) -> Scene:
    """A ``Scene`` every renderer can use (``SceneError`` names the field otherwise)."""
    if not isinstance(scene, Scene):
        raise SceneError(f"scene: expected a fitter.Scene, got {checks.show(scene)}")
    check_scene(scene)
    return scene


def dtype_of(dtype):
    """``jnp.float64`` or ``jnp.float32`` as a NumPy dtype (``fit.dtype``'s rule)."""
    try:
        name = None if dtype is None else np.dtype(dtype).name  # np.dtype(None) is float64
    except TypeError:
        name = dtype
    return jnp.dtype(option("dtype", name))


def mapping(value, name: str) -> dict:
    """A ``{"lobe.param": value}`` dict (None: empty)."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise FitError(f"{name}: expected a dict {{'lobe.param': value}}, got "
                       f"{checks.show(value)}")
    return dict(value)


def image_shape(scene: Scene) -> str:
    return (f"({scene.height}, {scene.width}, 3): scene.height x scene.width pixels, "
            "3 RGB channels")


def images(value, name: str, scene: Scene) -> np.ndarray:
    """``value`` as a float64 array, or a ``FitError`` saying what it is instead."""
    if isinstance(value, (str, bytes, os.PathLike)):
        raise FitError(f"{name}: got the file name {checks.show(value)}; read the image first "
                       "(fitter.imageio.read_image) and pass the array")
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested lists
        arr = np.asarray(None)
    if arr.dtype.kind not in "iuf":  # bool, complex, str, object: not radiance values
        raise FitError(f"{name}: expected an array of numbers of shape {image_shape(scene)}, "
                       f"got {checks.show(value)}")
    return arr.astype(np.float64)


def weights_of(weights, scene: Scene) -> np.ndarray | None:
    """(H, W, 3) finite, non-negative residual weights, or None."""
    if weights is None:
        return None
    hw = (scene.height, scene.width)
    try:
        wt = np.asarray(weights)
    except (TypeError, ValueError):  # ragged nested lists
        wt = np.asarray(None)
    if wt.dtype.kind not in "iuf":
        raise FitError(f"weights: expected an array of numbers of shape {hw} or "
                       f"{hw + (3,)}, got {checks.show(weights)}")
    wt = wt.astype(np.float64)
    if wt.shape not in (hw, hw + (3,)):
        raise FitError(f"weights has shape {wt.shape}, expected {hw} or {hw + (3,)} "
                       "(scene.height, scene.width[, 3])")
    if not np.all(np.isfinite(wt)):
        raise FitError("weights: contains NaN or Inf; give a pixel weight 0 to drop it")
    if np.any(wt < 0):
        raise FitError(f"weights: contains negative values (lowest {wt.min():g}); weights "
                       "must be >= 0, and 0 drops a pixel")
    return np.broadcast_to(wt[..., None] if wt.ndim == 2 else wt, hw + (3,))

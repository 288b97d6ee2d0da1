"""The environment: radiance seen along directions that leave the scene.

``envmap`` follows Mitsuba 3's ``envmap`` plugin with identity ``to_world``:
a direction v (unit, world) maps to

    u = atan2(v.x, -v.z) / (2 pi)  (mod 1),   v' = acos(v.y) / pi,

and the latitude-longitude image is looked up bilinearly with texel centres
at u = (i + 0.5) / W (wrapping in u) and v' = j / (H - 1) (rows at the
poles), as in Mitsuba's ``envmap.cpp``. The lookup is differentiable in the
direction: the polar angle is taken as atan2(|v_xz|, v.y), which has finite
derivatives where acos does not.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ._math import safe_sqrt, to_device
from .scene import Environment, resolve_path


class EnvData(NamedTuple):
    """Arrays of an environment: ``image`` (H, W, 3) for envmaps else (1, 1, 3)."""

    image: jnp.ndarray
    constant: jnp.ndarray  # (3,) radiance for black/constant


def load_environment(env: Environment, base_dir: str | None = None) -> EnvData:
    """Read the environment's arrays (the envmap EXR through ``fitter.imageio``)."""
    if env.type == "envmap":
        from .imageio import read_image  # OpenImageIO only when an envmap is used

        path = resolve_path(env.file, base_dir)
        img = np.asarray(read_image(path), dtype=np.float64) * env.scale
        return EnvData(to_device(img), to_device(np.zeros(3)))
    rad = np.zeros(3) if env.type == "black" else np.asarray(env.radiance, dtype=np.float64) * env.scale
    return EnvData(to_device(np.zeros((1, 1, 3))), to_device(rad))


def direction_to_uv(v):
    """Mitsuba envmap coordinates (u, v) in [0, 1) x [0, 1] of unit directions (..., 3)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    r2 = x * x + z * z
    off_pole = r2 > 0  # at the poles u is arbitrary; atan2(0, 0) has a NaN gradient
    u = jnp.arctan2(jnp.where(off_pole, x, 0.0), jnp.where(off_pole, -z, 1.0)) / (2.0 * jnp.pi)
    u = u - jnp.floor(u)
    theta = jnp.arctan2(safe_sqrt(r2), y)
    return u, theta / jnp.pi


def lookup(env_type: str, data: EnvData, dirs):
    """Radiance (..., 3) arriving from directions ``dirs`` (..., 3)."""
    if env_type != "envmap":
        return jnp.broadcast_to(data.constant, dirs.shape)
    img = data.image
    h, w = img.shape[0], img.shape[1]
    u, v = direction_to_uv(dirs)
    fx = u * w - 0.5
    fy = v * (h - 1)
    x0 = jnp.floor(fx)
    y0 = jnp.clip(jnp.floor(fy), 0, h - 2)
    wx = (fx - x0)[..., None]
    wy = (fy - y0)[..., None]
    x0i = x0.astype(jnp.int32) % w
    x1i = (x0i + 1) % w
    y0i = y0.astype(jnp.int32)
    y1i = y0i + 1
    top = img[y0i, x0i] * (1 - wx) + img[y0i, x1i] * wx
    bot = img[y1i, x0i] * (1 - wx) + img[y1i, x1i] * wx
    return top * (1 - wy) + bot * wy

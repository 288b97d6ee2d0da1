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

import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._keep import recent
from ._math import safe_sqrt, to_device
from .scene import Environment, resolve_path


#: Smallest envmap (width, height) Mitsuba 3's ``envmap`` accepts (``envmap.cpp``): its
#: rows run pole to pole, so a 2-row map holds only the poles (Mitsuba 3.9 renders one
#: unlike this lookup: a 4 x 2 map's background 0.1 off on average, the sphere 64 %).
MIN_ENVMAP = (2, 3)


class EnvData(NamedTuple):
    """Arrays of an environment: ``image`` (H, W, 3) for envmaps else (1, 1, 3)."""

    image: jnp.ndarray
    constant: jnp.ndarray  # (3,) radiance for black/constant


def load_environment(env: Environment, base_dir: str | None = None) -> EnvData:
    """Read the environment's arrays (the envmap EXR through ``fitter.imageio``,
    once per version of the file: ``_read_envmap``)."""
    if env.type == "envmap":
        path = resolve_path(env.file, base_dir)
        try:
            st = os.stat(path)
            stamp = (st.st_mtime_ns, st.st_size)
        except OSError:
            stamp = None  # (read_image names the problem)
        return _read_envmap(path, float(env.scale), stamp)
    rad = (np.zeros(3) if env.type == "black"
           else np.asarray(env.radiance, dtype=np.float64) * env.scale)
    return EnvData(to_device(np.zeros((1, 1, 3))), to_device(rad))


@recent(max_items=2, max_bytes=2**30)
def _read_envmap(path: str, scale: float, stamp) -> EnvData:
    """An envmap's arrays; ``stamp`` (the file's mtime and size) keys the cache: a fit
    asks for them ~6 times, and a 8192-wide map took ~1.7 s a read."""
    # (OpenImageIO only for an envmap)
    from .imageio import ImageError, check_radiance, read_image

    img = np.asarray(read_image(path), dtype=np.float64)
    # (a NaN texel reached every render through the sky's pyramid: a traceback in the fit)
    where = f"{path} (scene.environment.file)"
    check_radiance(img, where, "an envmap")
    h, w = img.shape[:2]
    if w < MIN_ENVMAP[0] or h < MIN_ENVMAP[1]:
        raise ImageError(f"{where}: {w}x{h} pixels; an envmap needs at least "
                         f"{MIN_ENVMAP[0]}x{MIN_ENVMAP[1]} (Mitsuba's envmap: rows from pole "
                         "to pole)")
    return EnvData(to_device(img * scale), to_device(np.zeros(3)))


def _uv_and_polar(v):
    """(u, v', off_pole, rho) of unit directions (..., 3): Mitsuba's envmap
    coordinates, where u is defined (not at a pole) and rho = |v_xz|."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    r2 = x * x + z * z
    off_pole = r2 > 0  # at the poles u is arbitrary; atan2(0, 0) has a NaN gradient
    u = jnp.arctan2(jnp.where(off_pole, x, 0.0), jnp.where(off_pole, -z, 1.0)) / (2.0 * jnp.pi)
    u = u - jnp.floor(u)
    rho = safe_sqrt(r2)
    return u, jnp.arctan2(rho, y) / jnp.pi, off_pole, rho


def direction_to_uv(v):
    """Mitsuba envmap coordinates (u, v) in [0, 1) x [0, 1] of unit directions (..., 3)."""
    u, vv, _, _ = _uv_and_polar(v)
    return u, vv


def _bilinear(img, u, v):
    """Bilinear lookup of ``img`` (H, W, 3) at (u, v) and the local slopes
    (d value / du, d value / dv), each (..., 3)."""
    h, w = img.shape[0], img.shape[1]
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
    a, b = img[y0i, x0i], img[y0i, x1i]
    c, d = img[y1i, x0i], img[y1i, x1i]
    top = a + (b - a) * wx
    bot = c + (d - c) * wx
    value = top + (bot - top) * wy
    d_u = ((b - a) + ((d - c) - (b - a)) * wy) * w
    d_v = (bot - top) * (h - 1)
    return value, d_u, d_v


@jax.custom_jvp
def _envmap(img, dirs):
    u, v, _, _ = _uv_and_polar(dirs)
    return _bilinear(img, u, v)[0]


@_envmap.defjvp
def _envmap_jvp(primals, tangents):
    """Derivative in the direction by hand (autodiff of the lookup compiled
    ~2.5x slower, measured): the bilinear slopes times du = (x dz - z dx) /
    (2 pi rho^2) of u = atan2(x, -z) / 2 pi and dv' = (y drho - rho dy) / pi
    of v' = atan2(rho, y) / pi, rho = |v_xz|; du = 0 at the poles (u is
    undefined there). The image is data: its tangent is ignored.
    ``tests/test_dielectric_fit.py`` checks it against central differences."""
    img, dirs = primals
    _, ddirs = tangents
    u, v, off_pole, rho = _uv_and_polar(dirs)
    value, d_u, d_v = _bilinear(img, u, v)
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    dx, dy, dz = ddirs[..., 0], ddirs[..., 1], ddirs[..., 2]
    r2 = jnp.where(off_pole, rho * rho, 1.0)
    du = jnp.where(off_pole, (x * dz - z * dx) / r2, 0.0) / (2.0 * jnp.pi)
    drho = jnp.where(off_pole, (x * dx + z * dz) / jnp.where(off_pole, rho, 1.0), 0.0)
    dv = (y * drho - rho * dy) / (rho * rho + y * y) / jnp.pi
    return value, d_u * du[..., None] + d_v * dv[..., None]


def lookup(env_type: str, data: EnvData, dirs):
    """Radiance (..., 3) arriving from directions ``dirs`` (..., 3)."""
    if env_type != "envmap":
        return jnp.broadcast_to(data.constant, dirs.shape)
    return _envmap(data.image, dirs)

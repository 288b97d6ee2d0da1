"""The forward model's own discretisation error, propagated into the parameters.

The model integrates each pixel with k x k sub-pixel samples and, for an
environment lighting opaque lobes, the map as sun cells and a sky stencil
(``fitter.envlight``). A fit matches *that* image to the target, so the
model's discretisation error is an error of the parameters the residual does
not show (it is absorbed). "k vs 2k": at the fitted parameters, render once
with the discretisation refined -- 2k x 2k samples per pixel, sun cells of a
quarter texel instead of a half (``FINER_SUN``) -- and take the difference
d = finer - fitted over the fitted pixels. Through the fit's linearisation,

    delta_z = (J^T W J)^-1 J^T W d

is how far the parameters would move were the model the finer one; its outer
product is added to the systematic covariance (a bias stated as an error).
Cost: one render of the fitted pixels at the finer setting and one J^T d
with the Jacobian the systematic part already computed. The sky stencil (the
smooth rest of an environment) is not refined: its pixel-centre samples and
ring cells are the same in both, so its error is not in delta_z.
"""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np

from ..environment import load_environment
from ..geometry import build_geometry
from ..material import Material
from ..render import render_active
from ..scene import DirectionalLight

#: The finer model's sub-pixel samples per axis: 2k, at most this.
MAX_SUPERSAMPLING = 16
#: The finer model's film samples (H W k'^2) are kept under this many (its
#: camera rays are traced for the whole image): k' = 2k up to 256^2 x 8^2,
#: less beyond (k + 1 at the least).
MAX_SAMPLES = 2**23
#: Lights (scene lights and sun cells) are rendered in groups of at most this
#: many light x pixel x sample terms (each ~80 bytes in the geometry):
#: the quarter-texel sun of the shipped probe is 128 lights.
MAX_LIGHT_SAMPLES = 2**23
#: Sun cells of the finer environment: a quarter texel (``envlight.SUN_CELL``
#: is a half), integrated with twice the sub-samples. Measured on the probe:
#: Phong e = 300's exponent 3.2 % low with whole-texel cells, 0.6 % with half,
#: 0.3 % with quarter (``envlight``'s notes).
FINER_SUN = {"SUN_CELL": 4, "SUN_SUB": 16}

_LOCK = threading.Lock()


def finer_supersampling(scene) -> int:
    """k' of the finer model: 2k, within ``MAX_SUPERSAMPLING`` and ``MAX_SAMPLES``."""
    k = scene.supersampling
    cap = int(np.sqrt(MAX_SAMPLES / max(scene.width * scene.height, 1)))
    return max(min(2 * k, MAX_SUPERSAMPLING, cap), k + 1)


def finer_sun(scene, base_dir):
    """(directions (Ls, 3) towards, irradiances (Ls, 3)) of the environment's sun
    cells at ``FINER_SUN`` (``envlight``'s module constants, set and restored
    under a lock: the library's own cached renderers are never built in here)."""
    from .. import envlight

    env64 = load_environment(scene.environment, base_dir)
    with _LOCK:
        saved = {k: getattr(envlight, k) for k in FINER_SUN if hasattr(envlight, k)}
        try:
            for k in saved:
                setattr(envlight, k, FINER_SUN[k])
            lights = envlight.env_lights(scene.environment.type, np.asarray(env64.image),
                                         np.asarray(env64.constant))
        finally:
            for k, v in saved.items():
                setattr(envlight, k, v)
    if lights is None:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.asarray(lights.sun_dir), np.asarray(lights.sun_irradiance)


def _lights_of(scene, material, base_dir):
    """Every light of the finer model as a scene light: the scene's own and,
    under an environment lighting opaque lobes, its sun cells as directional lights."""
    lights = tuple(scene.lights)
    if any(lb.kind == "brdf" for lb in material.lobe_objects) \
            and scene.environment.type != "black":
        dirs, irr = finer_sun(scene, base_dir)
        lights += tuple(DirectionalLight(tuple(float(x) for x in -d), tuple(float(x) for x in e))
                        for d, e in zip(dirs, irr))
    return lights


def _cast(a):
    return jnp.asarray(a, dtype=jnp.float64) if np.asarray(a).dtype.kind == "f" \
        else jnp.asarray(a)


def finer_values(problem, params) -> tuple[np.ndarray, np.ndarray]:
    """Values of the fitted pixels by the finer model, sky term excluded.

    Returns (values (P, 3), covered (P,) bool): a fitted pixel none of whose
    finer samples hits the sphere is not covered. ``params``: complete
    parameters in user units. The sky stencil (``envlight.sky_stencil``, the
    smooth part of an environment) is not refined: compare with
    ``coarse_without_sky``.
    """
    r = problem.renderer
    scene, material = r.scene, r.material
    base_dir = getattr(problem, "base_dir", None)
    fine = scene.replace(supersampling=finer_supersampling(scene))
    lights = _lights_of(scene, material, base_dir)
    env = jax.tree_util.tree_map(_cast, load_environment(scene.environment, base_dir))
    sphere = (jnp.asarray(scene.sphere.center, jnp.float64),
              jnp.asarray(scene.sphere.radius, jnp.float64))
    p64 = {k: jnp.asarray(v, jnp.float64) for k, v in params.items()}
    opaque = [lb.name for lb in material.lobe_objects if lb.kind == "brdf"]
    brdf_only = Material.make(opaque, {k: v for k, v in material.options
                                       if k.split(".")[0] in opaque}) if opaque else None
    flat = np.asarray(r.pixel_index)[problem.rows]
    n_pix = max(int(flat.size), 1)
    size = max(MAX_LIGHT_SAMPLES // (n_pix * fine.supersampling**2), 1)
    groups = [lights[i:i + size] for i in range(0, len(lights), size)] or [()]
    vals, covered = np.zeros((flat.size, 3)), None
    for g, group in enumerate(groups):
        # The first group carries the specular lobes and the background; the
        # others add their lights' opaque lobes only (linearity).
        mat = material if g == 0 else brdf_only
        if len(group) < size and g > 0:  # pad: one compile for every group
            group = group + (DirectionalLight((0.0, 0.0, -1.0), (0.0, 0.0, 0.0)),) * (
                size - len(group))
        geo = build_geometry(fine.replace(lights=group), scene.environment.type,
                             load_environment(scene.environment, base_dir), None)
        index = np.asarray(geo.pixel_index)
        pos = np.clip(np.searchsorted(index, flat), 0, index.size - 1)
        hit = index[pos] == flat
        covered = hit if covered is None else covered & hit
        sub = jax.tree_util.tree_map(_cast, geo.subset(pos[hit])._replace(
            pixel_index=None, background_image=None))
        del geo
        out = np.zeros((flat.size, 3))
        keys = mat.param_specs()
        out[hit] = np.asarray(render_active({k: v for k, v in p64.items() if k in keys}, sub,
                                            env, sphere, material=mat,
                                            env_type=r.env_type), dtype=np.float64)
        vals += out
    return vals, covered


def coarse_without_sky(data, params, material, env_type, model) -> np.ndarray:
    """The fitted model's values (P, 3) without its sky term: ``model`` itself
    when the environment lights no opaque lobe."""
    geo = data.geometry
    if not (geo.env_color.shape[0] and geo.env_color.shape[1]):
        return np.asarray(model, dtype=np.float64)
    empty = jnp.zeros((0, 0, 3), dtype=geo.env_color.dtype)
    return np.asarray(render_active(
        {k: jnp.asarray(v, data.target.dtype) for k, v in params.items()},
        geo._replace(env_color=empty), data.env, data.sphere, material=material,
        env_type=env_type), dtype=np.float64)


def shift(J, d) -> np.ndarray:
    """delta_z (n,) = (J^T J)^-1 J^T d: the parameter shift a residual change
    ``d`` (N,) makes through the linearisation ``J`` (N, n) (both weighted)."""
    J = np.asarray(J, dtype=np.float64)
    return np.linalg.lstsq(J, np.asarray(d, dtype=np.float64), rcond=None)[0]

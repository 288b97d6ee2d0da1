"""The forward model's own discretisation error, propagated into the parameters.

The model integrates each pixel with k x k sub-pixel samples and, for an
environment lighting opaque lobes, the map as sun cells and a sky stencil
(``fitter.envlight``). A fit matches *that* image to the target, so the
model's discretisation error is an error of the parameters the residual does
not show (it is absorbed). "k vs 2k": at the fitted parameters, render once
with the discretisation refined -- 2k x 2k samples per pixel, sun cells of a
quarter texel instead of a half (``FINER_SUN``), a dielectric's internal
bounces doubled (``finer_material``) -- and take the difference
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

import functools
import threading

import jax
import jax.numpy as jnp
import numpy as np

from ..bsdf.base import Cosines, cosines
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
#: many light x pixel x sample terms (~15 float64 temporaries each, in one
#: jitted call): the quarter-texel sun of the shipped probe is 128 lights.
MAX_LIGHT_SAMPLES = 2**22
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
    """Every light of the finer model as (anchor (L, 3), is_point (L,), colour (L, 3)):
    a point light's position, or a distant light's travel direction; the
    scene's lights and, under an environment lighting opaque lobes, its sun
    cells at ``FINER_SUN``."""
    anchor, point, color = [], [], []
    for light in scene.lights:
        if isinstance(light, DirectionalLight):
            anchor.append(light.direction)
            point.append(False)
            color.append(light.irradiance)
        else:
            anchor.append(light.position)
            point.append(True)
            color.append(light.intensity)
    if any(lb.kind == "brdf" for lb in material.lobe_objects) \
            and scene.environment.type != "black":
        dirs, irr = finer_sun(scene, base_dir)
        anchor += list(-dirs)
        point += [False] * len(dirs)
        color += list(irr)
    return (np.asarray(anchor, dtype=np.float64).reshape(-1, 3), np.asarray(point, dtype=bool),
            np.asarray(color, dtype=np.float64).reshape(-1, 3))


def finer_material(material):
    """The material with every lobe's integer ``bounces`` option (a dielectric's
    internal reflections) doubled, within its ``most``."""
    opts = dict(material.options)
    for lb in material.lobe_objects:
        for opt in lb.options:
            if opt.name == "bounces" and opt.choices is None:
                key = f"{lb.name}.{opt.name}"
                more = 2 * int(opts.get(key, opt.default))
                opts[key] = more if opt.most is None else min(more, opt.most)
    return Material.make(material.lobes, opts)


def _cast(a):
    return jnp.asarray(a, dtype=jnp.float64) if np.asarray(a).dtype.kind == "f" \
        else jnp.asarray(a)


@functools.partial(jax.jit, static_argnames=("material", "env_type"))
def _lit_value(params, geo, env, sphere, anchor, point, color, *, material, env_type):
    """Values (P, 3) of the opaque lobes under lights (anchor, point, color),
    the light terms computed here in JAX (as ``geometry.build_geometry`` does
    in NumPy: light direction and fall-off, cosines, lit samples)."""
    pos, n, view = geo.position[None], geo.normal[None], -geo.ray_dir[None]
    to = jnp.where(point[:, None, None, None], anchor[:, None, None, :] - pos,
                   -anchor[:, None, None, :] + 0.0 * pos)
    r2 = jnp.sum(to * to, axis=-1)
    wi = to / jnp.sqrt(r2)[..., None]
    falloff = jnp.where(point[:, None, None], 1.0 / r2, 1.0)
    cos = cosines(jnp.broadcast_to(n, wi.shape), wi, jnp.broadcast_to(view, wi.shape))
    lit = geo.hit[None] & (cos.cos_i > 0) & (cos.cos_o > 0)
    stand_in = Cosines(1.0, 1.0, 1.0, 1.0, 1.0, 0.0)
    cos = Cosines(*(jnp.where(lit, a, s) for a, s in zip(cos, stand_in)))
    weight = jnp.where(lit, geo.sample_weight * cos.cos_i * falloff, 0.0)
    geo = geo._replace(cosines=cos, light_weight=weight, light_color=color,
                       background=jnp.zeros_like(geo.background))
    return render_active(params, geo, env, sphere, material=material, env_type=env_type)


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
    fine = scene.replace(supersampling=finer_supersampling(scene), lights=())
    env64 = load_environment(scene.environment, base_dir)
    geo = build_geometry(fine, scene.environment.type, env64, None)  # rays, hits, background
    flat = np.asarray(r.pixel_index)[problem.rows]
    index = np.asarray(geo.pixel_index)
    pos = np.clip(np.searchsorted(index, flat), 0, index.size - 1)
    covered = index[pos] == flat
    sub = jax.tree_util.tree_map(_cast, geo.subset(pos[covered])._replace(
        pixel_index=None, background_image=None))
    del geo
    env = jax.tree_util.tree_map(_cast, env64)
    sphere = (jnp.asarray(scene.sphere.center, jnp.float64),
              jnp.asarray(scene.sphere.radius, jnp.float64))
    p64 = {k: jnp.asarray(v, jnp.float64) for k, v in params.items()}
    # No lights: the specular lobes (more bounces) and the background.
    vals = np.asarray(render_active(p64, sub, env, sphere, material=finer_material(material),
                                    env_type=r.env_type), dtype=np.float64)
    anchor, point, color = _lights_of(scene, material, base_dir)
    opaque = [lb.name for lb in material.lobe_objects if lb.kind == "brdf"]
    if opaque and len(anchor):
        brdf = Material.make(opaque, {k: v for k, v in material.options
                                      if k.split(".")[0] in opaque})
        keys = brdf.param_specs()
        pb = {k: v for k, v in p64.items() if k in keys}
        size = max(MAX_LIGHT_SAMPLES // (max(int(covered.sum()), 1) * fine.supersampling**2), 1)
        size = min(size, len(anchor))
        pad = -len(anchor) % size  # zero lights: one compile for every group
        anchor = np.concatenate([anchor, np.tile([[0.0, 0.0, -1.0]], (pad, 1))])
        point = np.concatenate([point, np.zeros(pad, bool)])
        color = np.concatenate([color, np.zeros((pad, 3))])
        for lo in range(0, len(anchor), size):
            sl = slice(lo, lo + size)
            vals = vals + np.asarray(_lit_value(
                pb, sub, env, sphere, jnp.asarray(anchor[sl]), jnp.asarray(point[sl]),
                jnp.asarray(color[sl]), material=brdf, env_type=r.env_type), dtype=np.float64)
    out = np.zeros((flat.size, 3))
    out[covered] = vals
    return out, covered


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

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
smooth rest of an environment) is not refined; its measured accuracy
(``SKY_STENCIL_ACCURACY`` of the non-Lambert lobes' sky term) is propagated
the same way instead.
"""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np

from ..bsdf.base import Cosines
from ..camera import camera_frame, pixel_rule
from ..environment import load_environment, lookup
from ..geometry import Geometry, intersect_sphere
from ..material import Material
from ..render import render_active
from ..scene import DirectionalLight

#: The finer model's sub-pixel samples per axis: 2k, at most this.
MAX_SUPERSAMPLING = 16
#: The finer model's film samples (H W k'^2) are kept under this many:
#: k' = 2k up to 256^2 x 8^2, less beyond (k + 1 at the least).
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

#: The sky stencil is not refined (its cells and pixel-centre samples cost
#: ~0.46 MB a pixel): its measured accuracy is stated instead, as that
#: relative error of the non-Lambert lobes' sky term, by viewing angle
#: theta_o (degrees): against a brute-force hemisphere quadrature Beckmann
#: m = 0.1 is within 0.7 % up to 84 degrees, -3 % at 87, -17 % at 89
#: (``envlight``'s notes, ``tests/test_envlight_reference.py``; m = 0.25:
#: 0.4 %, Phong e = 300: 0.2 %, so m = 0.1's figures bound the shipped
#: lobes'), and against Mitsuba the outermost 5 % of the radius (theta_o >
#: 72 degrees; limb pixels, 4 x 4 env samples) is 2 % low (README,
#: ``geometry.ENV_LIMB_COS``).
SKY_STENCIL_ACCURACY = ((0.0, 70.0, 74.0, 87.0, 89.0, 90.0),
                        (0.007, 0.007, 0.02, 0.03, 0.17, 0.17))

#: Body pixels (away from highlights and the rim: a smooth model error) the
#: finer model renders: every this many-th, each standing for this many.
BODY_STRIDE = 4

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


def _cosines(n, wi, wo) -> Cosines:
    """``bsdf.base.cosines`` with the cross product written out per component
    (jnp.cross on broadcast (L, P, K, 3) arrays ran ~20x slower on CPU)."""
    dot = lambda a, b: a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]  # noqa: E731
    ci, co = dot(n, wi), dot(n, wo)
    h = wi + wo
    hh, nh = dot(h, h), dot(n, h)
    up = (nh > 0) & (hh > 0)
    inv = jnp.where(up, 1.0 / jnp.sqrt(jnp.where(up, hh, 1.0)), 0.0)
    c0 = n[..., 1] * h[..., 2] - n[..., 2] * h[..., 1]
    c1 = n[..., 2] * h[..., 0] - n[..., 0] * h[..., 2]
    c2 = n[..., 0] * h[..., 1] - n[..., 1] * h[..., 0]
    tan2 = jnp.where(up, (c0 * c0 + c1 * c1 + c2 * c2) / jnp.where(up, nh * nh, 1.0), 0.0)
    return Cosines(ci, co, dot(wi, wo), nh * inv, dot(wo, h) * inv, tan2)


@jax.jit
def _light_terms(geo, anchor, point, color):
    """``geo`` with the lights (anchor, point, color) tabulated, in JAX, as
    ``geometry.build_geometry`` does in NumPy: light direction and fall-off,
    cosines, lit samples. A jitted call of its own, so the renderer reads the
    cosines from memory (fused into it, XLA recomputed them: 10x slower)."""
    pos, n, view = geo.position[None], geo.normal[None], -geo.ray_dir[None]
    to = jnp.where(point[:, None, None, None], anchor[:, None, None, :] - pos,
                   -anchor[:, None, None, :] + 0.0 * pos)
    r2 = jnp.sum(to * to, axis=-1)
    wi = to / jnp.sqrt(r2)[..., None]
    falloff = jnp.where(point[:, None, None], 1.0 / r2, 1.0)
    cos = _cosines(n, wi, view)
    lit = geo.hit[None] & (cos.cos_i > 0) & (cos.cos_o > 0)
    stand_in = Cosines(1.0, 1.0, 1.0, 1.0, 1.0, 0.0)
    cos = Cosines(*(jnp.where(lit, a, s) for a, s in zip(cos, stand_in)))
    weight = jnp.where(lit, geo.sample_weight * cos.cos_i * falloff, 0.0)
    return geo._replace(cosines=cos, light_weight=weight, light_color=color,
                        background=jnp.zeros_like(geo.background))


def _fine_geometry(scene, rows_flat, env_type, env):
    """``Geometry`` of the pixels ``rows_flat`` (flat indices) with ``scene``'s
    sub-pixel samples and no lights: the camera rays of those pixels alone
    (``camera.camera_rays`` traces the whole image), as
    ``geometry.build_geometry`` traces them."""
    k, w, h = scene.supersampling, scene.width, scene.height
    sub, wt = pixel_rule(k, scene.pixel_rule)
    row, col = np.divmod(np.asarray(rows_flat, dtype=np.int64), w)
    sx = np.broadcast_to(col[:, None, None] + sub[None, None, :], (row.size, k, k))
    sy = np.broadcast_to(row[:, None, None] + sub[None, :, None], (row.size, k, k))
    x = (2.0 * sx / w - 1.0).reshape(row.size, k * k)
    y = ((1.0 - 2.0 * sy / h) * (h / w)).reshape(row.size, k * k)
    cam = scene.camera
    fwd, right, up = camera_frame(scene)
    origin = np.asarray(cam.origin, dtype=np.float64)
    if cam.type == "perspective":
        t = np.tan(np.radians(cam.fov) / 2.0)
        d = fwd + (t * x)[..., None] * right + (t * y)[..., None] * up
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(origin, d.shape)
    else:
        hw = cam.half_width
        o = origin + (hw * x)[..., None] * right + (hw * y)[..., None] * up
        d = np.broadcast_to(fwd, o.shape)
    sph = scene.sphere
    t = intersect_sphere(o, d, sph.center, sph.radius)
    hit = np.isfinite(t)
    pos = o + np.where(hit, t, 0.0)[..., None] * d
    normal = (pos - np.asarray(sph.center)) / sph.radius
    normal = np.where(hit[..., None], normal, -d)
    pos = np.where(hit[..., None], pos, np.asarray(sph.center) + sph.radius * normal)
    weight = (wt[:, None] * wt[None, :]).reshape(k * k)
    miss = np.asarray(lookup(env_type, env, jnp.asarray(d)))
    background = np.einsum("pkc,k->pc", np.where(hit[..., None], 0.0, miss), weight)
    p, kk = hit.shape
    none = Cosines(*(np.zeros((0, p, kk)) for _ in Cosines._fields))
    return Geometry(pixel_index=None, hit=hit, sample_weight=weight, position=pos,
                    normal=normal, ray_dir=d, cosines=none, light_weight=np.zeros((0, p, kk)),
                    light_color=np.zeros((0, 3)), background=background,
                    background_image=None, env_index=np.zeros((0,), np.int64),
                    env_cosines=Cosines(*(np.zeros((0, 0)) for _ in Cosines._fields)),
                    env_color=np.zeros((0, 0, 3)))


def sample_rows(labels) -> tuple[np.ndarray, np.ndarray]:
    """(rows (M,) of the fitted pixels the finer model renders, their weights (M,)):
    every highlight and rim pixel (``_adequacy.pixel_regions`` 1, 2: where the
    discretisation error sits), every ``BODY_STRIDE``-th body pixel, weighted
    by the body's pixels per pick so J^T d stays an estimate of the whole sum."""
    labels = np.asarray(labels)
    body = np.nonzero(labels == 0)[0]
    picked = body[::BODY_STRIDE]
    rows = np.sort(np.concatenate([np.nonzero(labels != 0)[0], picked]))
    weight = np.where(labels[rows] == 0, body.size / max(picked.size, 1), 1.0)
    return rows, weight


def finer_values(problem, params, rows=None) -> tuple[np.ndarray, np.ndarray]:
    """Values of the fitted pixels by the finer model, sky term excluded.

    Returns (values (P, 3), coverage (P,)): coverage is the share of the
    pixel the finer samples see on the sphere (the sky term scales with it). ``params``: complete
    parameters in user units; ``rows``: which fitted pixels (default all). The sky stencil (``envlight.sky_stencil``, the
    smooth part of an environment) is not refined: compare with
    ``coarse_without_sky``.
    """
    r = problem.renderer
    scene, material = r.scene, r.material
    base_dir = getattr(problem, "base_dir", None)
    fine = scene.replace(supersampling=finer_supersampling(scene))
    env = jax.tree_util.tree_map(_cast, load_environment(scene.environment, base_dir))
    flat = np.asarray(r.pixel_index)[problem.rows]
    if rows is not None:
        flat = flat[rows]
    geo = _fine_geometry(fine, flat, scene.environment.type, env)
    covered = np.asarray(geo.hit).any(axis=1)
    sub = jax.tree_util.tree_map(_cast, geo)
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
        size = max(MAX_LIGHT_SAMPLES // (max(flat.size, 1) * fine.supersampling**2), 1)
        size = min(size, len(anchor))
        pad = -len(anchor) % size  # zero lights: one compile for every group
        anchor = np.concatenate([anchor, np.tile([[0.0, 0.0, -1.0]], (pad, 1))])
        point = np.concatenate([point, np.zeros(pad, bool)])
        color = np.concatenate([color, np.zeros((pad, 3))])
        for lo in range(0, len(anchor), size):
            sl = slice(lo, lo + size)
            lit = _light_terms(sub, jnp.asarray(anchor[sl]), jnp.asarray(point[sl]),
                               jnp.asarray(color[sl]))
            vals = vals + np.asarray(render_active(pb, lit, env, sphere, material=brdf,
                                                   env_type=r.env_type), dtype=np.float64)
    coverage = np.asarray(geo.hit, dtype=np.float64) @ np.asarray(geo.sample_weight)
    return np.where(covered[:, None], vals, 0.0), coverage


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


def sky_quadrature(data, params, material, env_type, model, without_sky) -> np.ndarray:
    """A stated bound of the sky stencil's error (P, 3): ``SKY_STENCIL_ACCURACY``
    at the pixel's viewing angle times the sky term of the opaque lobes other than Lambert (Lambert's is
    exact, rho/pi x irradiance); zeros when the environment lights no opaque lobe.

    ``model``, ``without_sky``: the fitted values with and without the sky
    term (``coarse_without_sky``).
    """
    sky = np.asarray(model, dtype=np.float64) - without_sky
    geo = data.geometry
    if not (geo.env_color.shape[0] and geo.env_color.shape[1]):
        return np.zeros_like(sky)
    if "lambert" in material.lobes:
        lam = Material.make(["lambert"])
        p, k = geo.hit.shape
        dark = geo._replace(  # no lights, no background: Lambert's sky term alone
            cosines=Cosines(*(jnp.zeros((0, p, k), geo.normal.dtype) for _ in Cosines._fields)),
            light_weight=jnp.zeros((0, p, k), geo.normal.dtype),
            light_color=jnp.zeros((0, 3), geo.normal.dtype),
            background=jnp.zeros_like(geo.background))
        sky = sky - np.asarray(render_active(
            {"lambert.rho_d": jnp.asarray(params["lambert.rho_d"], data.target.dtype)}, dark,
            data.env, data.sphere, material=lam, env_type=env_type), dtype=np.float64)
    n, d = np.asarray(geo.normal), np.asarray(geo.ray_dir)
    cos_o = np.clip(-np.sum(n * d, -1), 0.0, 1.0) @ np.asarray(geo.sample_weight)
    theta = np.degrees(np.arccos(np.clip(cos_o, 0.0, 1.0)))
    return np.interp(theta, *SKY_STENCIL_ACCURACY)[:, None] * sky


def shift(J, d) -> np.ndarray:
    """delta_z (n,) = (J^T J)^-1 J^T d: the parameter shift a residual change
    ``d`` (N,) makes through the linearisation ``J`` (N, n) (both weighted)."""
    J = np.asarray(J, dtype=np.float64)
    return np.linalg.lstsq(J, np.asarray(d, dtype=np.float64), rcond=None)[0]

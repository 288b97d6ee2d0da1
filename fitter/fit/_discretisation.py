"""The forward model's own discretisation error, propagated into the parameters.

The model integrates each pixel with k x k sub-pixel samples and, for an
environment lighting opaque lobes, the map as sun cells and a sky stencil
(``fitter.envlight``). A fit matches *that* image to the target, so the
model's discretisation error is an error of the parameters the residual does
not show (it is absorbed). "k vs 2k": at the fitted parameters, render once
with every discretisation refined through the public knobs -- 2k x 2k
samples per pixel, the sky term at ``envlight.Detail.finer()`` (193 theta_o
nodes, 4 x 8 lobe points per cell), sun cells of a quarter texel
(``FINER_SUN``), a dielectric's internal bounces doubled
(``finer_material``) -- with ``geometry.build_geometry``, and take the
difference d = finer - fitted over the fitted pixels. Through the fit's
linearisation,

    delta_z = (J^T W J)^-1 J^T W d

is how far the parameters would move were the model the finer one; its outer
product is added to the systematic covariance (a bias stated as an error).
The sky stencil's cells themselves (``fitter.skystencil``) are the same in
both models; their measured accuracy (``SKY_STENCIL_ACCURACY``) times the
non-Lambert lobes' sky term is propagated the same way.
Cost: one finer geometry of the scene, one render of the sampled fitted
pixels and one of their sky term, two J^T d with the Jacobian the systematic
part already computed (``benchmarks/discretisation_cost.py``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import envlight
from ..environment import load_environment
from ..geometry import build_geometry
from ..material import EXPOSURE_KEY, Material
from ..render import render_active

#: The finer model's sub-pixel samples per axis: 2k, at most this.
MAX_SUPERSAMPLING = 16
#: The finer model's film samples (H W k'^2) are kept under this many:
#: k' = 2k up to 256^2 x 8^2, less beyond (k + 1 at the least).
MAX_SAMPLES = 2**23
#: Sun cells of the finer environment (``envlight.split_sun``'s cell, sub): a
#: quarter texel (the default is a half), twice the sub-samples. Measured on
#: the probe: Phong e = 300's exponent 3.2 % low with whole-texel cells,
#: 0.6 % with half, 0.3 % with quarter (``envlight``'s notes).
FINER_SUN = (4, 16)
#: What the finer render does not refine: the sky stencil's cells (the same
#: in both models). Their measured accuracy, stated as that relative error of
#: the non-Lambert lobes' sky term (Lambert's is exact, rho/pi x irradiance):
#: against a brute-force hemisphere quadrature Beckmann m = 0.1 (the
#: narrowest shipped lobe's bound) is within 0.33 % up to 89.5 degrees
#: (``tests/test_envlight_reference.py`` asserts 0.5 %), against Mitsuba at
#: 4096 spp Torrance-Sparrow m = 0.1 relative RMSE 0.62 % over a 0.38 %
#: noise floor, limb pixels +0.03 % (benchmarks/README.md, envlight). The
#: default's whole error, so an upper bound of the cells' share.
SKY_STENCIL_ACCURACY = 0.005

#: Body pixels (away from highlights and the rim: a smooth model error) the
#: finer model renders: every this many-th, each standing for this many.
BODY_STRIDE = 4


def finer_supersampling(scene) -> int:
    """k' of the finer model: 2k, within ``MAX_SUPERSAMPLING`` and ``MAX_SAMPLES``."""
    k = scene.supersampling
    cap = int(np.sqrt(MAX_SAMPLES / max(scene.width * scene.height, 1)))
    return max(min(2 * k, MAX_SUPERSAMPLING, cap), k + 1)


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
    return Material.make(material.lobes, opts, exposure=material.exposure)


def _cast(a):
    return jnp.asarray(a, dtype=jnp.float64) if np.asarray(a).dtype.kind == "f" \
        else jnp.asarray(a)


def finer_geometry(scene, material, base_dir):
    """(Geometry, EnvData) of ``scene`` at the finer discretisation (float64 NumPy)."""
    fine = scene.replace(supersampling=finer_supersampling(scene))
    env64 = load_environment(scene.environment, base_dir)
    lighting = None
    if envlight.lit_by_environment(scene, material):
        lighting = envlight.env_lights(scene.environment.type, np.asarray(env64.image),
                                       np.asarray(env64.constant),
                                       detail=envlight.Detail.finer(), sun=FINER_SUN)
    return build_geometry(fine, scene.environment.type, env64, lighting), env64


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


def finer_values(problem, params, rows=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fitted pixels by the finer model (``finer_geometry``).

    Returns (values (P, 3), coverage (P,), sky (P, 3)): coverage is the share
    of the pixel the finer samples see on the sphere (0: none, the pixel is
    left out); sky the finer model's sky term of the opaque lobes other than
    Lambert (``SKY_STENCIL_ACCURACY`` applies to it). ``params``: complete
    parameters in user units; ``rows``: which fitted pixels (default all).
    """
    r = problem.renderer
    scene, material = r.scene, r.material
    geo, env64 = finer_geometry(scene, material, getattr(problem, "base_dir", None))
    flat = np.asarray(r.pixel_index)[problem.rows]
    if rows is not None:
        flat = flat[rows]
    index = np.asarray(geo.pixel_index)
    at = np.minimum(np.searchsorted(index, flat), max(index.size - 1, 0))
    found = index[at] == flat if index.size else np.zeros(flat.size, bool)
    sub = geo.subset(at[found])
    dev = jax.tree_util.tree_map(_cast, sub)
    env = jax.tree_util.tree_map(_cast, env64)
    sphere = (jnp.asarray(scene.sphere.center, jnp.float64),
              jnp.asarray(scene.sphere.radius, jnp.float64))
    p64 = {k: jnp.asarray(v, jnp.float64) for k, v in params.items()}
    vals = np.zeros((flat.size, 3))
    vals[found] = np.asarray(render_active(p64, dev, env, sphere,
                                           material=finer_material(material),
                                           env_type=r.env_type), dtype=np.float64)
    coverage = np.zeros(flat.size)
    coverage[found] = np.asarray(sub.hit, dtype=np.float64) @ np.asarray(sub.sample_weight)
    sky = np.zeros((flat.size, 3))
    glossy = [lb.name for lb in material.lobe_objects if lb.kind == "brdf" and lb.name != "lambert"]
    if glossy and np.asarray(sub.env_color).size:
        dark = dev._replace(  # no lights, no sun, no background: the sky term alone
            cosines=type(dev.cosines)(*(a[:0] for a in dev.cosines)),
            light_weight=dev.light_weight[:0], light_color=dev.light_color[:0], sun=(),
            background=jnp.zeros_like(dev.background))
        opts = {k: v for k, v in material.options if k.split(".")[0] in glossy}
        sky[found] = np.asarray(render_active(p64, dark, env, sphere,
                                              material=Material.make(glossy, opts),
                                              env_type=r.env_type), dtype=np.float64)
        sky *= float(params.get(EXPOSURE_KEY, 1.0)) if material.exposure else 1.0
    return vals, coverage, sky


def shift(J, d) -> np.ndarray:
    """delta_z (n,) = (J^T J)^-1 J^T d: the parameter shift a residual change
    ``d`` (N,) makes through the linearisation ``J`` (N, n) (both weighted)."""
    J = np.asarray(J, dtype=np.float64)
    return np.linalg.lstsq(J, np.asarray(d, dtype=np.float64), rcond=None)[0]

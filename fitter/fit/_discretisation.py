"""The forward model's own discretisation error, propagated into the parameters.

The model integrates each pixel with k x k sub-pixel samples and, for an
environment lighting opaque lobes, the map as sun cells and a sky stencil
(``fitter.envlight``). A fit matches *that* image to the target, so the
model's discretisation error is an error of the parameters the residual does
not show (it is absorbed). "k vs 2k": at the fitted parameters, render once
with the discretisation refined through the public knobs
(``geometry.build_geometry``, ``envlight.env_lights(sun=...)``) -- 2k x 2k
samples per pixel, a dielectric's internal bounces doubled
(``finer_material``), and, separately (``finer_values``), sun cells of a
quarter texel (``FINER_SUN``) -- and take the difference d = finer - fitted
over the fitted pixels. Through the fit's linearisation,

    delta_z = (J^T W J)^-1 J^T W d

is how far the parameters would move were the model the finer one; its outer
product is added to the systematic covariance (a bias stated as an error).
The sky term (``fitter.skystencil``) is not refined: at 2k its env samples
triple and, at ``envlight.Detail.finer()``, its tabulation doubles (measured
at 128^2 env_plastic: 52 s of a 72 s fit, peak RSS 4.8 GB, against 13 s and
1.3 GB without). Instead, its ring discretisation is compared with a stencil
of half the rings (``ring_error``, Richardson: the difference / 3), and its
measured accuracy (``SKY_STENCIL_ACCURACY``; the parts summed over the map,
``IRRADIANCE_ACCURACY`` and ``KERNEL_ACCURACY``) times the fitted sky term's
parts is propagated the same way, all independent.
Cost: finer geometries, renders of sampled pixels, one solve for every shift
with the Jacobian already made (``benchmarks/discretisation_cost.py``).
"""

from __future__ import annotations

import threading

import jax
import numpy as np

from .. import envlight
from .._keep import hold, nbytes, recent
from .._math import to_device
from ..environment import load_environment
from ..geometry import build_geometry
from ..material import EXPOSURE_KEY, Material
from ..render import KEEP_BYTES
from . import _adequacy, _renders, _sky
from ._problem import user_values

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
#: The fitted model's sun cells (``envlight``'s defaults), as ``_lighting`` takes them.
SUN = (envlight.SUN_CELL, envlight.SUN_SUB)
#: The sky stencil (not refined): its measured accuracy, stated as that relative error of
#: each lobe's sky term it sums: against a brute-force hemisphere quadrature Beckmann m = 0.1 (the
#: narrowest shipped lobe's bound) is within 0.33 % up to 89.5 degrees
#: (``tests/test_envlight_reference.py`` asserts 0.5 %), against Mitsuba at
#: 4096 spp Torrance-Sparrow m = 0.1 relative RMSE 0.62 % over a 0.38 %
#: noise floor, limb pixels +0.03 % (benchmarks/README.md, envlight).
SKY_STENCIL_ACCURACY = 0.005
#: The lobes' uniform parts (Lambert's rho/pi, Oren-Nayar's A rho/pi) times the
#: irradiance summed over the map (``fitter.irradiance``), stated to this relative
#: accuracy: the sum is within 2.8e-4 of a brute-force quadrature (rms 5e-5,
#: ``tests/test_irradiance.py``); against Mitsuba at 4096 spp under the probe
#: Lambert's whole term (its sun cells and pixel sampling too) has a relative RMSE of
#: 0.23 % over a 0.20 % noise floor, mean 0.00 %, limb -0.04 % (benchmarks/README.md,
#: envlight; through the sky stencil it had been 0.41 %, mean -0.12 %).
IRRADIANCE_ACCURACY = 0.001
#: The lobes' kernel parts (Oren-Nayar's B rho/pi x its angular term) summed over the
#: map per env sample (``irradiance.kernel_sums``), stated to this relative accuracy:
#: against a brute-force integral over the probe's sky, a 24^2 sphere's interior
#: pixels, at most 9.0e-3, rms 1.7e-3 (300 random normals and views: 4.5e-3, 6.3e-4).
KERNEL_ACCURACY = 0.01

#: The finer model rendered in float32 (``single``) where every lobe has
#: ``single_precision`` and no environment lights the lobes: its difference
#: from the model, the discretisation error, is ~1e-5-1e-3 of the values, float32's
#: rounding ~1e-7 (256^2 plastic's render 8.1 -> 4.1 ms in a compiled fit: it
#: reads half the bytes). Its parameters' rounding (~3e-8 relative) enters the
#: term as a shift of that size: stated errors within 0.35 % of float64's on
#: the shipped point-lit cases (a J dz correction took 1.5 ms for 0.25 %).
SINGLE = True
#: Body pixels (away from highlights and the rim: a smooth model error) the
#: finer model renders: every this many-th, each standing for this many.
BODY_STRIDE = 4
#: The finer model's film samples (``sample_rows``) near this: 256^2 (0.87 M) has
#: all; 1024^2 (5.4 M) made its NumPy geometry in 12 s of each compiled fit.
MAX_FINER_SAMPLES = 2**20


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


@recent(max_items=8, max_bytes=KEEP_BYTES)
def _lighting(environment, base_dir, kind):
    """``build_geometry``'s ``lighting`` for a finer geometry, or None without one:
    ``kind`` = (cell, sub), the sun's cells at that size and no sky; ``kind`` a
    ``envlight.Detail``, the sky alone on that stencil (``_half_rings``). Once per
    environment (a compiled env_plastic fit made its three every time: 0.06 s)."""
    env64 = load_environment(environment, base_dir)
    image, constant = env64.image, np.asarray(env64.constant)  # (its lights kept with it)
    if isinstance(kind, envlight.Detail):
        lighting = envlight.env_lights(environment.type, image, constant, detail=kind)
        return None if lighting is None else lighting._replace(
            sun_dir=np.zeros((0, 3)), sun_irradiance=np.zeros((0, 3)))
    lighting = envlight.env_lights(environment.type, image, constant, sun=kind)
    return None if lighting is None else lighting._replace(sky=None)


def sample_rows(labels, scene) -> tuple[np.ndarray, np.ndarray]:
    """(rows (M,) of the fitted pixels the finer model renders, their weights (M,)):
    every highlight and rim pixel (``_adequacy.pixel_regions`` 1, 2: where the
    error sits) and ``BODY_STRIDE``-th body pixel, every s-th of each beyond
    ``MAX_FINER_SAMPLES`` (``scene``'s finer samples), each weighted by its
    stratum's pixels per pick so J^T d stays an estimate of the whole sum."""
    labels = np.asarray(labels)
    sharp, body = np.nonzero(labels != 0)[0], np.nonzero(labels == 0)[0]
    n = (sharp.size + body[::BODY_STRIDE].size) * finer_supersampling(scene) ** 2
    s = max(1, int(np.ceil(n / MAX_FINER_SAMPLES)))
    picks = sharp[::s], body[::BODY_STRIDE * s]
    rows = np.sort(np.concatenate(picks))
    weight = np.where(labels[rows] == 0, body.size / max(picks[1].size, 1),
                      sharp.size / max(picks[0].size, 1))
    return rows, weight


#: ``prefetch`` makes the finer geometry ahead only up to this many samples
#: (pixels x k'^2; 2932 x 64 at the quickstart's 128^2): it is held beside the
#: solve's own memory.
PREFETCH_SAMPLES = 2**19
#: The finer geometries being made ahead (one fit's): {key: (thread, [prepared
#: geometry or None, (executable key, executable) or None])}; under ``SKY_TERMS``
#: the executable of ``sky_terms``' render.
_AHEAD: dict = {}
SKY_TERMS = "sky terms"


def _geometry_key(scene, base_dir, env_type, sun_cells, flat, single: bool = False) -> tuple:
    """What a finer geometry depends on (``_GEOMETRIES``, ``_AHEAD``): the scene,
    the folder its files resolve against, the environment's type, the sun's
    cells (False: no sun), the pixels and whether it is kept in float32."""
    return scene, base_dir, env_type, sun_cells, np.asarray(flat, np.int64).tobytes(), single


def _sphere(scene):
    return (np.asarray(scene.sphere.center, np.float64),
            np.asarray(scene.sphere.radius, np.float64))


def _host_params(params) -> dict:
    return {k: np.asarray(v, np.float64) for k, v in params.items()}


def prefetch(problem) -> None:
    """Start making the finer model's geometries of the sampled fitted pixels
    (``finer_values``) and the half-ring one (``ring_error``) on a thread, while
    the solver runs, and compiling the executables that render them and the
    fitted geometry's sky terms (``sky_terms``). They depend on the scene, pixels
    and parameters' shapes, not on the fit. NumPy (0.1 s at the quickstart's
    128^2; env_plastic's two with sun cells 1.9 s) and XLA's compile release the
    interpreter to the solve and the profile. What fails here is done again
    where needed (``_geometry``, ``_renders.render``); ``wait`` joins the thread."""
    r = problem.renderer
    scene = r.scene
    rows, _ = sample_rows(_adequacy.pixel_regions(problem.geometry), scene)
    flat = np.asarray(r.pixel_index)[problem.rows][rows]
    fine = scene.replace(supersampling=finer_supersampling(scene))
    lit = envlight.lit_by_environment(scene, r.material)
    # (scene, ``_lighting``'s kind or None, material, pixels, sky-term render, in
    # float32) of each geometry ``finer_values`` and ``ring_error`` make
    jobs = [(fine, SUN if lit else None, finer_material(r.material), flat, False,
             single(r.material, lit))]
    if lit:
        jobs.append((scene, FINER_SUN, r.material, flat, False, False))
    if flat.size * sum(s.supersampling**2 for s, *_ in jobs) > PREFETCH_SAMPLES:
        return
    stencil = r.material.stencil_lobes
    if lit and flat.size and stencil:
        jobs.append((scene.replace(lights=()), _half_rings(),
                     _sky.lobes_alone(r.material, stencil), flat[::RING_STRIDE], True, False))
    base = problem.base_dir
    keys = [_geometry_key(s, base, r.env_type, cells or False, px, f32)
            for s, cells, _, px, _, f32 in jobs]
    if keys[0] in _GEOMETRIES:  # a refit: kept
        return
    env64 = load_environment(scene.environment, base)
    free = {blk.key for blk in problem.blocks}
    # The complete parameters' shapes (``finer_values`` renders the fit's values).
    params = _host_params(user_values(problem.spec, problem.z_init(), {
        k: v for k, v in problem.init_full.items() if k not in free}))
    boxes: list = [[None, None] for _ in jobs]
    sky_box: list = [None, None]
    sky_ahead = lit and problem.geometry.has_sky and bool(stencil)

    def make():
        try:
            if sky_ahead:  # ``sky_terms``' render (quick): first
                mats = _sky.lobes_alone(r.material, stencil)
                args, key = _renders.args_and_key(params, _sky.dark(problem.geometry), r.env,
                                                  _sphere(scene), mats, r.env_type)
                sky_box[1] = key, _renders.compile_render(args, mats, r.env_type, key)
            for (s, cells, material, px, sky, one), box in zip(jobs, boxes):
                lighting = _lighting(scene.environment, base, cells) if cells else None
                if cells == FINER_SUN and (lighting is None or not lighting.sun_dir.shape[0]):
                    continue  # no sun: ``finer_values`` renders no finer sun
                if lighting is None and sky:
                    break
                box[0] = _prepared(build_geometry(s, r.env_type, env64, lighting, pixels=px,
                                                  cotangents=False), px, one)
                geo = _sky.dark(box[0][0]) if sky else box[0][0]
                args, key = _renders.args_and_key(params, geo, env64, _sphere(scene), material,
                                                  r.env_type, one)
                box[1] = key, _renders.compile_render(args, material, r.env_type, key, one)
        except Exception:  # noqa: BLE001 (made again, and any error raised, where needed)
            pass

    thread = threading.Thread(target=make, name="fitter-finer-geometry", daemon=True)
    wait()  # an earlier fit's, unused
    _AHEAD.clear()
    _AHEAD.update({key: (thread, box) for key, box in zip(keys, boxes)})
    if sky_ahead:
        _AHEAD[SKY_TERMS] = thread, sky_box
    thread.start()


def _joined(key) -> list:
    """What ``prefetch`` made under ``key`` ([geometry or None, (executable key,
    executable) or None]), its thread joined and its executable kept."""
    ahead = _AHEAD.pop(key, None)
    if ahead is None:
        return [None, None]
    ahead[0].join()
    if ahead[1][1] is not None and ahead[1][1][0] not in _renders.EXECUTABLES:
        _renders.keep(*ahead[1][1])
    return ahead[1]


def wait() -> None:
    """Join the thread ``prefetch`` started, if any (its work stays for the fit
    it was made for): no thread outlives a fit."""
    for thread, _ in list(_AHEAD.values()):
        thread.join()


def _prepared(geo, flat, single: bool = False):
    """(geometry of the pixels ``flat`` found, on the device (``single``: its
    floats as float32, half the bytes its render reads); found (P,) bool;
    coverage (P,)) of ``geo``, made for the pixels ``flat``."""
    index = np.asarray(geo.pixel_index)
    at = np.minimum(np.searchsorted(index, flat), max(index.size - 1, 0))
    found = index[at] == flat if index.size else np.zeros(flat.size, bool)
    rows = at[found]
    # Usually every pixel asked for is active, in order: no copy of the sun's (L, Q) arrays.
    sub = geo if np.array_equal(rows, np.arange(index.size)) else geo.subset(rows)
    coverage = np.zeros(flat.size)
    coverage[found] = np.asarray(sub.hit, dtype=np.float64) @ np.asarray(sub.sample_weight)
    sub = jax.tree_util.tree_map(lambda a: _renders.on_device(a, single), sub._replace(
        pixel_index=None, background_image=None, env_samples=None))
    return sub, found, coverage


#: The finer geometries of the last ``finer_values`` calls (on the device), kept
#: for a refit of the same scene and pixels: building them again (the sun's cells
#: x 2k samples) was 1.6 s of a compiled env_plastic fit's 5.9 s. At most
#: ``_KEEP_BYTES`` in all (env_plastic's three: ~0.4 GB), so a large image's finer
#: geometry is not held after its fit.
_GEOMETRIES: dict = {}
_KEEP_GEOMETRIES = 3
_KEEP_BYTES = 2**29


def _geometry(scene, env64, lighting, flat, env_type, key):
    """(geometry of the pixels ``flat`` found, on the device; found (P,) bool;
    coverage (P,)): the one kept under ``key`` (``_geometry_key``), else the one
    ``prefetch`` made (with its render executable), else made here; then kept
    (in float32 where the key says so)."""
    if key in _GEOMETRIES:
        return _GEOMETRIES[key]
    made = _joined(key)[0]
    out = (made if made is not None else _prepared(
        build_geometry(scene, env_type, env64, lighting, pixels=flat, cotangents=False), flat,
        key[-1]))
    hold(_GEOMETRIES, key, out, _KEEP_GEOMETRIES, _KEEP_BYTES, size=lambda g: nbytes(g[0]),
         protect=0)  # (even the newest, if it alone is over the bytes)
    return out


def _values(scene, material, env64, lighting, flat, params, env_type, key,
            single: bool = False):
    """(values (P, 3), coverage (P,)) of the pixels ``flat`` (flat indices) of
    ``scene`` lit by its lights and ``lighting`` (``geometry.build_geometry``);
    ``key``: that geometry's ``_geometry_key``; ``single``: rendered in float32."""
    sub, found, coverage = _geometry(scene, env64, lighting, flat, env_type, key)
    vals = np.zeros((flat.size, 3))
    vals[found] = _renders.render(_host_params(params), sub, env64, _sphere(scene), material,
                                  env_type, single)
    return vals, coverage


def single(material, lit: bool) -> bool:
    """Whether the finer model renders in float32 (``SINGLE``)."""
    return SINGLE and not lit and material.single_precision


def finer_values(problem, params, rows=None, coarse=None) -> tuple[np.ndarray, np.ndarray]:
    """Values of the fitted pixels by the finer model, sky term excluded: compare
    with the model minus its sky term (``sky_terms``).

    Each refinement alone, the differences summed (first order; together, the
    quarter-texel sun at 2k samples tabulated 128 cells x 100 k samples at
    128^2, 15 s and 2 GB): 2k samples with a dielectric's bounces doubled,
    plus, under an environment lighting opaque lobes, the sun at
    ``FINER_SUN`` minus the sun at the default cells, both at k.
    Returns (values (P, 3), coverage (P,)): coverage is the share of the pixel
    the finer samples see on the sphere (the sky term scales with it; 0: none,
    the pixel is left out). ``params``: complete parameters in user units;
    ``rows``: which fitted pixels (default all); ``coarse``: their fitted values
    without the sky term (default: rendered here).
    """
    r = problem.renderer
    scene, material, env_type = r.scene, r.material, r.env_type
    base = problem.base_dir
    env64 = load_environment(scene.environment, base)
    flat = np.asarray(r.pixel_index)[problem.rows]
    if rows is not None:
        flat = flat[rows]
    lit = envlight.lit_by_environment(scene, material)
    sun = _lighting(scene.environment, base, SUN) if lit else None
    fine = scene.replace(supersampling=finer_supersampling(scene))
    f32 = single(material, lit)
    key = lambda s, cells, kept32=False: _geometry_key(  # noqa: E731
        s, base, env_type, lit and cells, flat, kept32)
    vals, coverage = _values(fine, finer_material(material), env64, sun, flat, params, env_type,
                             key(fine, SUN, f32), f32)
    if sun is not None and sun.sun_dir.shape[0]:
        finer_sun = _lighting(scene.environment, base, FINER_SUN)
        more = _values(scene, material, env64, finer_sun, flat, params, env_type,
                       key(scene, FINER_SUN))[0]
        if coarse is None:
            coarse = _values(scene, material, env64, sun, flat, params, env_type,
                             key(scene, SUN))[0]
        vals = vals + more - coarse
    return vals, coverage


def sky_terms(data, params, material, env_type) -> tuple:
    """(the fitted model's sky term (P, 3) of its opaque lobes, its part the sky
    stencil sums (P, 3), the stated bounds of its error (k, P, 3), independent):
    ``IRRADIANCE_ACCURACY`` x the lobes' uniform parts (``Lobe.uniform``),
    ``KERNEL_ACCURACY`` x their kernel parts (``Lobe.kernel``; both summed over the
    map) and ``SKY_STENCIL_ACCURACY`` x the other lobes' together (the stencil's
    errors of two lobes share its cells). Zeros and (0, P, 3) when the environment
    lights none. The model minus the sky term is the model without it."""
    zero = np.zeros(np.shape(data.geometry.background))
    if not (material.opaque and data.geometry.sky_lit):
        return zero, zero, np.zeros((0,) + zero.shape)
    host = _host_params(params)
    summed = [_sky.summed_parts(data.geometry, host, material, lb)
              for lb in _sky.opaque_lobes(material) if lb.stencil_free]
    bounds = [IRRADIANCE_ACCURACY * sum(u for u, _ in summed)] if summed else []
    if any(np.any(k) for _, k in summed):
        bounds.append(KERNEL_ACCURACY * sum(k for _, k in summed))
    sky, stencil = sum(u + k for u, k in summed) + zero, zero
    if material.stencil_lobes:
        _joined(SKY_TERMS)  # its executable, if ``prefetch`` compiled it
        # to_device: jnp.asarray compiled a conversion kernel per shape on a first run
        params = {k: to_device(np.asarray(v), data.target.dtype) for k, v in params.items()}
        stencil = _sky_terms(params, data.geometry, data.env, data.sphere, material, env_type)
        bounds.append(SKY_STENCIL_ACCURACY * stencil)
    return sky + stencil, stencil, np.stack(bounds)


def _sky_terms(params, geo, env, sphere, material, env_type) -> np.ndarray:
    """The sky term (P, 3) of ``material``'s lobes the stencil sums on ``geo``
    (``_sky.dark``), times the exposure if any; ``params`` as ``_renders.render``
    takes them."""
    lobes = _sky.lobes_alone(material, material.stencil_lobes)
    sky = _renders.render(params, _sky.dark(geo), env, sphere, lobes, env_type)
    return sky * float(params[EXPOSURE_KEY]) if material.exposure else sky


#: The sky stencil's rings (``skystencil.RING_EDGES``) against half of them
#: (``Detail.rings`` = 2): their midpoint rule's error falls as the square of the
#: ring width, so the default's is estimated as the difference / (2^2 - 1)
#: (Richardson). Against Mitsuba at 4096 spp (benchmarks/README.md, envlight) the
#: Torrance-Sparrow term's mean error is -0.11 % and -0.45 % at half the rings
#: (4.1x: second order; the estimate, 0.34 % / 3, is the error), Lambert's -0.12 %
#: and -0.79 % (the estimate 0.22 %, twice it). Fits at half the rings moved the
#: same way as the default's errors, 2-4x as far: env_plastic eta 1.4953 -> 1.4858
#: (truth 1.5), env_point eta 1.5965 -> 1.5839 (1.6), env_oren_nayar sigma 0.3585
#: -> 0.4111 (0.35), rho_d likewise.
RING_RICHARDSON = 3.0
#: ``ring_error`` renders every this many-th of the sampled pixels (each standing
#: for this many): the ring error is smooth over the sphere, and its half-ring sky
#: table is tabulated anew for the pixels it renders.
RING_STRIDE = 8


def _half_rings() -> envlight.Detail:
    """The sky stencil of half the rings (``Detail.rings`` = 2), the rest as
    ``Detail()`` is now: ``ring_error``'s ``_lighting`` kind and geometry key."""
    return envlight.Detail(rings=2)


def ring_error(problem, params, rows, sky) -> np.ndarray:
    """The sky term's ring-discretisation error at the fitted pixels ``rows``
    (M, 3): (``sky`` - the same at half the rings) / ``RING_RICHARDSON`` at every
    ``RING_STRIDE``-th row, times ``RING_STRIDE`` (a sum over them estimates the
    sum over ``rows``), 0 at the others; ``sky`` (M, 3) is the part of the fitted
    sky term the stencil sums there (``sky_terms``). Zeros where the environment
    lights no lobe the stencil sums."""
    r = problem.renderer
    scene, material, env_type = r.scene, r.material, r.env_type
    env64 = load_environment(scene.environment, problem.base_dir)
    lighting = (_lighting(scene.environment, problem.base_dir, _half_rings())
                if envlight.lit_by_environment(scene, material) and material.stencil_lobes
                else None)
    pick = np.arange(0, len(rows), RING_STRIDE)
    if lighting is None or not pick.size:
        return np.zeros(np.shape(sky))
    dark = scene.replace(lights=())  # no point lights to trace: the sky term alone
    flat = np.asarray(r.pixel_index)[problem.rows][np.asarray(rows)[pick]]
    geo, found, _ = _geometry(dark, env64, lighting, flat, env_type, _geometry_key(
        dark, problem.base_dir, env_type, _half_rings(), flat))
    half = np.zeros((pick.size, 3))
    half[found] = _sky_terms(_host_params(params), geo, env64, _sphere(scene), material,
                             env_type)
    out = np.zeros(np.shape(sky))
    out[pick] = (np.asarray(sky, dtype=np.float64)[pick] - half) * (RING_STRIDE / RING_RICHARDSON)
    out[pick[~found]] = 0.0
    return out


def shift(J, d, gram=None) -> np.ndarray:
    """delta_z (n,) = (J^T J)^-1 J^T d: the parameter shift a residual change
    ``d`` (N,) makes through the linearisation ``J`` (N, n) (both weighted);
    (n, k) for k changes ``d`` (N, k) at once; ``gram``: J^T J if the caller has it.

    By the normal equations (a least-squares solve of the n x n system, so a
    singular J^T J still gives the minimum-norm shift): 0.8 ms at 256^2, 7 ms
    by SVD of J; they lose cond(J)^2 eps relative, an error term needs a few digits.
    """
    J = np.asarray(J, dtype=np.float64)
    gram = J.T @ J if gram is None else gram
    return np.linalg.lstsq(gram, J.T @ np.asarray(d, dtype=np.float64), rcond=None)[0]

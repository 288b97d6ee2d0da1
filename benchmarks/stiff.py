"""Stiff and extreme cases: a table, one fit per case, an outcome per fit.

Each case is one extreme (sharp or flat lobe, index near 1 or large, sigma at
its edges, reflectance at 0 or 1, grazing or hidden light, saturated pixels,
low SNR, far start) on a small image. Targets are rendered by the project's
forward model plus Gaussian noise of known sigma (seeded per case), and the
fit is told that sigma (``noise_sigma``: chi^2/dof check, stderr from the
known noise) and uses ``n_starts`` as a user would for sharp lobes.

Outcome of a fit (``classify``):

* ``nonfinite``: a NaN/Inf in the fitted parameters, in the loss gradient at
  the truth, the start or the solution, or in the stderr/correlation of a
  fit reported converged -- always a bug;
* ``confident_wrong``: status ``converged``, a parameter not reported
  unidentifiable with |error| > ``CONFIDENT_SIGMAS`` x its reported stderr
  *and* > its tolerance -- always a failure;
* ``recovered``: converged, every parameter not reported unidentifiable
  within its tolerance;
* ``reported``: anything else (not converged, unidentifiable, or an error
  within its stated uncertainty): honest.

Tolerance of a parameter, per coordinate: ``TOL_REL * |truth|`` for the
log-scaled ones (m, e: their scale is relative), ``max(TOL_REL * |truth|,
TOL_ABS)`` for the others (reflectances, sigma, eta can be 0 or near 1).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

TOL_REL = 0.05
TOL_ABS = 0.02
CONFIDENT_SIGMAS = 5.0
#: Pixel noise sigma of every target (radiance units; pixel values are 0.05-1).
NOISE = 1e-3
OUTCOMES = ("recovered", "reported", "confident_wrong", "nonfinite")

_SMITH = {"torrance_sparrow.geometry": "smith"}
_TWO = ((3.0, 4.0, 5.0, 50.0), (-4.0, 1.0, 3.0, 25.0))


def _at_angle(deg: float, dist: float = 6.0):
    """A light at ``deg`` from the camera axis (+z), in the x-z plane."""
    a = math.radians(deg)
    return (dist * math.sin(a), 0.0, dist * math.cos(a))


@dataclasses.dataclass(frozen=True)
class StiffCase:
    name: str
    lobes: tuple
    truth: dict
    options: dict = dataclasses.field(default_factory=dict)
    init: dict = dataclasses.field(default_factory=dict)
    lights: tuple = _TWO  # (x, y, z, intensity)
    snr: float | None = None  # noise sigma = mean pixel / snr (instead of NOISE)
    saturate: float = 0.0  # fraction of fitted pixels clipped at the target's quantile
    mask_saturated: bool = True  # tell the fit the saturation level
    n_starts: int = 4
    environment: bool = False  # the shipped envmap (dielectric)
    fast: bool = False  # in the CI subset (tests/test_stiff_cases.py)


def _plastic(m=0.2, eta=1.5, rho=0.5, **kw):
    return StiffCase(lobes=("lambert", "torrance_sparrow"), options=_SMITH,
                     truth={"lambert.rho_d": [rho] * 3, "torrance_sparrow.m": m,
                            "torrance_sparrow.eta": eta}, **kw)


def _phong(e, **kw):
    return StiffCase(lobes=("lambert", "phong"),
                     truth={"lambert.rho_d": [0.5, 0.4, 0.3], "phong.rho_s": [0.4] * 3,
                            "phong.e": e}, **kw)


def cases() -> list[StiffCase]:
    """The case table (``fast`` marks the CI subset: two materials, two compiles)."""
    far = {"torrance_sparrow.m": 0.5, "torrance_sparrow.eta": 1.5}
    out = [
        _plastic(name="m=1e-3", m=1e-3, init={"torrance_sparrow.m": 0.01}),
        _plastic(name="m=0.01", m=0.01, fast=True),
        _plastic(name="m=0.05", m=0.05, fast=True),
        _phong(1.0, name="e=1", fast=True),
        _phong(1000.0, name="e=1000", fast=True),
        _phong(1e4, name="e=1e4", fast=True),
        _plastic(name="eta=1.0", eta=1.0, fast=True),
        _plastic(name="eta=1.001", eta=1.001, fast=True),
        _plastic(name="eta=1.02", eta=1.02, fast=True),
        _plastic(name="eta=2.5", eta=2.5, fast=True),
        _plastic(name="eta=4.0", eta=4.0, fast=True),
        StiffCase(name="sigma=0", lobes=("oren_nayar",),
                  truth={"oren_nayar.rho_d": [0.5, 0.45, 0.4], "oren_nayar.sigma": 0.0}),
        StiffCase(name="sigma=1e-4", lobes=("oren_nayar",),
                  truth={"oren_nayar.rho_d": [0.5, 0.45, 0.4], "oren_nayar.sigma": 1e-4}),
        StiffCase(name="sigma=1.2", lobes=("oren_nayar",),
                  truth={"oren_nayar.rho_d": [0.5, 0.45, 0.4], "oren_nayar.sigma": 1.2}),
        _plastic(name="rho_d=0", rho=0.0, fast=True),
        _plastic(name="rho_d=1", rho=1.0, fast=True),
        _plastic(name="light at 89.9 deg", fast=True,
                 lights=(_at_angle(89.9) + (60.0,), _at_angle(180.0) + (25.0,))),
        _plastic(name="lights behind", fast=True,
                 lights=(_at_angle(180.0) + (60.0,), _at_angle(150.0, 8.0) + (25.0,))),
        _plastic(name="10% saturated, masked", saturate=0.1, fast=True),
        _plastic(name="10% saturated, unmasked", saturate=0.1, mask_saturated=False, fast=True),
        _plastic(name="SNR 5", snr=5.0, fast=True),
        _plastic(name="far start m x10", m=0.05, init=far, fast=True),
        _phong(1000.0, name="far start e /10", init={"phong.e": 100.0}, fast=True),
        StiffCase(name="dielectric eta=4 (near-total reflection at the rim)",
                  lobes=("dielectric",), environment=True, lights=(),
                  truth={"dielectric.eta": 4.0, "dielectric.attenuation": [0.9, 0.7, 0.5]}),
        StiffCase(name="dielectric eta=1.001", lobes=("dielectric",), environment=True,
                  lights=(),
                  truth={"dielectric.eta": 1.001, "dielectric.attenuation": [0.9, 0.7, 0.5]}),
    ]
    return out


def scene_of(case: StiffCase, size: int, supersampling: int = 2):
    import os

    import fitter

    lights = tuple(fitter.PointLight(tuple(float(v) for v in l[:3]), (float(l[3]),) * 3)
                   for l in case.lights)
    env = fitter.Environment()
    if case.environment:
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env = fitter.Environment(type="envmap", file=os.path.join(root, "data_synthetic",
                                                                  "envmap.exr"))
    return fitter.Scene(width=size, height=size, supersampling=supersampling, lights=lights,
                        environment=env)


def _finite(x) -> bool:
    return bool(np.all(np.isfinite(np.asarray(x, dtype=np.float64))))


def loss_gradients(scene, material, target, points, dtype) -> list[bool]:
    """Whether the gradient of 0.5 sum (model - target)^2 is finite at each point."""
    import jax
    import jax.numpy as jnp

    from fitter.render import cached_renderer

    r = cached_renderer(scene, material, jnp.dtype(dtype), None)
    flat = np.asarray(target).reshape(-1, 3)[r.pixel_index]
    ok = np.isfinite(flat)
    t = jnp.asarray(np.where(ok, flat, 0.0), dtype=dtype)
    w = jnp.asarray(ok, dtype=dtype)
    free = [k for k, s in material.param_specs().items() if s.free]

    def loss(p, rest):
        return 0.5 * jnp.sum(((r.active({**rest, **p}) - t) * w) ** 2)

    grad = jax.jit(jax.grad(loss))  # traced once for the three points
    out = []
    for pt in points:
        p = {k: jnp.asarray(pt[k], dtype=dtype) for k in free}
        rest = {k: jnp.asarray(v, dtype=dtype) for k, v in pt.items() if k not in free}
        g = grad(p, rest)
        out.append(all(_finite(v) for v in g.values()))
    return out


def _log_scaled(result, key: str) -> bool:
    from fitter.bsdf import LOBES

    lobe, name = key.split(".", 1)
    return any(p.name == name and p.transform == "log" for p in LOBES[lobe].params)


def classify(result, truth: dict) -> tuple[str, dict]:
    """(outcome, per-parameter detail) of a ``FitResult`` against the truth."""
    detail = {}
    nonfinite = not all(_finite(v) for v in result.params.values())
    if result.status == "converged":
        nonfinite |= not all(_finite(v) for v in result.stderr.values())
        nonfinite |= not _finite(result.correlation)
    wrong, within = False, True
    for k in result.free:
        if k in result.unidentifiable:
            continue
        v = np.atleast_1d(np.asarray(result.params[k], float))
        t = np.atleast_1d(np.asarray(truth[k], float))
        se = np.atleast_1d(np.asarray(result.stderr.get(k, np.nan), float))
        err = np.abs(v - t)
        tol = TOL_REL * np.abs(t) if _log_scaled(result, k) else \
            np.maximum(TOL_REL * np.abs(t), TOL_ABS)
        detail[k] = {"value": v.tolist(), "truth": t.tolist(), "abs_err": err.tolist(),
                     "stderr": se.tolist(), "tol": tol.tolist()}
        within &= bool(np.all(err <= tol))
        wrong |= bool(np.any((err > CONFIDENT_SIGMAS * np.nan_to_num(se, nan=np.inf))
                             & (err > tol)))
    if nonfinite:
        return "nonfinite", detail
    if result.status == "converged" and wrong:
        return "confident_wrong", detail
    # A parameter held as unidentifiable was not recovered, only honestly reported.
    if result.status == "converged" and within and not result.unidentifiable:
        return "recovered", detail
    return "reported", detail


#: Pixels whose noise-free value is below this many noise sigmas get weight 0: chosen
#: from the noise-free image, so the selection is unbiased, and the target has no
#: negative values (which the fit would drop, changing the pixel count per draw).
DARK_SIGMAS = 4.0


def make_target(case: StiffCase, scene, material, dtype=np.float64):
    """(target (H, W, 3), noise sigma, saturation level or None, weights (H, W, 3))."""
    import fitter

    clean = np.asarray(fitter.render({**case.truth, **case.options}, scene, material),
                       dtype=np.float64)
    seed = sum(ord(c) for c in case.name)
    rng = np.random.default_rng(seed)
    sigma = NOISE
    if case.snr is not None:
        lit = clean[clean.sum(-1) > 0]
        sigma = float(lit.mean() / case.snr)
    target = clean + rng.normal(0.0, sigma, clean.shape)
    weights = (clean >= DARK_SIGMAS * sigma).astype(np.float64)
    target = np.where(weights > 0, target, np.maximum(target, 0.0))
    level = None
    if case.saturate > 0:
        lit = target.max(-1)[clean.sum(-1) > 0]
        level = float(np.quantile(lit, 1.0 - case.saturate))
        target = np.minimum(target, level)
    return target, sigma, level, weights


def run_case(case: StiffCase, size: int = 24, dtype=None, supersampling: int = 2) -> dict:
    """Fit one case; returns a JSON-ready record with ``outcome``."""
    import time

    import jax.numpy as jnp

    import fitter
    from fitter.material import Material

    dtype = dtype or jnp.float64
    scene = scene_of(case, size, supersampling)
    material = Material.make(list(case.lobes), case.options)
    target, sigma, level, weights = make_target(case, scene, material)
    t0 = time.perf_counter()
    res = fitter.fit(target, scene, material, init=case.init or None, noise_sigma=sigma,
                     n_starts=case.n_starts, dtype=dtype, weights=weights,
                     saturation=level if case.mask_saturated else None)
    secs = time.perf_counter() - t0
    outcome, detail = classify(res, case.truth)
    start = material.full_params(case.init or {})
    truth = material.full_params(case.truth)
    grads = loss_gradients(scene, material, target * weights,
                           [truth, start, {**start, **{k: np.asarray(v) for k, v in
                                                     res.params.items()}}], dtype)
    if not all(grads):
        outcome = "nonfinite"
    return {"case": case.name, "dtype": jnp.dtype(dtype).name, "size": size,
            "outcome": outcome, "status": res.status, "message": res.message,
            "unidentifiable": list(res.unidentifiable), "warnings": list(res.warnings),
            "gradients_finite": grads, "detail": detail, "seconds": secs,
            "iterations": res.iterations}


def run(spec: dict) -> dict:
    """Worker: ``{"size", "dtypes", "fast_only"}`` -> ``{"rows": [...], "counts": {...}}``."""
    import jax.numpy as jnp

    rows = []
    for dt in spec.get("dtypes", ["float64"]):
        for case in cases():
            if spec.get("fast_only") and not case.fast:
                continue
            try:
                rows.append(run_case(case, int(spec.get("size", 24)), jnp.dtype(dt)))
            except Exception as exc:  # an exception is reported, never hidden
                rows.append({"case": case.name, "dtype": dt, "outcome": "error",
                             "message": f"{type(exc).__name__}: {exc}"})
    counts = {}
    for r in rows:
        counts.setdefault(r["dtype"], {o: 0 for o in OUTCOMES + ("error",)})
        counts[r["dtype"]][r["outcome"]] += 1
    return {"rows": rows, "counts": counts}

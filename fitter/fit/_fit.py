"""The fit driver: target image -> FitResult.

Flow: choose pixels -> build the problem -> hold unidentifiable parameters ->
solve from one or more starts (one compiled call) -> keep the lowest cost ->
re-check identifiability at the solution -> covariance -> FitResult.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .. import transforms
from ..material import Material
from ..render import Renderer, _renderer, render_active
from ..scene import Scene
from ._cache import compile_cached
from ._noise import estimate_noise
from ._problem import LOSSES, Block, Data, Spec, params_from_z, residuals, z_from_params
from ._solvers import SOLVERS, make_solver
from ._starts import starts as make_starts
from .result import FitResult
from ..errors import FitterError

#: A column of the Jacobian this much smaller than the largest one means the
#: image does not depend on that parameter at all.
ZERO_COLUMN = 1e-9
#: Condition number of the column-normalised Jacobian beyond which the
#: direction of the smallest singular value is taken as unidentifiable.
MAX_CONDITION = 1e8
#: A parameter whose +-1 sigma interval covers more than this fraction of its
#: box (in log for log boxes) is reported unidentifiable: at the centre of a
#: box that is a standard error of 3 in z.
MAX_SPAN = 0.9
#: Beyond this |z| the sigmoid's slope is < 1e-12: the parameter sits on its bound.
SATURATED_Z = 27.0
#: A fitted value within this fraction of its range from a box edge is "at bound".
AT_BOUND = 1e-4
#: With a known noise sigma, chi^2 per degree of freedom above this fails the fit.
MAX_REDUCED_CHI2 = 2.0
#: Without a noise sigma, a residual RMSE this many times the target's own noise
#: level (``_noise.estimate_noise``) fails the fit. Measured on the shipped
#: Mitsuba cases: good fits 0.2-3.5, fits stopped after 2 steps 25-450.
MAX_NOISE_RATIO = 10.0
#: Starts on a box edge (e.g. the default attenuation 1) are moved this fraction
#: of the range inside: on the edge the coordinate is saturated and the
#: Jacobian column vanishes.
START_MARGIN = 1e-2
#: Default step budgets.
MAX_STEPS = {"adam": 5000, "bfgs": 1000}
DEFAULT_MAX_STEPS = 200


#: Another start within this joint confidence level of the best one, but
#: beyond that region's reach in a parameter, makes that parameter
#: unidentifiable (``_ambiguous``).
AMBIGUOUS_LEVEL = 0.95
#: Rounds of hold-and-refit after a fit (``_Job.finish``).
MAX_REFITS = 2
#: The zero-column check at the start first looks at every 8th fitted pixel.
START_CHECK_STRIDE = 8
#: XLA options for the solver loops. Loop-invariant code motion hoists the
#: parameter-independent parts of every sample (masks, G, 1/cos) out of the
#: solver's while loop into separate, unfused passes over (lights, pixels,
#: samples) arrays: measured +30 ms per LM fit at 256^2 with 4x4 samples
#: (fixed cost 45 -> 15 ms), for no gain per step.
SOLVE_XLA_OPTIONS = {"xla_disable_hlo_passes": "while-loop-invariant-code-motion"}


class FitError(FitterError):
    """A fit that cannot be set up (message says what to change)."""


_COMPILED: dict = {}


def _jacobian_r(spec: Spec, z, data):
    """(R, r) at ``z``: the residuals (N,) and the Jacobian's R factor (n, n).

    J = Q R has J's column norms, singular values and Gram matrix J^T J =
    R^T R, all that the diagnostics need, without moving the (N, n) Jacobian
    to the host. A float32 fit (traced without x64) returns J itself; the
    host factors it in float64 (``_r_factor``).
    """
    J, r = jax.jacfwd(lambda z: (residuals(z, data, spec),) * 2, has_aux=True)(z)
    if J.dtype == jnp.float64:
        J = jnp.linalg.qr(J, mode="r")
    return J, r


def _r_factor(J):
    """R factor (n, n) in float64 of a Jacobian, or R itself, from ``_jacobian_r``."""
    J = np.asarray(J, dtype=np.float64)
    return J if J.shape[0] == J.shape[1] else np.linalg.qr(J, mode="r")


def _solve_fn(spec: Spec, solver_name: str, rtol: float, atol: float, max_steps: int):
    """Compiled entry: starts (S, n) -> (z, code, steps, cost) per start, the
    best start's index, and ``_jacobian_r`` there (the diagnostics)."""
    solver = make_solver(solver_name, rtol, atol)

    def fn(z, data):
        return residuals(z, data, spec)

    def one(z0, data):
        sol = optx.least_squares(fn, solver, z0, args=data, max_steps=max_steps, throw=False)
        info = getattr(sol.state, "f_info", None)
        # optimistix's solver state is not public API: anything else falls back.
        residual_jac = getattr(getattr(optx, "FunctionInfo", None), "ResidualJac", ())
        if residual_jac and isinstance(info, residual_jac):
            # Gauss-Newton family: the solver's last accepted linearisation is at
            # sol.value; materialising it costs n cheap tangents, not a new Jacobian.
            r, J = info.residual, info.jac.as_matrix()
            jr = (jnp.linalg.qr(J, mode="r") if J.dtype == jnp.float64 else J, r)
        else:
            jr = _jacobian_r(spec, sol.value, data)
        r = jr[1]
        return sol.value, sol.result._value, sol.stats["num_steps"], 0.5 * jnp.sum(r * r), jr

    def many(z0s, data):
        zs, codes, steps, costs, (Rs, rs) = jax.lax.map(lambda z0: one(z0, data), z0s)
        best = _best(costs, zs, jnp)
        return zs, codes, steps, costs, best, (Rs[best], rs[best])

    return many


def _batch_fn(spec: Spec, batch: str, **static):
    """One start per target: ``(z0, data with stacked targets/weights) -> stacked results``."""
    one = _solve_fn(spec, **static)

    def single(z0, target, weights, data):
        zs, codes, steps, costs, _, jr = one(z0[None], data._replace(target=target,
                                                                   weights=weights))
        return zs[0], codes[0], steps[0], costs[0], jr

    def run(z0, data):
        if batch == "vmap":
            return jax.vmap(single, in_axes=(None, 0, 0, None))(z0, data.target, data.weights, data)
        return jax.lax.map(lambda tw: single(z0, tw[0], tw[1], data), (data.target, data.weights))

    return run


def _compiled(kind, spec, args, **static):
    """Compile (once per structure and shapes) and return (executable, seconds spent)."""
    shapes = jax.tree_util.tree_map(lambda a: (jnp.shape(a), jnp.result_type(a)), args)
    key = (kind, spec, tuple(sorted(static.items())), str(shapes))
    if key in _COMPILED:
        return _COMPILED[key], 0.0
    if kind == "solve":
        f = _solve_fn(spec, **static)
    elif kind == "batch":
        f = _batch_fn(spec, **static)
    else:  # Jacobian (as its R factor in float64) and residuals in one pass
        f = functools.partial(_jacobian_r, spec)
    # optimistix creates some constants (e.g. LM's damping) as Python floats, which
    # x64 would make float64: a float32 fit is traced with x64 off.
    single = jnp.result_type(args[0]) == jnp.float32
    t0 = time.perf_counter()
    with jax.enable_x64(not single):
        exe = compile_cached(f, args, repr(key), SOLVE_XLA_OPTIONS if kind != "jacres" else None)
    _COMPILED[key] = exe
    return exe, time.perf_counter() - t0


@functools.lru_cache(maxsize=4)
def _fitted_geometry(renderer: Renderer, rows: bytes):
    """The renderer's geometry of the fitted ``rows`` (int64 bytes), on the device.

    Subset in NumPy (no per-op dispatch), then onto the device once: the
    solver must not copy host arrays on every call. Cached, as repeated fits
    of one scene (a series of images, a batch) select the same pixels.
    """
    idx = np.frombuffer(rows, dtype=np.int64)
    return jax.tree_util.tree_map(jnp.asarray, renderer.geometry.subset(idx)._replace(
        pixel_index=None, background_image=None))


def _as_material(material) -> Material:
    return material if isinstance(material, Material) else Material.make(material)


def select_pixels(renderer: Renderer, target, mask, exclude, saturation):
    """Rows of the renderer's active pixels to fit, and how many were dropped.

    ``mask``: ``"interior"`` (pixels whose every sub-pixel sample hits the
    sphere; default), ``"active"`` (any sample hits) or an (H, W) bool array.
    Pixels with a NaN/Inf value, in ``exclude``, or with a channel at/above
    ``saturation`` are dropped. Negative values are kept: zero-mean noise on a
    dark pixel is data, and dropping it would bias the fit.
    """
    geo = renderer.geometry
    h, w = renderer.scene.height, renderer.scene.width
    flat = target.reshape(h * w, 3)[renderer.pixel_index]
    hit = np.asarray(geo.hit)
    if isinstance(mask, str):
        if mask == "interior":
            chosen = hit.all(axis=1)
        elif mask == "active":
            chosen = np.ones(hit.shape[0], dtype=bool)
        else:
            raise FitError(f"mask = {mask!r}: expected 'interior', 'active' or an (H, W) array")
    else:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (h, w):
            raise FitError(f"mask has shape {m.shape}, expected {(h, w)}")
        chosen = m.reshape(-1)[renderer.pixel_index]
    good = np.all(np.isfinite(flat), axis=1)
    if exclude is not None:
        ex = np.asarray(exclude, dtype=bool)
        if ex.shape != (h, w):
            raise FitError(f"exclude has shape {ex.shape}, expected {(h, w)}")
        good &= ~ex.reshape(-1)[renderer.pixel_index]
    if saturation is not None:
        good &= np.all(np.where(np.isfinite(flat), flat, 0) < saturation, axis=1)
    rows = np.nonzero(chosen & good)[0]
    return rows, int(chosen.sum() - rows.size), flat


def _blocks(material: Material, fixed_keys, bounds) -> tuple[Block, ...]:
    """Free parameters as solver blocks, with their (possibly narrowed) boxes."""
    blocks = []
    for key, spec in material.param_specs().items():
        if key in fixed_keys:
            continue
        lo, hi = spec.lower, spec.upper
        if bounds and key in bounds:
            lo, hi = (float(v) for v in bounds[key])
            if not (spec.lower <= lo < hi <= spec.upper):
                raise FitError(f"bounds for {key} = {(lo, hi)} must satisfy "
                               f"{spec.lower:g} <= lower < upper <= {spec.upper:g}")
        blocks.append(Block(key, spec.size, spec.transform, lo, hi))
    return tuple(blocks)


def fit(target, scene: Scene, material, *, init: Mapping[str, Any] | None = None,
        fixed: Mapping[str, Any] | None = None, bounds: Mapping[str, tuple] | None = None,
        solver: str = "levenberg_marquardt", mask="interior", exclude=None, weights=None,
        noise_sigma: float | None = None, loss: str = "l2", loss_scale: float | None = None,
        saturation: float | None = None, n_starts: int = 1, max_steps: int | None = None,
        rtol: float = 1e-6, atol: float = 1e-8, dtype=jnp.float64,
        base_dir: str | None = None, identifiability: bool = True) -> FitResult:
    """Fit the material's parameters to a target image.

    Args:
        target: (H, W, 3) linear RGB radiance of the scene's image.
        scene: the known camera, sphere, lights and environment.
        material: a ``Material``, a lobe list, or a ``"lambert+phong"`` string.
        init: initial values ``{"lobe.param": value}``; missing ones take the
            lobe's default. A parameter that is fixed by default (e.g.
            ``torrance_sparrow.rho_s``) is freed by giving it here.
        fixed: values held fixed (option values such as
            ``"torrance_sparrow.geometry": "smith"`` may also stand here).
        bounds: narrower ``(lower, upper)`` per parameter (inside its box).
        solver: one of ``SOLVERS``.
        mask, exclude, saturation: pixel selection (see ``select_pixels``).
        weights: (H, W) or (H, W, 3) per-pixel residual weights.
        noise_sigma: known pixel noise standard deviation: residuals are
            divided by it, standard errors use it instead of the residual
            estimate, and chi^2 / dof > ``MAX_REDUCED_CHI2`` fails the fit.
        loss: ``"l2"``, ``"huber"`` or ``"cauchy"`` with scale ``loss_scale``
            (in units of the weighted residual; default 1 if noise_sigma is
            given, else 0.01).
        n_starts: number of starts: ``init`` plus ``n_starts - 1`` points of
            a Halton sequence over the parameter box (``fitter.fit._starts``);
            the lowest final cost is kept, all are reported.
        max_steps, rtol, atol: solver budget and tolerances.
        dtype: ``jnp.float64`` (default) or ``jnp.float32``.
        identifiability: hold and report parameters the data cannot constrain.

    Returns:
        A ``FitResult``; failures are reported in ``status``/``message``,
        not raised. Raises ``FitError`` / ``MaterialError`` for bad input.
    """
    t_start = time.perf_counter()
    if n_starts < 1:
        raise FitError(f"n_starts = {n_starts} must be >= 1")
    job = _Job.make(target[None] if np.ndim(target) == 3 else target, scene, material,
                    init=init, fixed=fixed, bounds=bounds, solver=solver, mask=mask,
                    exclude=exclude, weights=weights, noise_sigma=noise_sigma, loss=loss,
                    loss_scale=loss_scale, saturation=saturation, max_steps=max_steps,
                    rtol=rtol, atol=atol, dtype=dtype, base_dir=base_dir)
    if job.targets.shape[0] != 1:
        raise FitError(f"target has shape {np.shape(target)}, expected "
                       f"{(scene.height, scene.width, 3)}; use fit_batch for several targets")
    if identifiability:
        early = job.hold_dead_columns()
        if early is not None:
            return early
    data = job.data(0)
    z0s = job.cast(make_starts(job.spec, job.z_init(), n_starts))
    solve, tc = _compiled("solve", job.spec, (z0s, data), **job.static)
    job.t_compile += tc
    zs, codes, nsteps, costs, best, (R, r) = solve(z0s, data)
    zs, codes, nsteps, costs, best = (np.asarray(a) for a in (zs, codes, nsteps, costs, best))
    starts = [{"params": _user(job.spec, zs[i], data), "cost": float(costs[i]),
               "status": _status(int(codes[i]), zs[i], costs[i])} for i in range(len(costs))]
    return job.finish(0, zs[best], int(codes[best]), int(nsteps[best]), float(costs[best]),
                      identifiability, t_start, starts,
                      jr=(_r_factor(R), np.asarray(r, dtype=np.float64)),
                      alternatives=[(zs[i], float(costs[i])) for i in range(len(costs))
                                    if i != best])


def fit_batch(targets, scene: Scene, material, *, batch: str = "map",
              identifiability: bool = True, **kwargs) -> list[FitResult]:
    """Fit many targets of one scene and material in one compiled solve.

    Args:
        targets: (B, H, W, 3) images.
        batch: ``"map"`` (``jax.lax.map``, default: on CPU a vmapped solver
            loop runs every fit for as many steps as the slowest one) or
            ``"vmap"`` (``jax.vmap``, for accelerators).
        kwargs: as ``fit`` (except ``n_starts`` and ``exclude``); the pixel
            selection is shared, NaN/Inf/saturated pixels of each target get
            weight 0.

    Returns:
        One ``FitResult`` per target. A target whose solution leaves a
        parameter unidentifiable is refitted alone by ``fit`` with that
        parameter held, so each result is what ``fit`` would report; times
        of the shared solve are split evenly.
    """
    t_start = time.perf_counter()
    if batch not in ("map", "vmap"):
        raise FitError(f"batch = {batch!r}: expected 'map' or 'vmap'")
    targets = np.asarray(targets, dtype=np.float64)
    if targets.ndim != 4:
        raise FitError(f"targets have shape {targets.shape}, expected (B, H, W, 3)")
    job = _Job.make(targets, scene, material, **kwargs)
    if identifiability:
        early = job.hold_dead_columns()
        if early is not None:
            return [dataclasses.replace(early) for _ in range(targets.shape[0])]
    data = job.data(None)
    z0 = job.cast(job.z_init())
    solve, tc = _compiled("batch", job.spec, (z0, data), batch=batch, **job.static)
    job.t_compile += tc
    zs, codes, nsteps, costs, (R, r) = (jax.tree_util.tree_map(np.asarray, a)
                                        for a in solve(z0, data))
    share = (time.perf_counter() - t_start - job.t_compile) / len(targets)
    results = []
    for b in range(len(targets)):
        t0 = time.perf_counter()
        res = job.finish(b, zs[b], int(codes[b]), int(nsteps[b]), float(costs[b]),
                         identifiability, t0, starts=[], refit=False,
                         jr=(_r_factor(R[b]), np.asarray(r[b], dtype=np.float64)))
        if identifiability and res is None:  # became unidentifiable: refit alone
            res = fit(targets[b], scene, material, identifiability=True, **kwargs)
        else:
            res.time_run += share
            res.time_compile = job.t_compile / len(targets)
        results.append(res)
    return results


@dataclasses.dataclass
class _Job:
    """A fit set up: pixels, data arrays, free blocks; shared by fit and fit_batch."""

    material: Material
    renderer: Renderer
    geometry: Any  # the renderer's geometry restricted to ``rows``
    rows: np.ndarray
    n_dropped: int
    targets: np.ndarray  # (B, P, 3) selected pixels, 0 where unusable
    weights: np.ndarray  # (B, P, 3)
    init_full: dict
    blocks: tuple
    loss: str
    loss_scale: float
    noise_sigma: float | None
    dtype: Any
    static: dict
    noise: np.ndarray  # (B, 3) noise level estimated from each target
    unidentifiable: list = dataclasses.field(default_factory=list)
    warnings: list = dataclasses.field(default_factory=list)
    t_compile: float = 0.0

    @classmethod
    def make(cls, targets, scene, material, *, init=None, fixed=None, bounds=None,
             solver="levenberg_marquardt", mask="interior", exclude=None, weights=None,
             noise_sigma=None, loss="l2", loss_scale=None, saturation=None, max_steps=None,
             rtol=1e-6, atol=1e-8, dtype=jnp.float64, base_dir=None) -> "_Job":
        material = _as_material(material)
        if solver not in SOLVERS:
            raise FitError(f"unknown solver {solver!r}; known: {', '.join(SOLVERS)}")
        if loss not in LOSSES:
            raise FitError(f"unknown loss {loss!r}; known: {', '.join(LOSSES)}")
        targets = np.asarray(targets, dtype=np.float64)
        if targets.shape[1:] != (scene.height, scene.width, 3):
            raise FitError(f"target has shape {targets.shape[1:]}, expected "
                           f"{(scene.height, scene.width, 3)} from the scene")
        if noise_sigma is not None and not noise_sigma > 0:
            raise FitError(f"noise_sigma = {noise_sigma} must be > 0")
        options = {k: v for k, v in {**(init or {}), **(fixed or {})}.items()
                   if k in material.option_keys()}
        if options:
            material = Material.make(material.lobes, {**dict(material.options), **options})
        opt_keys = material.option_keys()
        numeric_fixed = {k: v for k, v in (fixed or {}).items() if k not in opt_keys}
        numeric_init = {k: v for k, v in (init or {}).items() if k not in opt_keys}
        overlap = set(numeric_fixed) & set(numeric_init)
        if overlap:
            raise FitError(f"{sorted(overlap)} given both as initial and as fixed values")
        init_full = material.full_params({**numeric_init, **numeric_fixed})
        fixed_keys = set(numeric_fixed) | {k for k, s in material.param_specs().items()
                                           if not s.free and k not in numeric_init}
        blocks = _blocks(material, fixed_keys, bounds)
        if not blocks:
            raise FitError("every parameter is fixed: nothing to fit")

        renderer = _renderer(scene, material, jnp.dtype(dtype),
                             os.path.abspath(base_dir) if base_dir else None)
        # Pixels are chosen on the first target; others mark their bad pixels by weight 0.
        rows, n_dropped, _ = select_pixels(renderer, targets[0], mask, exclude, saturation)
        if rows.size == 0:
            raise FitError("no pixels to fit: the mask selects none, or every selected pixel "
                           "is NaN/Inf, excluded or saturated")
        picked = targets.reshape(len(targets), -1, 3)[:, renderer.pixel_index[rows]]
        usable = np.all(np.isfinite(picked), axis=-1, keepdims=True)
        if saturation is not None:
            usable &= np.all(np.where(np.isfinite(picked), picked, 0) < saturation,
                             axis=-1, keepdims=True)
        w = np.ones(picked.shape)
        if weights is not None:
            wt = np.asarray(weights, dtype=np.float64)
            wt = np.broadcast_to(wt[..., None] if wt.ndim == 2 else wt,
                                 (scene.height, scene.width, 3))
            w = w * wt.reshape(-1, 3)[renderer.pixel_index[rows]]
        if noise_sigma is not None:
            w = w / noise_sigma
        w = np.where(usable, w, 0.0)
        steps = max_steps or MAX_STEPS.get(solver, DEFAULT_MAX_STEPS)
        geometry = _fitted_geometry(renderer, rows.astype(np.int64).tobytes())
        interior = np.zeros(scene.height * scene.width, dtype=bool)
        interior[renderer.pixel_index[rows]] = True
        noise = [estimate_noise(t, interior.reshape(scene.height, scene.width)) for t in targets]
        return cls(material, renderer, geometry, rows, n_dropped,
                   np.where(usable, picked, 0.0), w,
                   init_full, blocks, loss,
                   loss_scale if loss_scale is not None else (1.0 if noise_sigma else 0.01),
                   noise_sigma, dtype,
                   dict(solver_name=solver, rtol=rtol, atol=atol, max_steps=steps),
                   np.asarray(noise))

    def cast(self, a):
        return jnp.asarray(a, dtype=self.dtype)

    @property
    def spec(self) -> Spec:
        return Spec(self.material, self.renderer.env_type, self.blocks, self.loss,
                    self.loss_scale)

    def data(self, b: int | None, stride: int = 1) -> Data:
        """Arrays of target ``b`` (all targets stacked if None); every
        ``stride``-th fitted pixel only if ``stride`` > 1."""
        free = {blk.key for blk in self.blocks}
        fixed = {k: self.cast(v) for k, v in self.init_full.items() if k not in free}
        sel = slice(None) if b is None else b
        geometry = self.geometry if stride == 1 else _fitted_geometry(
            self.renderer, self.rows[::stride].astype(np.int64).tobytes())
        pick = lambda a: self.cast(a[sel][..., ::stride, :])  # noqa: E731
        return Data(geometry, self.renderer.env, self.renderer.sphere,
                    pick(self.targets), pick(self.weights), fixed)

    def z_init(self):
        return z_from_params(self.spec, self.init_full, START_MARGIN)

    def hold(self, keys, reasons):
        self.unidentifiable += list(keys)
        self.warnings += list(reasons)
        self.blocks = tuple(b for b in self.blocks if b.key not in keys)

    def hold_dead_columns(self) -> FitResult | None:
        """Hold parameters the fitted pixels do not depend on at the start.

        The Jacobian does not depend on the target, so one check serves a batch.
        Returns a failed result if nothing is left to fit.
        """
        z0 = self.z_init()
        # A column alive on a strided subset of the pixels is alive (the common
        # case, at 1/8 of the cost); one that looks dead there is checked on all.
        stride = START_CHECK_STRIDE if self.rows.size >= START_CHECK_STRIDE * 512 else 1
        while True:
            J0, _, tc = _jac_res(self.spec, z0, self.data(0, stride))
            self.t_compile += tc
            dead = _dead_columns(self.spec, z0, J0)
            if stride == 1 or not dead.any():
                break
            stride = 1
        dead = _blocks_of(self.spec, dead)
        self.hold(dead, [f"{k} does not change the fitted pixels at the start (zero "
                         f"Jacobian column); held at {_fmt(self.init_full[k])}" for k in dead])
        if not self.blocks:
            return _all_held(self.init_full, self.unidentifiable, self.warnings, self.rows.size,
                             self.n_dropped, self.t_compile, 0.0)
        return None

    def finish(self, b, z, code, iters, cost, identifiability, t_start, starts,
               refit=True, jr=None, alternatives=()) -> FitResult | None:
        """Check, refit without unidentifiable parameters, and report target ``b``.

        ``jr``: (R, r) at ``z`` if the solve returned them (``_jac_res``).
        ``alternatives``: (z, cost) where the other starts ended (``_ambiguous``).
        With ``refit=False`` an unidentifiable parameter at the solution
        returns None (the caller refits).
        """
        spec, data = self.spec, self.data(b)
        if jr is None:
            J, r, tc = _jac_res(spec, z, data)
            self.t_compile += tc
        else:
            J, r = jr
        warnings, unidentifiable = list(self.warnings), list(self.unidentifiable)
        # Hold what the image does not constrain and refit the rest, from the best
        # point and from where every other start ended (so the refit is checked
        # for ambiguity too). A parameter that is only ambiguous (another start
        # as good, elsewhere) is marked, not held: the others keep their errors
        # from the whole covariance, not ones conditional on an arbitrary value.
        marked = None
        for round_ in range(MAX_REFITS + 1 if identifiability else 0):
            if not np.isfinite(cost):
                break
            s2 = self.residual_variance(data, r, spec)
            unid = _unidentifiable_at(spec, z, J, s2)
            ambiguous = _ambiguous(spec, z, J, s2, cost, alternatives)
            if unid is None or round_ == MAX_REFITS:
                # Out of rounds: what is still unidentifiable is marked, not held.
                marked = [list(a) + list(b) for a, b in zip(unid or ([], []),
                                                             ambiguous or ([], []))]
                break
            if not refit:
                return None
            keys, reasons = unid
            best = _user(spec, z, data)
            for k, why in zip(*(ambiguous or ([], []))):
                if k not in keys:  # held with the others, at this fit's value
                    keys.append(k)
                    reasons.append(why + "; held at this fit's value")
                    self.init_full[k] = best[k]
            points = [best] + [_user(spec, za, data) for za, _ in alternatives]
            self.hold(keys, reasons)
            warnings, unidentifiable = list(self.warnings), list(self.unidentifiable)
            if not self.blocks:
                return _all_held(self.init_full, unidentifiable, warnings, self.rows.size,
                                 self.n_dropped, self.t_compile,
                                 time.perf_counter() - t_start - self.t_compile)
            spec, data = self.spec, self.data(b)
            z0s = self.cast(np.stack([z_from_params(spec, {**self.init_full, **{
                k: v for k, v in p.items() if k not in keys}}, START_MARGIN) for p in points]))
            solve, tc = _compiled("solve", spec, (z0s, data), **self.static)
            self.t_compile += tc
            zs, codes, nsteps, costs, best_i, (J, r) = solve(z0s, data)
            zs, codes, nsteps, costs = (np.asarray(x) for x in (zs, codes, nsteps, costs))
            best_i = int(best_i)
            z, code, cost, iters = zs[best_i], int(codes[best_i]), float(costs[best_i]), \
                iters + int(nsteps[best_i])
            J, r = _r_factor(J), np.asarray(r, dtype=np.float64)
            alternatives = [(zs[i], float(costs[i])) for i in range(len(costs)) if i != best_i]
        if marked and marked[0]:
            unidentifiable += [k for k in dict.fromkeys(marked[0])]
            warnings += marked[1]
        return self._report(b, spec, data, z, code, iters, cost, J, r, warnings,
                            unidentifiable, t_start, starts)

    def residual_variance(self, data: Data, r, spec: Spec) -> float:
        """s^2 of the covariance s^2 (J^T J)^-1: 1 when the residuals were divided
        by a known noise sigma, else chi^2 per degree of freedom (values with
        weight 0 are not observations)."""
        if self.noise_sigma is not None:
            return 1.0
        dof = max(int(np.count_nonzero(np.asarray(data.weights))) - spec.n, 1)
        return float(r @ r) / dof

    def _report(self, b, spec, data, z, code, iters, cost, J, r, warnings, unidentifiable,
                t_start, starts) -> FitResult:
        status = _status(code, z, cost)
        message = optx.RESULTS._index_to_message[code] or "solver tolerances met"
        dof = max(int(np.count_nonzero(np.asarray(data.weights))) - spec.n, 1)
        chi2 = float(r @ r)
        s2 = self.residual_variance(data, r, spec)
        if self.noise_sigma is not None and status == "converged" and chi2 / dof > MAX_REDUCED_CHI2:
            status = "failed"
            message = (f"poor fit: chi^2/dof = {chi2 / dof:.3g} > {MAX_REDUCED_CHI2} for the "
                       "given noise_sigma (a local minimum or a model that cannot explain the "
                       "image; try n_starts > 1)")
        cov_z, sd, _ = _covariance(spec, z, J, s2)
        if not np.all(np.isfinite(cov_z)):
            blind = np.isinf(np.diag(cov_z))
            cov_z = np.zeros_like(cov_z)
            status, message = "failed", (
                "the covariance is not finite (the solution is not finite)" if not blind.any()
                else f"{', '.join(_blocks_of(spec, blind))} does not change the fitted pixels "
                     "(fit with identifiability=True to hold it)")
            sd = np.zeros_like(sd)
        params = _user(spec, z, data)
        at_edge = _frame(spec, z)[3]
        stderr, coords = {}, []
        for blk, sl in spec.slices():
            if blk.key not in unidentifiable:  # marked ambiguous: no error to give
                stderr[blk.key] = sd[sl] if blk.size == 3 else float(sd[sl][0])
            coords += [blk.key] if blk.size == 1 else [f"{blk.key}[{i}]" for i in range(3)]
            if np.any(at_edge[sl]):
                warnings.append(f"{blk.key} = {_fmt(params[blk.key])} is at the bound of "
                                f"[{blk.lower:g}, {blk.upper:g}]; its standard error is half "
                                "a +-1 sigma interval cut by that bound")
        d = np.sqrt(np.maximum(np.diag(cov_z), 1e-300))
        corr = cov_z / np.outer(d, d)
        weights = np.asarray(data.weights, dtype=np.float64)
        used = weights > 0
        if spec.loss == "l2":  # residuals are (model - target) * weight
            model = np.asarray(data.target) + r.reshape(-1, 3) / np.where(used, weights, 1.0)
        else:
            model = np.asarray(render_active(
                {k: self.cast(v) for k, v in params.items()}, data.geometry, data.env,
                data.sphere, material=spec.material, env_type=spec.env_type))
        err = np.where(used, model - np.asarray(data.target), 0.0)
        rmse = np.sqrt(np.sum(err**2, axis=0) / np.maximum(used.sum(axis=0), 1))
        noise = self.noise[0 if b is None else b]
        level = np.sqrt(np.sum(np.where(used, np.asarray(data.target), 0.0) ** 2)
                        / max(used.sum(), 1))
        # A noise-free, perfectly smooth target (a mirror in a constant environment)
        # has noise 0: agreement to 1e-6 of the signal is never called poor.
        scale = max(float(np.sqrt(np.mean(noise**2))), 1e-6 * float(level))
        ratio = float(np.sqrt(np.mean(rmse**2)) / scale) if scale > 0 else 0.0
        if self.noise_sigma is None and status == "converged" and ratio > MAX_NOISE_RATIO:
            status = "failed"
            message = (f"poor fit: the residual RMSE is {ratio:.3g} times the target's noise "
                       "level (Immerkaer estimate): a local minimum or a model that cannot "
                       "explain the image; try n_starts > 1 or other initial values")
        total = time.perf_counter() - t_start
        return FitResult(
            params={k: (np.asarray(params[k]) if np.size(params[k]) > 1 else float(params[k]))
                    for k in spec.material.param_specs()},
            stderr=stderr, free=[blk.key for blk in spec.blocks], unidentifiable=unidentifiable,
            correlation=corr, coordinates=coords, status=status, message=message,
            iterations=iters, cost=cost, image_rmse=rmse, n_pixels=int(self.rows.size),
            n_excluded=self.n_dropped + int(np.sum(~used.all(axis=-1))),
            time_compile=self.t_compile, time_run=max(total - self.t_compile, 0.0),
            warnings=warnings, starts=starts)


def _fmt(v) -> str:
    a = np.asarray(v)
    return f"{float(a):.6g}" if a.ndim == 0 else "[" + ", ".join(f"{x:.6g}" for x in a) + "]"


def _best(costs, zs, xp=np):
    """Index of the lowest finite cost with a finite solution (0 if none)."""
    ok = xp.isfinite(costs) & xp.all(xp.isfinite(zs), axis=1)
    return xp.argmin(xp.where(ok, costs, xp.inf))


def _status(code: int, z, cost) -> str:
    if not (np.all(np.isfinite(z)) and np.isfinite(cost)):
        return "failed"
    if code == 0:
        return "converged"
    if code == int(optx.RESULTS.nonlinear_max_steps_reached._value):
        return "max_steps"
    return "failed"


def _user(spec: Spec, z, data: Data) -> dict:
    """User values (NumPy float64) of coordinates ``z`` plus the fixed values."""
    p = params_from_z(spec, np.asarray(z, dtype=np.float64),
                      {k: np.asarray(v, dtype=np.float64) for k, v in data.fixed.items()})
    return {k: np.asarray(v) for k, v in p.items()}


def _blocks_of(spec: Spec, flags: np.ndarray) -> list[str]:
    return [b.key for b, sl in spec.slices() if np.any(flags[sl])]


def _jac_res(spec, z, data):
    """(R (n, n), residuals (N,), compile seconds) at ``z``, as float64 NumPy.

    R is the Jacobian's R factor (``_jacobian_r``); diagnostics and
    covariances are computed in float64, whatever the fit's dtype.
    """
    z = jnp.asarray(z, dtype=data.target.dtype)
    exe, tc = _compiled("jacres", spec, (z, data))
    R, r = exe(z, data)
    return _r_factor(R), np.asarray(r, dtype=np.float64), tc


def _dead_columns(spec: Spec, z, J) -> np.ndarray:
    """Coordinates whose parameter cannot change the fitted pixels (bool (n,)).

    ``J``: the Jacobian (N, n) or its R factor (same column norms); likewise
    for ``_unidentifiable_at`` (same singular values and J^T J).

    Each column is measured in user units times the parameter's natural scale
    (``transforms.natural_scale``), so a coordinate saturated near a box edge
    is not mistaken for a parameter without effect.
    """
    # float64 throughout: in float32 the 1e-300 guard below would round to 0.
    _, dxdz, scale, _ = _frame(spec, z)
    J = np.asarray(J, dtype=np.float64)
    effect = np.linalg.norm(J, axis=0) / np.maximum(dxdz, 1e-300) * scale
    # A coordinate run off to a box edge has no slope left; that is "at bound"
    # (reported as such), not evidence that the parameter has no effect.
    saturated = np.abs(np.asarray(z, dtype=np.float64)) > SATURATED_Z
    return (effect <= ZERO_COLUMN * max(effect.max(), 1e-300)) & ~saturated


def _unidentifiable_at(spec, z, J, s2: float):
    """Blocks without usable information at ``z``: (keys, reasons) or None.

    ``s2``: the residual variance of the covariance (``_Job.residual_variance``).
    """
    keys, reasons = [], []
    J = np.asarray(J, dtype=np.float64)
    if not np.all(np.isfinite(J)):
        return None
    norms = np.linalg.norm(J, axis=0)
    dead = _dead_columns(spec, z, J)
    for k in _blocks_of(spec, dead):
        keys.append(k)
        reasons.append(f"{k} does not change the fitted pixels at the solution; held at its "
                       "initial value")
    # Columns run off to a box edge carry no slope (reported as at bound); a
    # zero-norm column would make the normalized SVD below NaN.
    live = ~dead & (np.abs(np.asarray(z, dtype=np.float64)) <= SATURATED_Z) & (norms > 0)
    if live.sum() >= 2:
        Jn = J[:, live] / norms[live]
        _, sv, vt = np.linalg.svd(Jn, full_matrices=False)
        cond = sv[0] / max(sv[-1], 1e-300)
        if cond > MAX_CONDITION:
            idx = np.nonzero(live)[0][int(np.argmax(np.abs(vt[-1])))]
            flag = np.zeros_like(dead)
            flag[idx] = True
            for k in _blocks_of(spec, flag):
                if k not in keys:
                    keys.append(k)
                    reasons.append(f"{k} is not separable from the other parameters "
                                   f"(Jacobian condition number {cond:.2g}); held at its "
                                   "initial value")
    if s2 > 0 and not keys:
        _, _, span = _covariance(spec, z, J, s2)
        loose = span > MAX_SPAN
        for k in _blocks_of(spec, loose):
            keys.append(k)
            reasons.append(f"{k} is not constrained by the image (standard error larger than "
                           "its whole range); held at its initial value")
    return (keys, reasons) if keys else None


def _ambiguous(spec: Spec, z, J, s2: float, cost: float, alternatives):
    """Parameters other starts place elsewhere at an equally good cost: (keys, reasons) or None.

    The covariance at the best start is a local, linear statement. Another
    start that ends within the ``AMBIGUOUS_LEVEL`` joint confidence region
    (chi^2 above the best by less than that quantile q of chi^2 with n degrees
    of freedom) but more than sqrt(q) standard errors away in a coordinate --
    outside the region's projection, were the cost quadratic -- shows the
    image does not determine that parameter: measured at m = 1e-3 on
    32^2 (m = 0.0054 +- 0.0001 by one start, 0.003 by another, delta chi^2 =
    6.6) and at eta = 1 (m = 1.0 +- 0.09 against 0.003, delta chi^2 = 2.7).
    """
    from scipy.stats import chi2

    alternatives = [(za, ca) for za, ca in alternatives
                    if np.isfinite(ca) and np.all(np.isfinite(za))]
    if not alternatives:
        return None
    if not s2 > 0:
        return None
    cov, sd, _ = _covariance(spec, z, J, s2)
    level = chi2.ppf(AMBIGUOUS_LEVEL, spec.n)
    # Were the cost quadratic, no point of the region would lie further than
    # sqrt(level) standard errors from the best in any coordinate (the
    # projection of the ellipsoid): beyond that is evidence, not chance.
    reach = np.sqrt(level * np.diag(cov))
    x = _frame(spec, z)[0]
    keys, reasons = [], []
    for za, ca in alternatives:
        if ca - cost > 0.5 * s2 * level:
            continue
        xa = _frame(spec, za)[0]
        far = np.abs(_fit_coordinates(spec, z, za)) > reach
        for key in _blocks_of(spec, far):
            if key in keys:
                continue
            sl = dict((blk.key, sl) for blk, sl in spec.slices())[key]
            keys.append(key)
            reasons.append(f"{key} is not determined by the image: another start fits as well "
                           f"(chi^2 {2.0 * (ca - cost) / s2:+.2g}) at {_fmt(xa[sl])} against "
                           f"{_fmt(x[sl])} +- {_fmt(sd[sl])}")
    return (keys, reasons) if keys else None


def _frame(spec: Spec, z):
    """Per coordinate at ``z``, float64 (n,) each: the user value x, dx/dz, the
    natural scale (``transforms.natural_scale``) and whether x is at a bound
    (within ``AT_BOUND`` of its box's edge, in log for a log box)."""
    z = np.asarray(z, dtype=np.float64)
    parts = []
    for b, sl in spec.slices():
        x = transforms.to_user(b.transform, z[sl], b.lower, b.upper)
        u = transforms.box_fraction(b.transform, x, b.lower, b.upper)
        parts.append((x, transforms.derivative(b.transform, z[sl], b.lower, b.upper),
                      transforms.natural_scale(b.transform, x, b.lower, b.upper),
                      (u < AT_BOUND) | (u > 1.0 - AT_BOUND)))
    return tuple(np.concatenate([np.atleast_1d(p[i]) for p in parts]) for i in range(4))


def _fit_coordinates(spec: Spec, z, za) -> np.ndarray:
    """``za - z`` in the coordinates of ``_covariance`` at ``z``: z, or
    x / natural_scale for a value at its bound."""
    x, _, scale, edge = _frame(spec, z)
    d = np.asarray(za, dtype=np.float64) - np.asarray(z, dtype=np.float64)
    return np.where(edge, (_frame(spec, za)[0] - x) / scale, d)


def _covariance(spec: Spec, z, J, s2: float):
    """Covariance of the fitted coordinates and the +-1 sigma interval of each parameter.

    Returns (cov (n, n), stderr (n,), span (n,)). Interior coordinates are z;
    a value at its bound (``AT_BOUND``) uses u = x / natural_scale instead (J
    column divided by dx/dz, times the scale), as dx/dz -> 0 there would make
    its error vanish, a confidence the image never gave. A column with no
    slope at all gets an infinite variance, not pinv's 0.

    ``stderr`` is half the width of the coordinate's +-1 sigma interval mapped
    to the parameter and clipped to its box: the delta method when that
    interval is small, and honest when it reaches a box edge (z = -5 +- 5 is
    rho in [4e-5, 0.5], not 0.0067 +- 0.033). ``span`` is the interval's width
    as a fraction of the box (for log boxes, in log). ``J`` may be the
    Jacobian's R factor (same J^T J).
    """
    z = np.asarray(z, dtype=np.float64)
    x, dxdz, scale, edge = _frame(spec, z)
    J = np.array(J, dtype=np.float64)
    J[:, edge] *= (scale / np.where(dxdz > 0, dxdz, np.inf))[edge]
    cov = s2 * np.linalg.pinv(J.T @ J, hermitian=True)
    blind = np.linalg.norm(J, axis=0) == 0
    cov[blind, :] = cov[:, blind] = 0.0
    cov[blind, blind] = np.inf
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    finite = np.isfinite(sd)
    d = np.where(finite, sd, 1e300)
    lo, hi = np.empty(spec.n), np.empty(spec.n)
    for b, sl in spec.slices():
        lo[sl] = transforms.to_user(b.transform, z[sl] - d[sl], b.lower, b.upper)
        hi[sl] = transforms.to_user(b.transform, z[sl] + d[sl], b.lower, b.upper)
        lo[sl] = np.where(edge[sl], np.clip(x[sl] - d[sl] * scale[sl], b.lower, b.upper), lo[sl])
        hi[sl] = np.where(edge[sl], np.clip(x[sl] + d[sl] * scale[sl], b.lower, b.upper), hi[sl])
    span = np.concatenate([np.atleast_1d(
        transforms.box_fraction(b.transform, hi[sl], b.lower, b.upper)
        - transforms.box_fraction(b.transform, lo[sl], b.lower, b.upper))
        for b, sl in spec.slices()])
    return cov, np.where(finite, 0.5 * (hi - lo), np.inf), np.where(finite, span, 1.0)


def _all_held(init_full, unidentifiable, warnings, n_pix, n_drop, tc, tr) -> FitResult:
    return FitResult(
        params={k: (np.asarray(v) if np.size(v) > 1 else float(v)) for k, v in init_full.items()},
        stderr={}, free=[], unidentifiable=unidentifiable, correlation=np.zeros((0, 0)),
        coordinates=[], status="failed", message="no parameter is identifiable from this image",
        iterations=0, cost=float("nan"), image_rmse=np.full(3, np.nan), n_pixels=n_pix,
        n_excluded=n_drop, time_compile=tc, time_run=tr, warnings=warnings)

"""The compiled solve: traced once per problem structure and shapes, kept in
this process (and on disk through ``_cache``) for every later fit."""

from __future__ import annotations

import functools
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

from .._keep import hold
from .._math import to_device
from ..blasthreads import catch_up
from ..compilation_cache import FAST_COMPILE
from . import _valley
from ._cache import compile_cached, lower_cached
from ._problem import Spec, residuals
from ._solvers import make_solver, result_code

#: XLA options of every fit executable (``compilation_cache.FAST_COMPILE``:
#: half the compile, same speed; the solve's outputs change by <= 4e-10
#: relative, the solver stopping elsewhere within its tolerance).
FAST_XLA_OPTIONS = FAST_COMPILE
#: XLA options for the solver loops. Loop-invariant code motion hoists the
#: parameter-independent parts of every sample (masks, G, 1/cos) out of the
#: solver's while loop into separate, unfused passes over (lights, pixels,
#: samples) arrays: measured +30 ms per LM fit at 256^2 with 4x4 samples
#: (fixed cost 45 -> 15 ms), for no gain per step.
SOLVE_XLA_OPTIONS = {**FAST_XLA_OPTIONS,
                     "xla_disable_hlo_passes": "while-loop-invariant-code-motion"}
#: The solver loops of a material of specular lobes only (ray-traced radiance
#: with envmap lookups: the dielectric's bounce graphs are large and their run
#: is gathers and libm calls) with LLVM's optimisation at level 1: the shipped
#: dielectric's first run 4.22 -> 4.02 s, compiled 1.26 -> 1.25 s
#: (``dielectric.py --repeat 3``, same run); ``configs/mirror.toml`` unchanged
#: (first 1.52-1.60 s, compiled 0.13-0.14 s either way). Not for opaque lobes:
#: env_plastic's compiled fit 1.47 -> 1.78 s, the 128^2 point-lit plastic 0.45
#: -> 0.86 s.
SPECULAR_SOLVE_XLA_OPTIONS = {**SOLVE_XLA_OPTIONS, "xla_backend_optimization_level": 1}
#: XLA options for code run once on few pixels (the start's dead-column check):
#: LLVM's optimisation off too cuts its compile again (dielectric: 1.2 ->
#: 0.4 s, running 24 -> 64 ms; values differ by ~2e-11 relative, and only test
#: a column for zero).
ONCE_XLA_OPTIONS = {**FAST_XLA_OPTIONS, "xla_backend_optimization_level": 0}

_COMPILED: dict = {}
#: ``_COMPILED`` keeps the most recently used this many: a process fitting images of
#: ever new shapes (a batch worker) kept every executable it compiled.
KEEP_COMPILED = 32


def _hold(key, exe) -> None:
    """``exe`` under ``key`` in ``_COMPILED`` as the most recently used
    (``fitter._keep.hold``: beyond ``KEEP_COMPILED`` the least recently used go)."""
    hold(_COMPILED, key, exe, KEEP_COMPILED)


def jacobian_r(spec: Spec, z, data):
    """(R, r) at ``z``: the Jacobian's R factor (n, n) and the residuals (N,).

    J = Q R has J's column norms, singular values and Gram matrix J^T J =
    R^T R, all that the diagnostics need, without moving the (N, n) Jacobian
    to the host. A float32 fit (traced without x64) returns J itself; the
    host factors it in float64 (``r_factor``).
    """
    J, r = jax.jacfwd(lambda z: (residuals(z, data, spec),) * 2, has_aux=True)(z)
    if J.dtype == jnp.float64:
        J = jnp.linalg.qr(J, mode="r")
    return J, r


def jacobian_full(spec: Spec, z, data):
    """(J (N, n), r (N,)) at ``z``: the whole Jacobian, for the block sandwich
    covariance (``_adequacy.sandwich``), which needs J's rows."""
    return jax.jacfwd(lambda z: (residuals(z, data, spec),) * 2, has_aux=True)(z)


#: ``residuals_at`` evaluates points side by side while their scene arrays
#: (the fitted geometry's elements, times the points) stay under this: at 128^2
#: with 4x4 samples and 2 lights (3.3 M elements) 6 at once; from about 256^2
#: one at a time, the memory of one residual evaluation. Measured on the
#: quickstart's 36 profile points: 75 ms, against 160 ms one at a time with
#: loop-invariant code motion (as before) and 100 ms without.
MAP_BATCH_ELEMENTS = 2 * 10**7
#: Points per evaluation under an environment lighting opaque lobes, where the
#: sky table has over ``SKY_BATCH_ELEMENTS`` elements: the sky sum reads its
#: whole table (0.4 GB at 128^2) per evaluation, so several points share one
#: pass (env_plastic's 36 points on every pixel: 1.01 s one by one, 0.89 s six
#: at a time, for ~0.1 GB more). 6 divides the profile's 6 (n + 1) points, so
#: no second body is compiled for a remainder. A smaller table (the cost
#: profile's pixel subset with its own samples' rows, 12 M elements) goes one
#: point at a time: 0.20-0.21 s against 0.21-0.24 s, and its executable
#: compiles in 0.44-0.51 CPU-s instead of 0.74-0.78 (no batched graph).
SKY_BATCH = 6
SKY_BATCH_ELEMENTS = 2**25


def residuals_at(spec: Spec, zs, data, single: bool = False):
    """Residuals (k, N) at each point of ``zs`` (k, n), a few points at a time
    (``lax.map``: ``SKY_BATCH`` with a large sky table, else ``MAP_BATCH_ELEMENTS``;
    no Jacobian). ``single``: the model in float32 (``residuals``'; ``_profile``'s
    estimates)."""
    if data.geometry.has_sky:
        batch = SKY_BATCH if np.size(data.geometry.env_color) > SKY_BATCH_ELEMENTS else 1
    else:
        size = sum(np.size(a) for a in jax.tree_util.tree_leaves(data.geometry))
        batch = MAP_BATCH_ELEMENTS // max(size, 1)
    k = zs.shape[0]
    loops = -(-k // int(max(1, min(k, batch))))
    batch = -(-k // loops)
    # Padded with copies of the last point to loops x batch: lax.map compiles a
    # second body for a remainder.
    zs = jnp.concatenate([zs, jnp.broadcast_to(zs[-1:], (loops * batch - k, zs.shape[1]))])
    return jax.lax.map(lambda z: residuals(z, data, spec, single), zs,
                       batch_size=batch if batch > 1 else None)[:k]


def residuals_at_rows(spec: Spec, zs, data, rows, single: bool = False):
    """``residuals_at`` on the fitted pixels ``rows`` (M,) only, (k, 3M):
    picked inside the executable (``Geometry.take``), not copied on the host
    (~20 ms of a compiled 256^2 fit's profile)."""
    data = data._replace(geometry=data.geometry.take(rows), target=data.target[rows],
                         weights=data.weights[rows])
    return residuals_at(spec, zs, data, single)


def gauss_newton_step(spec: Spec, z, data):
    """At ``z``: (R (n, n), r (N,), J (N, n), the Gauss-Newton step dz (n,), cost).

    dz solves the normal equations J^T J dz = -J^T r (Cholesky; p x p, as
    the solvers' ``_solvers._normal``)."""
    J, r = jacobian_full(spec, z, data)
    dz = -jax.scipy.linalg.solve(J.T @ J, J.T @ r, assume_a="pos")
    return jnp.linalg.qr(J, mode="r"), r, J, dz, 0.5 * jnp.sum(r * r)


def r_factor(J) -> np.ndarray:
    """R factor (n, n) in float64 of a Jacobian, or R itself, from ``jacobian_r``."""
    J = np.asarray(J, dtype=np.float64)
    return J if J.shape[0] == J.shape[1] else np.linalg.qr(J, mode="r")


def best_start(costs, zs, xp=np):
    """Index of the lowest finite cost with a finite solution (0 if none)."""
    ok = xp.isfinite(costs) & xp.all(xp.isfinite(zs), axis=1)
    return xp.argmin(xp.where(ok, costs, xp.inf))


def _solve_fn(spec: Spec, solver_name: str, rtol: float, atol: float, max_steps: int):
    """Compiled entry: starts (S, n) -> (z, code, steps, cost) per start, the
    best start's index, and ``jacobian_r`` there (the diagnostics)."""
    # A conductor's eta, k are solved along their circles of equal F0 (``_valley``):
    # the solver's coordinates w, the fit's z = to_z(w) everywhere else. In float64
    # only: a small eta is the difference of the circle's centre and radius (gold's
    # red: 34.7 - 34.5), and float32 lost the fit (its Jacobian NaN).
    charts = _valley.charts(spec)

    def one(z0, data):
        # optimistix only when tracing (0.5 s to import): a cached trace does without it
        import optimistix as optx

        chs = charts if z0.dtype == jnp.float64 else ()

        def fn(w, data):
            return residuals(_valley.to_z(w, chs), data, spec)

        solver = make_solver(solver_name, rtol, atol)
        sol = optx.least_squares(fn, solver, _valley.to_w(z0, chs), args=data,
                                 max_steps=max_steps, throw=False)
        z = _valley.to_z(sol.value, chs)
        info = getattr(sol.state, "f_info", None)
        # optimistix's solver state is not public API: anything else falls back.
        residual_jac = getattr(getattr(optx, "FunctionInfo", None), "ResidualJac", ())
        if residual_jac and isinstance(info, residual_jac):
            # Gauss-Newton family: the solver's last accepted linearisation is at
            # sol.value; materialising it costs n cheap tangents, not a new Jacobian
            # (in w: times dw/dz, n x n).
            r, J = info.residual, info.jac.as_matrix()
            if chs:
                J = J @ jax.jacfwd(lambda v: _valley.to_w(v, chs))(z)
        else:
            J, r = jacobian_full(spec, z, data)
        # The whole J too: the covariance's block sandwich needs its rows
        # (``jac_full``), and returning it spares a linearisation after the fit.
        jr = (jnp.linalg.qr(J, mode="r") if J.dtype == jnp.float64 else J, r, J)
        return (z, result_code(sol.result), sol.stats["num_steps"],
                0.5 * jnp.sum(r * r), jr)

    def many(z0s, data):
        zs, codes, steps, costs, (Rs, rs, Js) = jax.lax.map(lambda z0: one(z0, data), z0s)
        best = best_start(costs, zs, jnp)
        return zs, codes, steps, costs, best, (Rs[best], rs[best], Js[best])

    return many


def _batch_fn(spec: Spec, batch: str, **static):
    """One start per target: ``(z0, data with stacked targets/weights) -> stacked results``."""
    one = _solve_fn(spec, **static)

    def single(z0, target, weights, data):
        zs, codes, steps, costs, _, jr = one(z0[None], data._replace(target=target,
                                                                   weights=weights))
        return zs[0], codes[0], steps[0], costs[0], jr[:2]  # (R, r): B whole Js are large

    def run(z0, data):
        if batch == "vmap":
            return jax.vmap(single, in_axes=(None, 0, 0, None))(z0, data.target, data.weights, data)
        return jax.lax.map(lambda tw: single(z0, tw[0], tw[1], data), (data.target, data.weights))

    return run


#: dtype -> its name (``str`` of a dtype took 10 us, ~230 times a compiled fit).
_NAMES: dict = {}


def _name(a) -> str:
    dt = a.dtype if hasattr(a, "dtype") else jnp.result_type(a)
    name = _NAMES.get(dt)
    if name is None:
        name = _NAMES[dt] = str(dt)
    return name


def _key(kind: str, spec: Spec, args, once: bool, static: dict):
    # Flattened, not a tree of (shape, dtype) made into a string: 0.1 ms, not 1.1
    # ms, four times in a compiled fit.
    leaves, tree = jax.tree_util.tree_flatten(args)
    shapes = tuple((np.shape(a), _name(a)) for a in leaves)
    return (kind, spec, tuple(sorted(static.items())), str(tree), shapes, once)


def _function(kind: str, spec: Spec, static: dict):
    if kind == "solve":
        return _solve_fn(spec, **static)
    if kind == "batch":
        return _batch_fn(spec, **static)
    if kind == "jacfull":
        return functools.partial(jacobian_full, spec)
    if kind == "gauss_newton":
        return functools.partial(gauss_newton_step, spec)
    if kind == "residuals":
        return functools.partial(residuals_at, spec, **static)
    if kind == "rows":
        return functools.partial(residuals_at_rows, spec, **static)
    return functools.partial(jacobian_r, spec)  # the Jacobian (as its R factor) and residuals


def _options(kind: str, once: bool, spec: Spec) -> dict:
    # (residuals_at's loop, like the solver's, runs 2x faster without LICM)
    if once:
        return ONCE_XLA_OPTIONS
    if kind in ("jacres", "jacfull", "gauss_newton"):
        return FAST_XLA_OPTIONS
    if all(lb.kind == "specular" for lb in spec.material.lobe_objects):
        return SPECULAR_SOLVE_XLA_OPTIONS
    return SOLVE_XLA_OPTIONS


def _x64(args) -> bool:
    """Whether to trace with x64: optimistix creates some constants (e.g. LM's
    damping) as Python floats, which x64 would make float64, so a float32 fit is
    traced with x64 off (a thread-local setting)."""
    return jnp.result_type(args[0]) != jnp.float32


def _build(kind: str, spec: Spec, args, once: bool, static: dict, key):
    with jax.enable_x64(_x64(args)):
        exe = compile_cached(_function(kind, spec, static), args, repr(key),
                             _options(kind, once, spec))
    catch_up()  # a first lowering of a LAPACK op loads SciPy's OpenBLAS
    return exe


def _compile_lowered(lowered, options: dict, x64: bool):
    with jax.enable_x64(x64):
        return lowered.compile(options)


#: Executables being compiled on a thread (``compile_ahead``): {key: (thread, [executable])}.
_PENDING: dict = {}


def compile_ahead(kind: str, spec: Spec, args, once: bool = False, behind: bool = False,
                  **static) -> None:
    """Trace what ``compiled(kind, spec, args, once, **static)`` will ask for
    here and start XLA's compile of it on a thread, which releases the
    interpreter: the caller's next work (tracing and compiling a check) runs
    beside it, and ``compiled`` then waits for it.

    The same function, options and shapes make the same executable, so a fit
    gives the same result either way. A guess that turns out wrong (other
    shapes or structure when asked) is only compile time spent; a failure
    here or on the thread is compiled again where asked. ``wait`` joins the
    threads. ``behind``: compile after the compiles started ahead before it
    (needed first: the solve's).
    """
    key = _key(kind, spec, args, once, static)
    if key in _COMPILED or key in _PENDING:
        return
    x64 = _x64(args)
    try:
        with jax.enable_x64(x64):
            lowered = lower_cached(_function(kind, spec, static), args, repr(key))
    except Exception:  # noqa: BLE001 (traced again, and any error raised, where asked)
        return
    catch_up()
    box: list = []
    first = [t for t, _ in _PENDING.values()] if behind else []

    def run():
        for t in first:
            t.join()
        try:
            box.append(_compile_lowered(lowered, _options(kind, once, spec), x64))
        except Exception:  # noqa: BLE001 (compiled again, and any error raised, where asked)
            pass

    thread = threading.Thread(target=run, name="fitter-compile-ahead", daemon=True)
    _PENDING[key] = (thread, box)
    thread.start()


def wait() -> None:
    """Join every ``compile_ahead`` thread; keep what they compiled for later fits."""
    for key, (thread, box) in list(_PENDING.items()):  # (or fits on other threads)
        thread.join()
        _PENDING.pop(key, None)
        if box and key not in _COMPILED:
            _hold(key, box[0])


def compiled(kind: str, spec: Spec, args, once: bool = False, **static):
    """Compile (once per structure and shapes) and return (executable, seconds spent).

    ``kind``: ``"solve"`` (multi-start solve of one target), ``"batch"`` (one
    start per stacked target), ``"jacres"`` (``jacobian_r``), ``"jacfull"``
    (``jacobian_full``), ``"gauss_newton"`` (``gauss_newton_step``),
    ``"residuals"`` (``residuals_at``) or ``"rows"`` (``residuals_at_rows``).
    ``once``: the code runs once on few pixels: compiled with ``ONCE_XLA_OPTIONS``.
    One started by ``compile_ahead`` is waited for (seconds: the wait).
    """
    key = _key(kind, spec, args, once, static)
    if key in _COMPILED:
        exe = _COMPILED[key]
        _hold(key, exe)  # the most recently used
        return exe, 0.0
    t0 = time.perf_counter()
    ahead = _PENDING.pop(key, None)
    if ahead is not None:
        ahead[0].join()
    exe = ahead[1][0] if ahead is not None and ahead[1] else _build(kind, spec, args, once,
                                                                     static, key)
    _hold(key, exe)
    return exe, time.perf_counter() - t0


def jac_res(spec: Spec, z, data, once: bool = False):
    """(R (n, n), residuals (N,), compile seconds) at ``z``, as float64 NumPy.

    R is the Jacobian's R factor (``jacobian_r``); diagnostics and
    covariances are computed in float64, whatever the fit's dtype.
    ``once``: as ``compiled``'s (a check that runs once on few pixels).
    """
    z = jnp.asarray(z, dtype=data.target.dtype)
    exe, tc = compiled("jacres", spec, (z, data), once=once)
    R, r = exe(z, data)
    return r_factor(R), np.asarray(r, dtype=np.float64), tc


def residuals_at_points(spec: Spec, zs, data, single: bool = False) -> np.ndarray:
    """Residuals (k, N) at each point of ``zs`` (k, n), float64 on the host
    (``single``: evaluated in float32, as ``residuals_at``)."""
    zs = jnp.asarray(zs, dtype=data.target.dtype)
    exe, _ = compiled("residuals", spec, (zs, data), **_single(single))
    return np.asarray(exe(zs, data), dtype=np.float64)


def residuals_of_rows(spec: Spec, zs, data, rows, single: bool = False) -> np.ndarray:
    """Residuals (k, 3M) of the fitted pixels ``rows`` (M,) at each point of
    ``zs`` (k, n), float64 on the host (``residuals_at_rows``; ``single``: as
    ``residuals_at``)."""
    # (int32 rows: a float32 fit traces without 64-bit types, where int64 warned)
    zs, rows = jnp.asarray(zs, dtype=data.target.dtype), to_device(np.asarray(rows, np.int32))
    exe, _ = compiled("rows", spec, (zs, data, rows), **_single(single))
    return np.asarray(exe(zs, data, rows), dtype=np.float64)


def _single(single: bool) -> dict:
    # (no key entry when off: the float64 executables keep their keys)
    return {"single": True} if single else {}


def costs_at(spec: Spec, zs, data) -> np.ndarray:
    """Half the sum of squared residuals (k,) at each point of ``zs`` (k, n),
    summed in float64 on the host whatever the fit's dtype."""
    r = residuals_at_points(spec, zs, data)
    return 0.5 * np.sum(r * r, axis=1)


#: The last solution's whole Jacobian (``remember_jacobian``): one only, and
#: dropped once used (at 1024^2 one is ~130 MB), with what it was made from.
_JACOBIANS: list = []


def _snapshot(a):
    """``a`` as it is now: a device array itself (immutable), a host array's
    read-only view, or a copy of a writable one (the caller may change it later)."""
    if isinstance(a, jax.Array):
        return a
    v = np.asarray(a)
    return v.copy() if v.flags.writeable else v


def _same(a, b) -> bool:
    if a is b:  # the same device array (``Problem.data`` hands out the same ones)
        return True
    a, b = np.asarray(a), np.asarray(b)
    return (a.shape == b.shape and a.dtype == b.dtype
            and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))


def _made_from(spec: Spec, z, data):
    """What a remembered Jacobian was made from: compared, not hashed (a hash of the
    target and weights took ~8 ms of a compiled 256^2 fit; a comparison is a memcmp)."""
    return (spec, _snapshot(z), _snapshot(data.target), _snapshot(data.weights),
            {k: _snapshot(v) for k, v in data.fixed.items()})


def _is_made_from(made, spec: Spec, z, data) -> bool:
    spec0, z0, target, weights, fixed = made
    return (spec0 == spec and _same(z0, z) and _same(target, data.target)
            and _same(weights, data.weights) and fixed.keys() == data.fixed.keys()
            and all(_same(v, data.fixed[k]) for k, v in fixed.items()))


def remember_jacobian(spec: Spec, z, data, J, r) -> None:
    """Keep the solver's last linearisation (J (N, n), r (N,)) at its solution
    ``z``, so that ``jac_full`` there returns it instead of linearising again."""
    _JACOBIANS[:] = [(_made_from(spec, z, data), np.asarray(J, dtype=np.float64),
                      np.asarray(r, dtype=np.float64))]


def jac_full(spec: Spec, z, data):
    """(J (N, n), residuals (N,), compile seconds) at ``z``, float64 NumPy.

    The solver's own linearisation when ``z`` is a solution it returned
    (``remember_jacobian``: the same J, spared a second linearisation)."""
    if _JACOBIANS and _is_made_from(_JACOBIANS[0][0], spec, z, data):
        _, J, r = _JACOBIANS.pop()
        return J, r, 0.0
    z = jnp.asarray(z, dtype=data.target.dtype)
    exe, tc = compiled("jacfull", spec, (z, data))
    J, r = exe(z, data)
    return np.asarray(J, dtype=np.float64), np.asarray(r, dtype=np.float64), tc

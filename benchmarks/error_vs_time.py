"""Error against run time for one (case, resolution, method): a worker of ``benchmarks/run.py``.

Sampling along the optimization: each method is driven step by step and the
parameters are recorded after every iteration, with the wall-clock time spent
in the solver so far (recording excluded, compile excluded and reported
separately):

* JAX methods (the project's solvers): the same optimistix solver, residuals
  and coordinates as ``fitter.fit`` (``fitter.fit._problem``,
  ``fitter.fit._solvers``), driven by ``solver.init`` / ``solver.step`` /
  ``solver.terminate`` each jit-compiled once -- the loop body of
  ``optimistix.least_squares``, dispatched from Python once per step. Where
  ``fitter.fit`` starts coarse (LM on a large image, ``fitter.fit._coarse``),
  so does the trace: LM steps on the 2 x 2 averaged image, then the
  full-size Gauss-Newton steps, each recorded; the fastest of
  ``TRACE_REPEATS`` traces is kept. The product's own figures (``fitter.fit``
  cold: compile + run; warm: run, the least of ``WARM_REPEATS``) are
  measured in the same process.
* scipy (baseline A): ``least_squares``'s per-iteration ``callback``.
* Mitsuba (baseline B): one record per Adam iteration.

Errors are recorded against the case's truth; the image RMSE of every sample
is computed afterwards with the JAX forward model at the recorded parameters
over the fitted (interior) pixels, so the metric is the same for every method.
"""

from __future__ import annotations

import os
import time

import numpy as np

#: Cases: the shipped Mitsuba case (``fitter.cases``) and the common start.
CASES = {
    "lambert": {"init": {"lambert.rho_d": [0.5, 0.5, 0.5]}},
    "oren_nayar": {"init": {"oren_nayar.rho_d": [0.3, 0.3, 0.3], "oren_nayar.sigma": 0.2}},
    "phong": {"init": {"phong.rho_s": [0.5, 0.5, 0.5], "phong.e": 20.0}},
    "torrance_sparrow": {"init": {"torrance_sparrow.m": 0.4, "torrance_sparrow.eta": 1.3}},
    "mirror": {"init": {"mirror.rho_m": [0.5, 0.5, 0.5]}},
    "plastic": {"init": {"lambert.rho_d": [0.5, 0.5, 0.5], "torrance_sparrow.m": 0.3,
                         "torrance_sparrow.eta": 1.3}},
    "oren_nayar_phong": {"init": {"oren_nayar.rho_d": [0.5, 0.5, 0.5], "oren_nayar.sigma": 0.1,
                                  "phong.rho_s": [0.5, 0.5, 0.5], "phong.e": 40.0}},
    "dielectric": {"init": {"dielectric.eta": 1.3, "dielectric.attenuation": [0.5, 0.5, 0.5]}},
}
#: Methods: the project's solvers and the two baselines.
JAX_METHODS = {"lm": "levenberg_marquardt", "dogleg": "dogleg", "bfgs": "bfgs", "adam": "adam"}
BASELINES = ("scipy", "mitsuba")
#: Baselines port only this material (lambert + torrance_sparrow, Smith G).
BASELINE_CASE = "plastic"
#: Relative error floor: a parameter whose truth is below it is compared absolutely.
REL_FLOOR = 1e-3
RTOL, ATOL = 1e-8, 1e-10
#: ``fitter.fit``'s compiled figures: the least time of this many calls.
WARM_REPEATS = 5
#: The JAX methods' step traces: the fastest of this many runs.
TRACE_REPEATS = 3
TRACE_STEPS = {"lm": 100, "dogleg": 100, "bfgs": 400, "adam": 1500}


def repo_root() -> str:
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_job(case: str, res: int):
    """(job, base_dir) of a shipped case at ``res`` x ``res``."""
    from fitter.config import job_from_dict
    from fitter.cases import CASES as SHIPPED

    base = os.path.join(repo_root(), "data_synthetic", case)
    job = job_from_dict(SHIPPED[case], base_dir=base)
    return job.replace(scene=job.scene.replace(width=res, height=res)), base


def errors(x: dict, truth: dict, keys) -> dict:
    """``{coordinate: (value, truth, abs err, rel err)}`` of the free parameters."""
    out = {}
    for k in keys:
        v, t = np.atleast_1d(np.asarray(x[k], float)), np.atleast_1d(np.asarray(truth[k], float))
        for i in range(v.size):
            name = k if v.size == 1 else f"{k}[{i}]"
            a = abs(v[i] - t[i])
            out[name] = (float(v[i]), float(t[i]), float(a), float(a / max(abs(t[i]), REL_FLOOR)))
    return out


def _vec_to_params(x):
    return {"lambert.rho_d": x[:3], "torrance_sparrow.m": x[3], "torrance_sparrow.eta": x[4]}


def _params_to_vec(p):
    return np.concatenate([np.asarray(p["lambert.rho_d"], float).reshape(3),
                           [float(p["torrance_sparrow.m"]), float(p["torrance_sparrow.eta"])]])


class _Problem:
    """The fit problem exactly as ``fitter.fit`` sets it up (interior pixels, l2)."""

    def __init__(self, job, base, target, init):
        from fitter.fit._setup import Problem

        fit_job = Problem.make(target[None], job.scene, job.material, init=init, fixed=job.fixed,
                               base_dir=base)
        self.renderer, self.init_full = fit_job.renderer, fit_job.init_full
        self.free = [b.key for b in fit_job.blocks]
        self.spec, self.data = fit_job.spec, fit_job.data(0)
        self.n_pixels = int(fit_job.rows.size)
        self._z0 = fit_job.z_init()

    def z0(self):
        return self._z0

    def params(self, z):
        import jax.numpy as jnp

        from fitter.fit._problem import params_from_z

        p = params_from_z(self.spec, jnp.asarray(z), self.data.fixed)
        return {k: np.asarray(v) for k, v in p.items()}

    def rmse_fn(self):
        """Jitted (complete params) -> RMSE over the fitted pixels."""
        import jax
        import jax.numpy as jnp

        from fitter.render import render_active

        spec, data = self.spec, self.data

        @jax.jit
        def f(params):
            m = render_active(params, data.geometry, data.env, data.sphere,
                              material=spec.material, env_type=spec.env_type)
            return jnp.sqrt(jnp.mean((m - data.target) ** 2))

        return lambda p: float(f({k: jnp.asarray(v) for k, v in p.items()}))


def stepper(problem: _Problem, solver_name: str, rtol: float = RTOL, atol: float = ATOL):
    """(init(z) -> state, step(z, state) -> (z, state, done), compile seconds)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    from fitter.fit._problem import residuals
    from fitter.fit._solvers import make_solver

    spec, data = problem.spec, problem.data
    solver = make_solver(solver_name, rtol, atol)
    scalar = isinstance(solver, optx.AbstractMinimiser)

    def fn(z, d):
        r = residuals(z, d, spec)
        return (0.5 * jnp.sum(r * r) if scalar else r), None

    tags = frozenset()
    z0 = jnp.asarray(problem.z0())
    f_struct = jax.eval_shape(lambda z: fn(z, data)[0], z0)
    init = eqx.filter_jit(lambda z, d: solver.init(fn, z, d, {}, f_struct, None, tags))
    t0 = time.perf_counter()
    state0 = init(z0, data)
    jax.block_until_ready(eqx.filter(state0, eqx.is_array))
    dyn0, static = eqx.partition(state0, eqx.is_array)

    @jax.jit
    def step(z, dyn, d):
        state = eqx.combine(static, dyn)
        z2, state2, _ = solver.step(fn, z, d, {}, state, tags)
        done, result = solver.terminate(fn, z, d, {}, state2, tags)
        done = done | (result != optx.RESULTS.successful) | ~jnp.all(jnp.isfinite(z2))
        return z2, eqx.filter(state2, eqx.is_array), done

    jax.block_until_ready(step(z0, dyn0, data))
    compile_s = time.perf_counter() - t0

    def run_init(z):
        return eqx.filter(init(z, data), eqx.is_array)

    return run_init, lambda z, dyn: step(z, dyn, data), compile_s


def coarse_problem(method, job, base, target, init):
    """The coarse stage's problem when ``fitter.fit`` would start coarse (LM, a
    large image: ``fitter.fit._coarse.eligible``), else None."""
    from fitter.fit import _coarse

    if method != "lm" or not _coarse.eligible(
            job.scene, mask="interior", exclude=None, weights=None, saturation=None,
            loss="l2", dtype=np.float64, n_starts=1):
        return None
    s = job.scene
    h, w = s.height // 2, s.width // 2
    small = np.asarray(target, dtype=np.float64).reshape(h, 2, w, 2, 3).mean(axis=(1, 3))
    scene = s.replace(width=w, height=h, supersampling=s.supersampling // 2)
    return _Problem(job.replace(scene=scene), base, small, init)


def finish_fine(prob, z, samples, t_run):
    """The full-size Gauss-Newton finish of ``fitter.fit._coarse.solve`` from the
    coarse solution ``z``, one recorded sample per step (a settling chord step
    too, ``_coarse.chord_step``), with the product's executables and
    tolerances. Returns (z, t_run, compile seconds)."""
    import jax.numpy as jnp

    from fitter.fit import _coarse, _solvers
    from fitter.fit._compile import compiled, residuals_at_points

    spec, data = prob.spec, prob.data
    rtol, atol = _solvers.RTOL, _solvers.ATOL
    t0 = time.perf_counter()
    step, _ = compiled("gauss_newton", spec, (jnp.asarray(z), data))
    residuals_at_points(spec, np.asarray(z)[None], data)  # compiles it
    compile_s = time.perf_counter() - t0
    z = np.asarray(z, dtype=np.float64)
    for _ in range(_coarse.MAX_FINE_STEPS):
        t0 = time.perf_counter()
        R, r, J, dz, cost = (np.asarray(a) for a in step(jnp.asarray(z), data))
        t_run += time.perf_counter() - t0
        done = _coarse.settled(z, dz, rtol, atol)
        z = z + dz
        samples.append((len(samples), t_run, prob.params(z)))
        if done:
            break
        t0 = time.perf_counter()
        r1 = residuals_at_points(spec, z[None], data)[0]
        dz1 = _coarse.chord_step(R, J, r, r1, z, dz, float(cost), rtol, atol)
        t_run += time.perf_counter() - t0
        if dz1 is not None:
            z = z + dz1
            samples.append((len(samples), t_run, prob.params(z)))
            break
    return z, t_run, compile_s


def run_jax(method, job, base, target, init, max_steps):
    """Product figures (``fitter.fit`` cold, warm) and the step trace."""
    import jax

    import fitter
    from fitter.fit import _solvers

    solver = JAX_METHODS[method]
    kw = dict(init=init, fixed=job.fixed, solver=solver, base_dir=base)
    cold = fitter.fit(target, job.scene, job.material, **kw)
    # What a user who gives no start gets (the CLI's default): the lobe defaults.
    plain = {**kw, "init": None}
    fitter.fit(target, job.scene, job.material, **plain)
    # The compiled calls' least time of WARM_REPEATS, interleaved (the machine is shared).
    warms, plains = [], []
    for _ in range(WARM_REPEATS):
        warms.append(fitter.fit(target, job.scene, job.material, **kw))
        plains.append(fitter.fit(target, job.scene, job.material, **plain))
    warm = min(warms, key=lambda r: r.time_run)
    defaults = min(plains, key=lambda r: r.time_run)
    prob = _Problem(job, base, target, init)
    coarse = coarse_problem(method, job, base, target, init)
    # What fitter.fit does: a large image starts on its 2 x 2 average
    # (fitter.fit._coarse), stepped here like the direct solve.
    first = coarse or prob
    run_init, step, compile_s = stepper(first, solver, *(
        (_solvers.RTOL, _solvers.ATOL) if coarse else (RTOL, ATOL)))
    best = None
    for rep in range(TRACE_REPEATS):  # the fastest trace (each is ~0.05 s: a hiccup shows)
        z = jax.numpy.asarray(prob.z0())
        samples = [(0, 0.0, prob.params(z))]
        t_run = 0.0
        t0 = time.perf_counter()
        dyn = run_init(z)
        jax.block_until_ready(dyn)
        t_run += time.perf_counter() - t0
        for i in range(1, max_steps + 1):
            t0 = time.perf_counter()
            z, dyn, done = step(z, dyn)
            done = bool(done)  # waits for the step
            t_run += time.perf_counter() - t0
            samples.append((i, t_run, prob.params(z)))
            if done:
                break
        if coarse is not None:
            z, t_run, compile_gn = finish_fine(prob, z, samples, t_run)
            compile_s += compile_gn if rep == 0 else 0.0
        if best is None or t_run < best[0]:
            best = (t_run, samples)
    samples = best[1]
    product = {"compile_s": cold.time_compile, "fit_cold_s": cold.time_compile + cold.time_run,
               "fit_warm_s": warm.time_run, "iterations": warm.iterations,
               "fit_warm_defaults_s": defaults.time_run,
               "iterations_defaults": defaults.iterations,
               "status": warm.status, "params": warm.to_dict()["params"]}
    return prob, samples, compile_s, product


def run_baseline(method, job, base, target, init, opts):
    prob = _Problem(job, base, target, init)
    x0 = _params_to_vec(prob.init_full)
    samples = [(0, 0.0, prob.init_full)]
    rec = lambda x, t: samples.append((len(samples), t, {**prob.init_full,  # noqa: E731
                                                         **_vec_to_params(x)}))
    if method == "scipy":
        import baseline_scipy

        # A first, untimed call pays NumPy/scipy's one-off costs (imports, caches).
        baseline_scipy.fit(target, job.scene, x0, None, max_nfev=1)
        _, secs, nfev, _ = baseline_scipy.fit(target, job.scene, x0, None, record=rec)
        compile_s, extra = 0.0, {"nfev": int(nfev), "fit_warm_s": secs}
    else:
        import baseline_mitsuba

        _, secs, first = baseline_mitsuba.fit(target, job.scene, x0, spp=opts["spp"],
                                              lr=opts.get("lr", 0.02), iters=opts["iters"],
                                              record=rec)
        compile_s, extra = first, {"spp": opts["spp"], "lr": opts.get("lr", 0.02),
                                   "fit_warm_s": secs}
    return prob, samples, compile_s, extra


def run(spec: dict) -> dict:
    """One worker job: ``{"case", "res", "method", "target" (.npy), ...}`` -> result dict."""
    import sys

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import fitter  # noqa: F401  (x64)
    from fitter.compilation_cache import enable_compilation_cache

    # FITTER_CACHE_DIR (set by run.py: empty for a first run, a folder for the
    # warm rerun) as the CLI uses it: persistent XLA cache and exported traces.
    enable_compilation_cache()

    case, res, method = spec["case"], int(spec["res"]), spec["method"]
    job, base = load_job(case, res)
    target = np.load(spec["target"])
    init = CASES[case]["init"]
    t0 = time.perf_counter()
    if method in JAX_METHODS:
        prob, samples, compile_s, extra = run_jax(
            method, job, base, target, init, spec.get("max_steps", TRACE_STEPS[method]))
    else:
        prob, samples, compile_s, extra = run_baseline(method, job, base, target, init, spec)
    wall = time.perf_counter() - t0
    rmse = prob.rmse_fn()
    every = max(1, len(samples) // 200)  # keep at most ~200 image evaluations
    trace = []
    for j, (i, t, p) in enumerate(samples):
        e = errors(p, job.truth, prob.free)
        row = {"step": i, "time_s": t, "max_rel_err": max(v[3] for v in e.values()),
               "errors": e}
        if j % every == 0 or j == len(samples) - 1:
            row["image_rmse"] = rmse(prob.renderer.params(p))
        trace.append(row)
    return {"case": case, "res": res, "method": method, "n_pixels": prob.n_pixels,
            "compile_s": compile_s, "wall_s": wall, "trace": trace, **extra}

"""The public drivers, target image(s) -> FitResult.

Flow: set up the problem -> search the start and cut work options where a lobe
has them (``_search``) -> hold parameters without effect at the start (for
Levenberg-Marquardt only where the solution shows one, ``_checked_after``) ->
solve from one or more starts (one compiled call) -> keep the lowest cost
(solved again from inside the box where it stopped in a corner, ``_corner``) ->
check identifiability at the solution, hold and refit -> verdict.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import envlight
from ..blasthreads import one_blas_thread
from ..gcthreshold import fewer_collections
from ..hugepages import advice_off
from ..limits import check_scene
from ..material import Material
from ..scene import Scene
from . import _args, _coarse, _corner, _discretisation, _edge, _glints, _profile
from ._ahead import import_ahead, settled
from ._compile import (best_start, compile_ahead, compiled, jac_res, r_factor,
                       remember_jacobian)
from ._covariance import residual_variance
from ._identify import (WEAK_EIG, ambiguous, chi2_1dof_level, dead_columns, known_valley,
                        profile_size, unidentifiable_at, weak_direction, weak_profile)
from ._problem import blocks_of, format_value, user_values, z_from_params
from ._search import cheapened, searched
from ._setup import START_MARGIN, FitError, Problem
from ._solvers import ATOL, RTOL
from ._starts import starts as make_starts
from ._verdict import all_held, report, start_status
from .result import FitResult

#: Rounds of hold-and-refit after a fit (``_finish``).
MAX_REFITS = 2
#: The zero-column check at the start first looks at every 8th fitted pixel.
START_CHECK_STRIDE = 8
#: Solvers whose fits make that check only where the solution shows a zero
#: column (``_checked_after``): a damped step never moves a coordinate whose
#: column is zero. It cost ~0.6 s of an environment-lit first fit (its trace and
#: compile), ~0.1 s of each compiled one and a full-size linearisation of a
#: coarse start's. Undamped Gauss-Newton and dogleg would factor a singular
#: J^T J, so they are checked first.
CHECK_AFTER = ("levenberg_marquardt",)
#: Starts a one-start fit is re-solved from when the solution lies in a weakly
#: identified valley (``_identify.weak_direction``).
AUTO_STARTS = 4


@advice_off
@one_blas_thread
@fewer_collections
@settled
def fit(target, scene: Scene, material, *, init: Mapping[str, Any] | None = None,
        fixed: Mapping[str, Any] | None = None, bounds: Mapping[str, tuple] | None = None,
        solver: str = "levenberg_marquardt", mask="interior", exclude=None, weights=None,
        noise_sigma: float | None = None, loss: str = "l2", loss_scale: float | None = None,
        saturation: float | None = None, n_starts: int = 1, max_steps: int | None = None,
        rtol: float = RTOL, atol: float = ATOL, dtype=jnp.float64,
        base_dir: str | None = None, identifiability: bool = True,
        progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit the material's parameters to a target image.

    Args:
        target: (H, W, 3) linear RGB radiance of the scene's image.
        scene: the known camera, sphere, lights and environment.
        material: a ``Material``, a lobe list, or a ``"lambert+phong"`` string.
        init: initial values ``{"lobe.param": value}``; missing ones take the
            lobe's default. A parameter that is fixed by default (e.g.
            ``torrance_sparrow.rho_s``, ``"exposure"``: a scale of the whole image,
            ``fitter.material.EXPOSURE``) is freed by giving it here.
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
        progress: called with a short line as the fit advances (the step
            reached; after each start its steps and cost), e.g. to update a
            spinner. The compiled solve cannot call back into Python (its
            trace is cached on disk), so the finest grain is one start.

    Returns:
        A ``FitResult``; failures are reported in ``status``/``message``,
        not raised.

    Raises:
        FitterError: for bad input, before any work, with a message naming
            the argument or key (the config's rules, ``_args``): ``FitError``
            (an argument), ``MaterialError`` (a parameter or lobe),
            ``SceneError`` (a scene field), ``ResourceError`` (over
            ``fitter.limits``: starts, supersampling, memory).
    """
    t_start = time.perf_counter()
    scene = _args.scene_of(scene)
    # Parsed here, as ``Problem.make`` would: a lobe string or list gets the sky tables
    # made ahead too (``import_ahead`` reads a Material only).
    material = material if isinstance(material, Material) else Material.make(material)
    import_ahead(scene, material)
    n_starts = _args.option("n_starts", n_starts)
    identifiability = _args.option("identifiability", identifiability)
    check_scene("fit", scene, material, n_starts=n_starts, base_dir=base_dir)
    target = _args.images(target, "target", scene)
    if target.shape not in ((scene.height, scene.width, 3), (1, scene.height, scene.width, 3)):
        several = "; use fit_batch for several targets" if target.ndim == 4 else ""
        raise FitError(f"target has shape {target.shape}, expected "
                       f"{_args.image_shape(scene)}{several}")
    problem = Problem.make(target[None] if target.ndim == 3 else target, scene, material,
                           init=init, fixed=fixed, bounds=bounds, solver=solver, mask=mask,
                           exclude=exclude, weights=weights, noise_sigma=noise_sigma, loss=loss,
                           loss_scale=loss_scale, saturation=saturation, max_steps=max_steps,
                           rtol=rtol, atol=atol, dtype=dtype, base_dir=base_dir)
    say = progress or _quiet
    problem = cheapened(searched(problem))
    coarse = _coarse.eligible(problem.renderer.scene, mask=mask, exclude=exclude,
                              weights=weights, saturation=saturation, loss=loss, dtype=dtype,
                              n_starts=n_starts)
    t_compile = 0.0
    # Damped solves check for parameters without effect after the solve (``_checked_after``).
    after = identifiability and problem.static["solver_name"] in CHECK_AFTER
    # The stated error's finer geometries (NumPy, XLA compiles) on a thread from
    # here, beside the solve's compile and run; after the start check where one
    # comes first (its holds change the problem). Under a sky (sun cells at 2k
    # samples, a finer sun, half the rings: ~3 s of a first env fit) from before
    # the solve's tracing too (env_plastic's first fit -0.15 s); a dielectric's
    # short one gained nothing there (first run 5.30 s against 5.24 s, 4 pairs).
    early = after and envlight.lit_by_environment(problem.renderer.scene, problem.material)
    if early:
        _discretisation.prefetch(problem)
    if identifiability:
        if not coarse:  # the solve traced, compiled on a thread beside what follows
            compile_ahead("solve", problem.spec, (problem.cast(problem.z_init()[None]),
                                                  problem.data(0)), **problem.static)
        if not after:
            say("checking which parameters the pixels depend on")
            problem, t_compile = _hold_dead_columns(problem, coarse)
            if not problem.blocks:
                return all_held(problem, 0, t_compile, 0.0)
    if not early:
        _discretisation.prefetch(problem)
    data = problem.data(0)
    if n_starts == 1 and identifiability:  # the cost profile's pixels (``weak_profile``)
        _profile.ahead(problem.spec, data, profile_size(problem.spec.n))
    z0s = make_starts(problem.spec, problem.z_init(), n_starts)
    first = None
    if coarse:
        first = _coarse.solve(problem, target.reshape(target.shape[-3:]), z0s, data,
                              solve_starts, say)
    if first is None:
        first = solve_starts(problem, z0s, data, say)
    if after:
        problem, first, tc = _checked_after(problem, first, n_starts, say, coarse)
        t_compile += tc
        if not problem.blocks:
            return all_held(problem, 0, t_compile, time.perf_counter() - t_start - t_compile)
        data = problem.data(0)
    first, corner = _corner.leave(problem, first, data, solve_starts, say)
    zs, codes, nsteps, costs, best, (R, r), tc = first
    t_compile += tc
    notes = [corner] if corner else []
    if n_starts == 1 and identifiability:
        eig, along = weak_direction(problem.spec, r_factor(R))
        why, extra = None, np.zeros((0, problem.spec.n))
        # A valley the lobe names (its derived quantity) is reported, not walked.
        known = eig < WEAK_EIG and known_valley(problem.spec, along,
                                                user_values(problem.spec, zs[best], data.fixed))
        # Not a valley locally: profile the cost (at a minimum only).
        if eig >= WEAK_EIG and start_status(int(codes[best]), zs[best],
                                            costs[best]) == "converged":
            why, extra, _ = weak_profile(problem.spec, data, zs[best], r_factor(R), r,
                                         problem.noise_sigma)
        if (eig < WEAK_EIG and not known) or why:  # several starts (and check ambiguity)
            z0s = np.concatenate([make_starts(problem.spec, problem.z_init(), AUTO_STARTS),
                                  extra[:2]])
            (zs, codes, nsteps, costs, best, (R, r), tc), corner = _corner.leave(
                problem, solve_starts(problem, z0s, data, say, "weakly identified: "), data,
                solve_starts, say)
            t_compile += tc
            found = (f"correlation eigenvalue {eig:.2g} < {WEAK_EIG:g}" if not why else
                     f"the cost profile (weakest direction, each parameter's) shows {why}")
            notes = [f"weakly identified at the first solution ({found}, along "
                     f"{', '.join(along)}): solved from {len(z0s)} starts to check for a "
                     "valley or another minimum"] + ([corner] if corner else [])
    starts = [{"params": user_values(problem.spec, zs[i], data.fixed), "cost": float(costs[i]),
               "status": start_status(int(codes[i]), zs[i], costs[i])}
              for i in range(len(costs))]
    say("checking identifiability and the stated errors")
    res = _finish(problem, 0, zs[best], int(codes[best]), int(nsteps[best]), float(costs[best]),
                  identifiability=identifiability, t_start=t_start, t_compile=t_compile,
                  say=say, starts=starts, jr=(r_factor(R), np.asarray(r, dtype=np.float64)),
                  alternatives=[(zs[i], float(costs[i])) for i in range(len(costs))
                                if i != best])
    res.warnings.extend(notes)
    return res


def _quiet(text: str) -> None:
    pass


def solve_starts(problem: Problem, z0s, data, say=_quiet, what: str = ""):
    """Solve from each start (S, n) in turn, one compiled call per start.

    Returns (zs (S, n), codes, steps, costs (S,), best index, (R, r) at the
    best, compile seconds), as the compiled multi-start solve gives them. A
    call per start costs nothing on CPU (a ``lax.map`` runs the starts one by
    one too), reuses one executable for any number of starts, and lets
    ``say`` report each start's steps and cost while the fit runs.
    """
    z0s = np.asarray(z0s)
    one = problem.cast(z0s[:1])
    solve, t_compile = compiled("solve", problem.spec, (one, data), **problem.static)
    outs, n = [], len(z0s)
    for i in range(n):  # the line stands while the start solves
        best_so_far = (f" (best cost so far {min(float(o[3][0]) for o in outs):.4g})"
                       if outs else "")
        say(f"{what}solving from start {i + 1}/{n}{best_so_far}")
        *out, (R, r, J) = solve(problem.cast(z0s[i:i + 1]), data)
        out = [np.asarray(a) for a in out]
        outs.append((*out, (np.asarray(R), np.asarray(r))))
        say(f"{what}start {i + 1}/{n} done: {int(out[2][0])} steps, cost "
            f"{float(out[3][0]):.4g}")
        costs = np.concatenate([o[3] for o in outs])
        if int(best_start(costs, np.concatenate([o[0] for o in outs]))) == i:
            best_J = np.asarray(J)  # one whole Jacobian to the host, not one per start
    zs, codes, steps, costs = (np.concatenate([o[k] for o in outs]) for k in range(4))
    best = int(best_start(costs, zs))
    remember_jacobian(problem.spec, zs[best], data, best_J, outs[best][5][1])
    return zs, codes, steps, costs, best, outs[best][5], t_compile


@advice_off
@one_blas_thread
@fewer_collections
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
    for name in ("n_starts", "exclude"):
        if name in kwargs:
            raise FitError(f"fit_batch takes no {name} (one start per target, one pixel "
                           "selection for all); fit the targets one by one with fit to use it")
    scene = _args.scene_of(scene)
    identifiability = _args.option("identifiability", identifiability)
    material = material if isinstance(material, Material) else Material.make(material)
    check_scene("fit", scene, material, base_dir=kwargs.get("base_dir"))
    targets = _args.images(targets, "targets", scene)
    if targets.ndim != 4 or len(targets) == 0:
        raise FitError(f"targets have shape {targets.shape}, expected (B, H, W, 3) with B >= 1 "
                       f"and (H, W, 3) = {_args.image_shape(scene)}")
    problem = Problem.make(targets, scene, material, **kwargs)
    t_compile = 0.0
    if identifiability:
        problem, t_compile = _hold_dead_columns(problem)
        if not problem.blocks:
            return [all_held(problem, b, t_compile, 0.0) for b in range(len(targets))]
    data = problem.data(None)
    z0 = problem.cast(problem.z_init())
    solve, tc = compiled("batch", problem.spec, (z0, data), batch=batch, **problem.static)
    t_compile += tc
    zs, codes, nsteps, costs, (R, r) = (jax.tree_util.tree_map(np.asarray, a)
                                        for a in solve(z0, data))
    share = (time.perf_counter() - t_start - t_compile) / len(targets)
    results = []
    for b in range(len(targets)):
        res = _finish(problem, b, zs[b], int(codes[b]), int(nsteps[b]), float(costs[b]),
                      identifiability=identifiability, t_start=time.perf_counter(),
                      t_compile=t_compile, starts=[], refit=False,
                      jr=(r_factor(R[b]), np.asarray(r[b], dtype=np.float64)))
        # became unidentifiable, out of steps short of a box edge, resting on a glint
        # (``_glints``) or in a corner of the box (``_corner``): refit alone
        if identifiability and (res is None or _edge.candidate(problem.spec, res)
                                or "few_pixels" in res.adequacy.get("blocks", {})
                                or _corner.interior_start(problem.spec, zs[b],
                                                          data.fixed) is not None):
            res = fit(targets[b], scene, material, identifiability=True, **kwargs)
        else:
            res = dataclasses.replace(res, time_run=res.time_run + share,
                                      time_compile=t_compile / len(targets))
        results.append(res)
    return results


def _hold_dead_columns(problem: Problem, coarse: bool = False) -> tuple[Problem, float]:
    """Hold parameters the fitted pixels do not depend on at the start.

    Returns the problem without them and the seconds spent compiling. The
    Jacobian does not depend on the target, so one check serves a batch.
    Where the start search saw every free parameter change the cost
    (``problem.alive``), none can be dead and no Jacobian is made.
    ``coarse``: the fit will start coarse (``_coarse``), whose full-size
    Gauss-Newton step has the Jacobian's R factor on all pixels: the check uses
    that executable (one compile fewer) instead of its own.
    """
    z0 = problem.z_init()
    t_compile = 0.0
    if coarse:
        args = (problem.cast(z0), problem.data(0))
        step, t_compile = compiled("gauss_newton", problem.spec, args)
        J0 = r_factor(step(*args)[0])
        dead = blocks_of(problem.spec, dead_columns(problem.spec, z0, J0))
        return problem.held(dead, [_dead_reason(problem, k) for k in dead]), t_compile
    if all(b.key in problem.alive for b in problem.blocks):
        return problem, 0.0  # the start search saw each change the cost (``_search``)
    # A column alive on a strided subset of the pixels is alive (the common
    # case, at 1/8 of the cost); one that looks dead there is checked on all.
    stride = START_CHECK_STRIDE if problem.rows.size >= START_CHECK_STRIDE * 512 else 1
    while True:
        J0, _, tc = jac_res(problem.spec, z0, problem.data(0, stride), once=True)
        t_compile += tc
        dead = dead_columns(problem.spec, z0, J0)
        if stride == 1 or not dead.any():
            break
        stride = 1
    dead = blocks_of(problem.spec, dead)
    return problem.held(dead, [_dead_reason(problem, k) for k in dead]), t_compile


def _checked_after(problem: Problem, first, n_starts: int, say=_quiet, coarse=False):
    """The start check (``_hold_dead_columns``) after a damped solve, made only
    where the solution shows a zero Jacobian column.

    Levenberg-Marquardt's damped step leaves a coordinate whose column is zero
    where it is, so a parameter dead at the start is dead at the solution too;
    one that lives at the solution is fitted (the check at the start would have
    held it at its start). A coarse start's undamped full-size finish
    (``_coarse``) fails on a zero column, and the full-size solve it falls back
    to is damped. Returns (problem, ``solve_starts``'s result, compile seconds
    spent beyond that result's): the problem and solve as they were, or, with
    parameters dead at the start, those held and the rest solved again
    (directly at full size).
    """
    zs, _, _, _, best, (R, _), _ = first
    if not dead_columns(problem.spec, zs[best], r_factor(R)).any():
        return problem, first, 0.0
    say("checking which parameters the pixels depend on")
    held, t_check = _hold_dead_columns(problem, coarse)
    if held.blocks == problem.blocks:  # dead at the solution only: ``_finish`` holds it
        return problem, first, t_check
    if not held.blocks:
        return held, first, t_check + first[-1]
    z0s = make_starts(held.spec, held.z_init(), n_starts)
    return held, solve_starts(held, z0s, held.data(0), say), t_check + first[-1]


def _dead_reason(problem: Problem, key: str) -> str:
    return (f"{key} does not change the fitted pixels at the start (zero Jacobian column); "
            f"held at {format_value(problem.init_full[key])}")


def _finish(problem: Problem, b: int, z, code: int, iters: int, cost: float, *,
            identifiability: bool, t_start: float, t_compile: float, starts: list,
            refit: bool = True, jr=None, alternatives=(), say=_quiet) -> FitResult | None:
    """Check, refit without unidentifiable parameters, and report target ``b``.

    ``jr``: (R, r) at ``z`` if the solve returned them (``jac_res``).
    ``alternatives``: (z, cost) where the other starts ended (``ambiguous``).
    With ``refit=False`` an unidentifiable parameter at the solution
    returns None (the caller refits).
    """
    spec, data = problem.spec, problem.data(b)
    if jr is None:
        J, r, tc = jac_res(spec, z, data)
        t_compile += tc
    else:
        J, r = jr
    # Hold what the image does not constrain and refit the rest, from the best
    # point and from where every other start ended (so the refit is checked
    # for ambiguity too). A parameter that is only ambiguous (another start
    # as good, elsewhere) is marked, not held: the others keep their errors
    # from the whole covariance, not ones conditional on an arbitrary value.
    marked = None
    for round_ in range(MAX_REFITS + 1 if identifiability else 0):
        if not np.isfinite(cost):
            break
        s2 = residual_variance(problem.noise_sigma, data, r, spec)
        unid = unidentifiable_at(spec, z, J, s2)
        amb = ambiguous(spec, z, J, s2, cost, alternatives)
        if unid is None or round_ == MAX_REFITS:
            # Out of rounds: what is still unidentifiable is marked, not held.
            if unid is not None:
                unid = (unid[0], [why + "; left at this fit's value, with no stated error"
                                  for why in unid[1]])
            marked = [list(u) + list(a) for u, a in zip(unid or ([], []), amb or ([], []))]
            break
        if not refit:
            return None
        keys, whys = unid
        reasons = [why + "; held at its initial value" for why in whys]
        best = user_values(spec, z, data.fixed)
        values = {}
        for k, why in zip(*(amb or ([], []))):
            if k not in keys:  # held with the others, at this fit's value
                keys.append(k)
                reasons.append(why + "; held at this fit's value")
                values[k] = best[k]
        points = [best] + [user_values(spec, za, data.fixed) for za, _ in alternatives]
        free = problem
        problem = free.held(keys, reasons, values)
        if not problem.blocks:
            return all_held(problem, b, t_compile, time.perf_counter() - t_start - t_compile)
        spec, data = problem.spec, problem.data(b)
        z0s = np.stack([z_from_params(spec, {**problem.init_full, **{
            k: v for k, v in p.items() if k not in keys}}, START_MARGIN) for p in points])
        zs, codes, nsteps, costs, best_i, (J, r), tc = solve_starts(
            problem, z0s, data, say, f"refit with {', '.join(keys)} held: ")
        t_compile += tc
        # Held at its start (the first len(whys) keys), a parameter the linearisation
        # calls unconstrained may be one the image rejects there (the 95 % level of
        # chi^2 with 1 dof; Oren-Nayar's sigma run to ~0, where the model's slope in
        # it vanishes: held at 0.3 the refit failed as "poor fit"): then it is held
        # at this fit's value.
        rise = 2.0 * (float(costs[best_i]) - cost) / s2 if s2 > 0 else 0.0
        if rise > chi2_1dof_level():
            reasons[:len(whys)] = [f"{why}; held at this fit's value, as the image rejects "
                                   f"its initial value (chi^2 {rise:+.3g} held there)"
                                   for why in whys]
            values.update({k: best[k] for k in keys[:len(whys)]})
            problem = free.held(keys, reasons, values)
            spec, data = problem.spec, problem.data(b)
            zs, codes, nsteps, costs, best_i, (J, r), tc = solve_starts(
                problem, z0s, data, say, f"refit with {', '.join(keys)} held at this fit: ")
            t_compile += tc
        z, code, cost = zs[best_i], int(codes[best_i]), float(costs[best_i])
        iters += int(nsteps[best_i])
        J, r = r_factor(J), np.asarray(r, dtype=np.float64)
        alternatives = [(zs[i], float(costs[i])) for i in range(len(costs)) if i != best_i]
    if refit and identifiability and np.isfinite(cost):
        glint = _glints.refit(problem, b, z, solve_starts, say)
        if glint is not None:
            problem, z, code, cost, steps, (J, r), tc = glint
            spec, data = problem.spec, problem.data(b)
            iters, t_compile = iters + steps, t_compile + tc
    warnings, unidentifiable = list(problem.warnings), list(problem.unidentifiable)
    if marked and marked[0]:
        unidentifiable += list(dict.fromkeys(marked[0]))
        warnings += marked[1]
    res = report(problem, b, spec, data, z, code, iters, cost, J, r, warnings,
                 unidentifiable, t_start, t_compile, starts)
    if refit and identifiability and res.status == "max_steps":  # a best fit on a box edge?
        res = _edge.pin(problem, b, res, cost, solve_starts, _finish, say, t_start,
                        t_compile, starts) or res
    return res

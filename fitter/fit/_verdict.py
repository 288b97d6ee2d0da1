"""The verdict on a fit and its ``FitResult``: the solver's status checked
against goodness of fit, standard errors, image RMSE, warnings and times."""

from __future__ import annotations

import time

import numpy as np

from ..bsdf.derived import settle
from ..render import render_active
from . import _adequacy, _discretisation
from ._compile import jac_full
from ._covariance import (
    covariance,
    degrees_of_freedom,
    intervals,
    propagator,
    residual_variance,
    scaled_jacobian,
)
from ._problem import Data, Spec, blocks_of, format_value, frame, robust, user_values
from ._setup import Problem
from ._solvers import solver_outcome
from .result import FitResult

#: With a known noise sigma, chi^2 per degree of freedom above this fails the fit.
MAX_REDUCED_CHI2 = 2.0
#: Without a noise sigma, a residual RMSE this many times the target's own noise
#: level (``_noise.estimate_noise``) fails the fit. Measured on the shipped
#: Mitsuba cases: good fits 0.2-3.5, fits stopped after 2 steps 25-450.
MAX_NOISE_RATIO = 10.0
#: Lowest noise level a target is judged against, relative to the mean of its
#: fitted values: on a noise-free target (a forward-model render, a converged
#: high-spp render) the Immerkaer estimate falls towards 0 (as the image's
#: curvature, ~1/size^2), and a residual the model's own discretisation leaves
#: would count as "many times the noise". Sources: Mitsuba vs this model,
#: interior mean relative difference 1.3e-6 - 1.4e-4 (issue 15); this model at
#: 4x4 vs 8x8 Gauss samples, relative RMSE over the fitted pixels 5e-5
#: (256^2, lambert + torrance_sparrow) to 2.8e-4 (64^2 mirror) and 1.2e-4 at
#: 512^2 lambert, where the estimate was 7e-6 and the fit failed at 17x
#: (measured here); float32 EXR quantisation is 6e-8 (2^-24), negligible. So a
#: fit passes on a noise-free target while its residual RMSE is below
#: ``MAX_NOISE_RATIO * NOISE_FLOOR`` = 1e-3 of the mean.
NOISE_FLOOR = 1e-4


def _noise_ratio(problem: Problem, b: int | None, data: Data, rmse, used):
    """(residual RMSE / the target's noise level, that level, whether it is the
    floor ``NOISE_FLOOR`` x the mean value, that mean): ``rmse`` (3,) and
    ``used`` as ``_image_rmse`` gives them; a NaN estimate gives ratio 0."""
    noise = problem.noise[0 if b is None else b]
    mean = np.sum(np.abs(np.where(used, np.asarray(data.target), 0.0))) / max(used.sum(), 1)
    estimate = float(np.sqrt(np.mean(noise**2)))
    floored = estimate < NOISE_FLOOR * float(mean)  # NaN (no estimate): no check
    scale = NOISE_FLOOR * float(mean) if floored else estimate
    ratio = float(np.sqrt(np.mean(rmse**2)) / scale) if scale > 0 else 0.0
    return ratio, scale, floored, mean


def start_status(code: int, z, cost) -> str:
    """``"converged"``, ``"max_steps"`` or ``"failed"`` (a non-finite solution
    fails whatever the solver said)."""
    if not (np.all(np.isfinite(z)) and np.isfinite(cost)):
        return "failed"
    return solver_outcome(code)[0]


def near_bounds(spec: Spec, params, sd) -> list:
    """[(block, bound, its stated error)] of the parameters whose value lies within
    its stated error ``sd`` (n,) of a bound of its box: where a fit out of steps
    has its best fit on the box's edge (Oren-Nayar sigma = 0, measured: 0.0029
    +- 0.03 after 200 steps), the coordinate runs off towards infinity."""
    near = []
    for blk, sl in spec.slices():
        x = np.atleast_1d(np.asarray(params[blk.key], dtype=np.float64))
        for bound in (blk.lower, blk.upper):
            if np.any(np.abs(x - bound) <= sd[sl]):
                near.append((blk, bound, sd[sl] if blk.size > 1 else float(sd[sl][0])))
                break
    return near


def _near_bound(spec: Spec, params, sd) -> str:
    """``near_bounds`` as text ("" if none)."""
    return "; ".join(f"{blk.key} = {format_value(params[blk.key])} lies within its stated "
                     f"error ({format_value(e)}) of its bound {bound:g}"
                     for blk, bound, e in near_bounds(spec, params, sd))


def _out_of_steps(static: dict, edge: str = "") -> str:
    """The message of a fit out of steps: the budget as the advice, or where a
    value lies on its box's edge (``_near_bound``, text ``edge``) why more steps
    will not help."""
    stopped = (f"stopped after {static['max_steps']} steps without meeting rtol = "
               f"{static['rtol']:g} / atol = {static['atol']:g}")
    if edge:
        return (f"{stopped}: {edge}, a best fit on the edge of its box, which the solver's "
                "coordinate approaches without reaching (more steps are unlikely to meet the "
                "tolerances); the values are where it stopped")
    return (f"{stopped}; the values are where it stopped: raise max_steps (fit.max_steps), "
            "start nearer (init, n_starts > 1) or loosen rtol/atol")


def _image_rmse(model, data: Data):
    """Per-channel RMSE (3,) of model - target over the values with a weight,
    which values have one ((P, 3) bool) and model - target there (0 elsewhere)."""
    weights = np.asarray(data.weights, dtype=np.float64)
    used = weights > 0
    err = np.where(used, np.asarray(model) - np.asarray(data.target), 0.0)
    ones = np.ones(err.shape[0])  # sums over pixels as products: ~7x faster than axis=0
    return np.sqrt((ones @ (err * err)) / np.maximum(ones @ used, 1)), used, err


def report(problem: Problem, b: int, spec: Spec, data: Data, z, code: int, iters: int,
           cost: float, J, r, warnings: list, unidentifiable: list, t_start: float,
           t_compile: float, starts: list) -> FitResult:
    """The ``FitResult`` of target ``b`` solved at ``z`` (``J``: the Jacobian's R
    factor there, ``r`` the residuals), with its goodness-of-fit verdict."""
    status = start_status(code, z, cost)
    message = solver_outcome(code)[1] or "solver tolerances met"  # max_steps: below
    warnings = list(warnings)
    dof = degrees_of_freedom(data, spec)
    chi2 = float(r @ r)
    s2 = residual_variance(problem.noise_sigma, data, r, spec)
    if problem.noise_sigma is not None and status == "converged" and chi2 / dof > MAX_REDUCED_CHI2:
        status = "failed"
        message = (f"poor fit: chi^2/dof = {chi2 / dof:.3g} > {MAX_REDUCED_CHI2} for the "
                   "given noise_sigma")
    cov_z, sd, _ = covariance(spec, z, J, s2)
    if not np.all(np.isfinite(cov_z)):
        blind = np.isinf(np.diag(cov_z))
        cov_z = np.zeros_like(cov_z)
        status, message = "failed", (
            "the covariance is not finite (the solution is not finite)" if not blind.any()
            else f"{', '.join(blocks_of(spec, blind))} does not change the fitted pixels "
                 "(fit with identifiability=True to hold it)")
        sd = np.zeros_like(sd)
    params = user_values(spec, z, data.fixed)
    at_edge = frame(spec, z)[3]
    weights = np.asarray(data.weights, dtype=np.float64)
    if spec.loss == "l2":  # residuals are (model - target) * weight
        model = np.asarray(data.target) + r.reshape(-1, 3) / np.where(weights > 0, weights, 1.0)
    else:
        model = np.asarray(render_active(
            {k: problem.cast(v) for k, v in params.items()}, data.geometry, data.env,
            data.sphere, material=spec.material, env_type=spec.env_type))
    sd_stat, sd_sys, sd_disc, hac, spread = sd, np.zeros_like(sd), np.zeros_like(sd), None, None
    if np.all(np.isfinite(cov_z)) and np.any(sd > 0):
        sd, sd_stat, sd_sys, sd_disc, hac, spread = _with_systematic(
            problem, spec, data, z, cov_z, params, model, J)
    unidentifiable = list(unidentifiable)
    for coord, few in ((hac or {}).get("few_pixels") or {}).items():
        key = coord.split("[")[0]
        if key not in unidentifiable:
            unidentifiable.append(key)
            which = f"{coord}: " if coord != key else ""
            warnings.append(
                f"{key} rests on a pixel or two ({which}{few['effective_pixels']:.2g} effective "
                f"pixels, most of it at row {few['row']}, column {few['column']}: a glint or "
                "a sub-pixel highlight): its error would be that pixel's own residual, one "
                "draw of its noise, so none is stated; give noise_sigma if the noise is "
                "known")
    stderr, stderr_stat, stderr_sys, stderr_disc = {}, {}, {}, {}
    for blk, sl in spec.slices():
        if blk.key not in unidentifiable:  # marked ambiguous: no error to give
            for out, v in ((stderr, sd), (stderr_stat, sd_stat), (stderr_sys, sd_sys),
                           (stderr_disc, sd_disc)):
                out[blk.key] = v[sl] if blk.size == 3 else float(v[sl][0])
        if np.any(at_edge[sl]):
            warnings.append(f"{blk.key} = {format_value(params[blk.key])} is at the bound of "
                            f"[{blk.lower:g}, {blk.upper:g}]; its standard error is half "
                            "a +-1 sigma interval cut by that bound")
    edge = _near_bound(spec, params, sd) if status == "max_steps" else ""
    if status == "max_steps":  # (its stated errors known: is a value on its box's edge?)
        message = _out_of_steps(problem.static, edge)
    d = np.sqrt(np.maximum(np.diag(cov_z), 1e-300))
    corr = cov_z / np.outer(d, d)
    rmse, used, err = _image_rmse(model, data)
    ratio, scale, floored, mean = _noise_ratio(problem, b, data, rmse, used)
    # A best fit on its box's edge (out of steps there: more would not move it) is
    # judged as a converged one: a target far brighter than the lobes render ends there.
    if (problem.noise_sigma is None and (status == "converged" or edge)
            and ratio > MAX_NOISE_RATIO):
        status = "failed"
        level = (f"noise level (its floor, {NOISE_FLOOR:g} of the mean value: the target "
                 "looks noise-free)" if floored else "noise level (Immerkaer estimate)")
        message = f"poor fit: the residual RMSE is {ratio:.3g} times the target's {level}"
        if edge:
            message += f" at a best fit on the edge of its box ({edge})"
    pix = _fitted_pixels(problem, data)
    adequacy = {
        "noise_ratio": ratio, "noise_floored": bool(floored),
        "regions": _adequacy.region_stats(err, used, _adequacy.pixel_regions(data.geometry),
                                          scale),
        "neighbour_correlation": _adequacy.neighbour_correlation(
            err, pix, problem.renderer.scene.width, data.geometry.kept(
                "neighbours", lambda: _adequacy.neighbour_pairs(
                    pix, problem.renderer.scene.width)))}
    if hac is not None:
        adequacy["blocks"] = hac
    failing = status == "failed" and message.startswith("poor fit")
    # Out of steps from several starts that agree: not the start, nor (only)
    # the budget -- judged like a converged fit, the model comes first.
    if status == "converged" or (status == "max_steps" and _adequacy.starts_agree(starts)):
        verdict = _adequacy.judge(adequacy, float(np.sqrt(np.mean(rmse**2))) / max(mean, 1e-300))
        if verdict is not None:
            if status == "max_steps":
                verdict += f" (and the solver stopped after {problem.static['max_steps']} steps)"
            status, message, failing = "failed", verdict, True
    if failing:
        message = f"{message}: " + _adequacy.cause(err, model, used, adequacy, starts,
                                                   np.asarray(data.target), bool(edge))
    # (A residual of rounding alone, far below the noise, is structured but says nothing.)
    mostly = _systematic_warning(adequacy, sd_stat, sd_sys, sd_disc)
    if status == "converged" and mostly and ratio > _adequacy.SYS_WARN_LEVEL:
        warnings.append(mostly)
    total = time.perf_counter() - t_start
    res = FitResult(
        params={k: (np.asarray(params[k]) if np.size(params[k]) > 1 else float(params[k]))
                for k in spec.material.param_specs()}, stderr=stderr,
        free=[blk.key for blk in spec.blocks],
        unidentifiable=unidentifiable, correlation=corr, coordinates=spec.coordinates(),
        status=status,
        message=message, iterations=iters, cost=cost, image_rmse=rmse,
        n_pixels=int(problem.rows.size),
        n_excluded=problem.n_dropped + int(np.count_nonzero(used @ np.ones(3) < 3)),
        time_compile=t_compile, time_run=max(total - t_compile, 0.0),
        warnings=warnings, starts=starts, fitted=problem.fitted(0 if b is None else b),
        stderr_stat=stderr_stat, stderr_sys=stderr_sys, stderr_disc=stderr_disc,
        adequacy=adequacy)
    if any(lb.derived is not None for lb in spec.material.lobe_objects):
        settle(spec.material, res,  # a conductor's F0; eta, k only along its curve
               None if spread is None else propagator(spec, z, data.fixed, spread))
    return res


def _fitted_pixels(problem: Problem, data: Data) -> np.ndarray:
    """(P,) flat image index of each fitted pixel (the fitted geometry is made
    for these pixels: kept with it, ``Geometry.kept``)."""
    return data.geometry.kept("pixels", lambda: np.asarray(
        problem.renderer.pixel_index)[problem.rows])


def _systematic_warning(adequacy: dict, sd_stat, sd_sys, sd_disc) -> str | None:
    """The warning for stated errors whose systematic part exceeds ``SYS_WARN``
    times the statistical one, naming the larger of its two sources: the
    residual's spatial structure (the block sandwich's excess) or the model's
    own discretisation (``stderr_disc``), which a white residual carries too
    (a model target at noise 1e-4: 11 times, neighbour correlation 0.01)."""
    stat = np.maximum(sd_stat, 1e-300)
    total = float(np.max(sd_sys / stat)) if np.size(sd_sys) else 0.0
    if not total > _adequacy.SYS_WARN:
        return None
    disc = float(np.max(sd_disc / stat))
    structured = float(np.max(np.sqrt(np.maximum(sd_sys**2 - sd_disc**2, 0.0)) / stat))
    if structured >= disc:
        return (f"the residual is spatially structured ({_adequacy.where(adequacy)}): the "
                f"stated errors include a systematic part up to {total:.3g} times the "
                "statistical one (stderr_sys, stderr_stat)")
    # (a systematic part comes with the blocks' entry: ``_with_systematic``)
    k, k2 = adequacy["blocks"]["discretisation"]["supersampling"]
    return (f"the stated errors are mostly the model's own discretisation: rendered with "
            f"{k2} x {k2} sub-pixel samples instead of {k} x {k} (and its other quadratures "
            f"refined) the fit would move by up to {disc:.3g} times its statistical error "
            f"(stderr_disc); the residual's spatial structure adds up to {structured:.3g} "
            "times (stderr_sys, stderr_stat)")


def _with_systematic(problem: Problem, spec: Spec, data: Data, z, cov_stat, params, model, R):
    """(stderr total, statistical, systematic, of which discretisation (each (n,)),
    block info, the matrices ``_covariance.along`` takes), from the Gauss-Newton
    covariance ``cov_stat``.

    Statistical = ``cov_stat`` plus what noise varying over the pixels adds
    (``_adequacy.heteroscedastic``: shot noise). Systematic = the significant
    excess of the spatial-block sandwich (``_adequacy``) over the statistical
    covariance, plus the outer product of the parameter shift the model's own
    discretisation error implies (``_discretisation``: the fitted parameters
    rendered k vs 2k, the difference taken through the linearisation). The
    parts add in quadrature.
    """
    J, r, _ = jac_full(spec, z, data)
    Js = scaled_jacobian(spec, z, J)
    Rs = scaled_jacobian(spec, z, R)  # R: J's R factor, so Js^T Js = Rs^T Rs
    gram = Rs.T @ Rs  # the sandwich's and the shifts'
    pix = _fitted_pixels(problem, data)
    ids, n_blocks = data.geometry.kept("blocks", lambda: _adequacy.block_ids(
        pix, problem.renderer.scene.width))
    cov_hac = _adequacy.sandwich(Js, r, ids, n_blocks, gram)
    # Noise varying over the pixels (shot noise) is statistical; the blocks add what
    # spatially structured residuals do beyond it.
    cov_gn = cov_stat
    cov_pix, n_eff = _adequacy.pixel_sandwich(Js, r, len(pix), gram)
    cov_stat = cov_stat + _adequacy.pixel_excess(cov_stat, cov_pix, n_eff)
    sd_stat = intervals(spec, z, cov_stat)[0]
    cov_sys = _adequacy.systematic(cov_stat, cov_hac, n_blocks)
    info = {"n_blocks": int(n_blocks),
            "hac_over_stat_max": float(np.sqrt(np.max(
                np.diag(cov_hac) / np.maximum(np.diag(cov_stat), 1e-300))))}
    # (A noise_sigma given is the pixel's noise too: V_stat holds for it.)
    few = (_adequacy.few_pixels(Js, len(pix), gram, n_eff) if problem.noise_sigma is None
           else {})
    if few:
        names, width = spec.coordinates(), problem.renderer.scene.width
        info["few_pixels"] = {names[j]: {"effective_pixels": n_j, "row": int(pix[p] // width),
                                         "column": int(pix[p] % width)}
                              for j, (n_j, (p, *_)) in few.items()}
    t0 = time.perf_counter()
    rows, share = data.geometry.kept("finer rows", lambda: _discretisation.sample_rows(
        _adequacy.pixel_regions(data.geometry), problem.renderer.scene))
    finer = np.zeros_like(model)
    coverage = np.zeros(model.shape[0])
    sky_term, stencil, sky = _discretisation.sky_terms(data, params, spec.material,
                                                       spec.env_type)
    coarse = model - sky_term  # the model without its sky term
    finer[rows], coverage[rows] = _discretisation.finer_values(problem, params, rows,
                                                               coarse[rows])
    # The sky term (not refined) over the part of the pixel the finer samples
    # see on the sphere: finer = finer lights + background + sky x coverage.
    seen = data.geometry.kept("seen", lambda: np.asarray(data.geometry.hit, dtype=np.float64)
                              @ np.asarray(data.geometry.sample_weight, dtype=np.float64))
    covered = coverage > 0
    scale = np.zeros(model.shape[0])
    scale[rows] = share  # body pixels stand for their unrendered neighbours
    w = np.asarray(data.weights, dtype=np.float64) * covered[:, None]
    diff = finer + sky_term * (coverage / np.maximum(seen, 1e-300))[:, None] - model
    diff = np.where(covered[:, None], diff, 0.0)
    changes = [diff]
    if data.geometry.has_sky:  # (without a sky the ring error is zero: no column)
        rings = np.zeros_like(model)
        rings[rows] = _discretisation.ring_error(problem, params, rows, stencil[rows])
        changes.append(rings)
    # One least-squares solve for every shift; independent, they add in quadrature.
    deltas = _discretisation.shift(Js, np.stack(
        [(c * w * scale[:, None]).reshape(-1) for c in changes]
        + [(s * np.asarray(data.weights, dtype=np.float64)).reshape(-1) for s in sky], axis=1),
        gram)
    cov_disc = deltas @ deltas.T
    info["discretisation"] = {
        "supersampling": [problem.renderer.scene.supersampling,
                          _discretisation.finer_supersampling(problem.renderer.scene)],
        "rms_over_mean": float(np.sqrt(np.mean(diff[covered] ** 2))
                               / max(float(np.mean(np.abs(model[covered]))), 1e-300)),
        "seconds": time.perf_counter() - t0}
    sd_tot = intervals(spec, z, cov_stat + cov_sys + cov_disc)[0]
    sd_sys = np.sqrt(np.maximum(sd_tot**2 - sd_stat**2, 0.0))
    sd_d = np.sqrt(np.maximum(intervals(spec, z, cov_stat + cov_disc)[0] ** 2 - sd_stat**2, 0.0))
    return (sd_tot, sd_stat, sd_sys, np.minimum(sd_d, sd_sys), info,
            (cov_gn, cov_pix, n_eff, cov_hac, n_blocks, cov_disc))


def all_held(problem: Problem, b: int, t_compile: float, t_run: float) -> FitResult:
    """The failed ``FitResult`` of target ``b`` when every parameter is held:
    the values are the held ones, cost and image RMSE are those of their render."""
    spec, data = problem.spec, problem.data(b)  # no free blocks: data.fixed is complete
    model = np.asarray(render_active(data.fixed, data.geometry, data.env, data.sphere,
                                     material=spec.material, env_type=spec.env_type),
                       dtype=np.float64)
    weights = np.asarray(data.weights, dtype=np.float64)
    r = np.asarray(robust((model - np.asarray(data.target, dtype=np.float64)) * weights,
                          spec.loss, spec.loss_scale), dtype=np.float64)
    rmse, used, err = _image_rmse(model, data)
    message = ("no parameter is identifiable from this image: every free parameter is held "
               "(see warnings)")
    ratio = _noise_ratio(problem, b, data, rmse, used)[0]
    c, share = _adequacy.scale_share(err, model, used)
    # A coordinate run to where its slope underflows is held as unconstrained: a target
    # far brighter than the lobes render (100x an albedo's) ends so; its render says.
    if problem.noise_sigma is None and ratio > MAX_NOISE_RATIO and share > _adequacy.SCALE_SHARE:
        message += (f"; the held values' render leaves a residual {ratio:.3g} times the "
                    f"target's noise level, the target {1 - c:.4g} times it ({100 * share:.0f}"
                    " % of the residual is that uniform scale): "
                    + _adequacy.EXPOSURE_ADVICE)
    return FitResult(
        params={k: (np.asarray(v) if np.size(v) > 1 else float(v))
                for k, v in problem.init_full.items()}, stderr={},
        free=[], unidentifiable=list(problem.unidentifiable), correlation=np.zeros((0, 0)),
        coordinates=[], status="failed", message=message,
        iterations=0, cost=0.5 * float(np.sum(r * r)), image_rmse=rmse,
        n_pixels=int(problem.rows.size),
        n_excluded=problem.n_dropped + int(np.sum(~used.all(axis=-1))),
        time_compile=t_compile, time_run=t_run, warnings=list(problem.warnings),
        fitted=problem.fitted(b))

"""A best fit on the edge of its box, which the solver approaches without reaching.

A box edge is at z = -+inf of the fit's coordinates (``fitter.transforms``).
Where the model's slope in a parameter also vanishes at the edge (Oren-Nayar
at sigma = 0: its A and B terms change as sigma^2), the solver's coordinate
runs towards the edge ever more slowly and the fit runs out of steps short of
it: extreme_sigma0 (Mitsuba, 128^2) stopped after 200 steps at sigma = 0.0029,
where chi^2 is 64 above its value at sigma = 0 with rho_d refit.

``pin``: a fit out of steps with a value within its stated error of an edge
is refit with that value held on the edge. If the refit converges and fits
at least as well (chi^2 within ``EDGE_SLACK`` of the stopped fit's, or
lower), the edge is the best fit in the box and is reported, with the others'
errors from the refit. The pinned value's statistical error is one-sided: the
profile likelihood, chi^2 with the other parameters refit (linearised about
the refit), rises by 1 at x_1 (``one_sided``), and, as for any value at its
bound (``_covariance.covariance``), its standard error is half the interval
[edge, x_1]. Its systematic part is that statistical error times the largest
systematic-to-statistical ratio of the refit's parameters (``scaled_like``): the
linearisation the others' systematic parts come from has no slope in it on
the edge, and the one where the solver stopped, short of the optimum, reads
the misfit of the solver's own stopping point as structure (measured: 0.6 on
a model-rendered 128^2 target, 0.03 on Mitsuba's, for sigma = 0 exactly).
"""

from __future__ import annotations

import numpy as np

from ._compile import jac_full, r_factor, remember_jacobian, residuals_at_points
from ._covariance import residual_variance
from ._identify import PROFILE_RESOLUTION, rounding_rise
from ._problem import format_value, user_values, z_from_params
from ._verdict import near_bounds, start_status

#: A pinned refit is kept if its chi^2 exceeds the stopped fit's by at most this.
EDGE_SLACK = 0.1
#: Offsets from the edge, as fractions of the box's range, at which the
#: profile likelihood is evaluated (``one_sided``): 4 a decade.
PROFILE_OFFSETS = 10.0 ** np.linspace(-6.0, 0.0, 25)


def one_sided(spec, data, key: str, bound: float, values: dict, J_other, r_edge, s2: float):
    """The value x_1 (float, or None where chi^2 rises by less than 1 over the
    whole box) at which chi^2 of the fit with ``key`` held at x and the other
    parameters refit, linearised about ``values`` (J_other (N, n-1), the
    refit's Jacobian, r_edge its residuals on the edge), exceeds its value on
    the edge by 1.

    ``spec``, ``data``: the fit with ``key`` free, ``values`` the refit's user
    values (``key`` on ``bound``). A profile likelihood: min over d of
    |r(x) + J_other d|^2 / s2 is |r(x)|^2 minus its projection on J_other.
    """
    blk = next(b for b in spec.blocks if b.key == key)
    span = blk.upper - blk.lower
    side = 1.0 if bound == blk.lower else -1.0
    xs = bound + side * span * np.clip(PROFILE_OFFSETS, 1e-6, 1.0 - 1e-6)
    zs = np.stack([z_from_params(spec, {**values, key: x}, 0.0) for x in xs])
    rs = residuals_at_points(spec, zs, data)
    q = np.linalg.qr(np.asarray(J_other, dtype=np.float64))[0]

    def chi2(r):
        r = np.atleast_2d(r)
        return (np.sum(r * r, axis=1) - np.sum((r @ q) ** 2, axis=1)) / s2

    rise = chi2(rs) - chi2(r_edge)[0]
    above = np.nonzero(np.isfinite(rise) & (rise >= 1.0))[0]
    if not above.size or not np.all(np.isfinite(rise[:above[0]])):
        return None
    i = above[0]
    if i == 0:
        return float(xs[0])
    lo, hi = rise[i - 1], rise[i]
    d0, d1 = abs(xs[i - 1] - bound), abs(xs[i] - bound)
    if lo > 0:  # a power law in the distance from the edge between the two points
        t = np.log(1.0 / lo) / np.log(hi / lo)
        return float(bound + side * d0 * (d1 / d0) ** t)
    return float(bound + side * (d0 + (1.0 - lo) / (hi - lo) * (d1 - d0)))


def candidate(spec, res):
    """(key, edge) of the scalar value ``pin`` would hold on the edge of its box,
    for a ``FitResult`` out of steps, or None: the one within its stated error
    of an edge and nearest it in stated errors, where another is left to refit."""
    if res.status != "max_steps" or len(spec.blocks) < 2:
        return None
    sd = np.concatenate([np.full(blk.size, res.stderr.get(blk.key, 0.0), dtype=np.float64)
                         for blk in spec.blocks])
    near = [(abs(res.params[blk.key] - bound) / max(e, 1e-300), blk.key, float(bound))
            for blk, bound, e in near_bounds(spec, res.params, sd) if blk.size == 1]
    return min(near)[1:] if near else None


def pin(problem, b: int, stopped, cost: float, solve_starts, finish, say, t_start: float,
        t_compile: float, starts: list):
    """The fit ``stopped`` (a ``FitResult`` out of steps, at cost ``cost``)
    refit with a value on its box's edge, or None where no value is near an
    edge, the refit does not converge or fits worse (``EDGE_SLACK``), or the
    profile is not resolved (chi^2 rises by less than 1 over the box, or
    rounding could move it by more: ``_identify.rounding_rise``).

    ``solve_starts``, ``finish``: the drivers' solver and their checks of a
    solution (identifiability, hold and refit, verdict). One scalar value is
    pinned: the one nearest its edge in stated errors; the fit must have
    another to refit.
    """
    spec, data = problem.spec, problem.data(b)
    edge = candidate(spec, stopped)
    if edge is None:
        return None
    key, bound = edge
    pinned = problem.pinned({key: bound})
    pdata = pinned.data(b)
    z0 = z_from_params(pinned.spec, {**pinned.init_full, **{
        k: v for k, v in stopped.params.items() if k != key}}, 0.0)
    zs, codes, nsteps, costs, best, (R, r), tc = solve_starts(
        pinned, z0[None], pdata, say, f"refit with {key} on its edge {bound:g}: ")
    t_compile += tc
    z_p, cost_p = zs[best], float(costs[best])
    r = np.asarray(r, dtype=np.float64)
    s2 = residual_variance(problem.noise_sigma, pdata, r, pinned.spec)
    if (start_status(int(codes[best]), z_p, cost_p) != "converged" or not s2 > 0
            or 2.0 * (cost_p - cost) / s2 > EDGE_SLACK
            or rounding_rise(pdata, r, s2) > PROFILE_RESOLUTION):
        return None
    values = user_values(pinned.spec, z_p, pdata.fixed)
    J_other, r_other, tc = jac_full(pinned.spec, z_p, pdata)
    remember_jacobian(pinned.spec, z_p, pdata, J_other, r_other)  # the verdict's, too
    t_compile += tc
    x1 = one_sided(spec, data, key, bound, values, J_other, r, s2)
    if x1 is None:
        return None
    stat = 0.5 * abs(x1 - bound)
    res = finish(pinned, b, z_p, int(codes[best]), stopped.iterations + int(nsteps[best]),
                 cost_p, identifiability=True, t_start=t_start, t_compile=t_compile,
                 starts=starts, jr=(r_factor(R), r), say=say)
    sys_, disc = scaled_like(res, stat)
    gap = 2.0 * (cost - cost_p) / s2
    at = (f"chi^2 {gap:.3g} above its value on the edge" if gap >= 0.01 else
          "chi^2 as low as on the edge")
    res.warnings.append(
        f"{key} is on the edge of its box, {bound:g}: the fit with it free ran out of "
        f"steps approaching it (at {format_value(stopped.params[key])}, {at}); held "
        "there, the others refit. Its statistical error is one-sided: chi^2 (the others "
        f"refit) rises by 1 at {format_value(x1)}, so half of [{bound:g}, "
        f"{format_value(x1)}]; its systematic part in the proportion of the others'")
    res.stderr[key] = float(np.hypot(stat, sys_))
    res.stderr_stat[key] = stat
    res.stderr_sys[key] = sys_
    res.stderr_disc[key] = disc
    res.free = [k for k in stopped.free if k in res.free or k == key]
    return res


def scaled_like(res, stat: float) -> tuple[float, float]:
    """(systematic, discretisation) parts for a statistical error ``stat``, in the
    proportion of the result's parameter (or channel) whose systematic part is
    the largest against its statistical one; (0, 0) where none has one."""
    sys_ratio, disc_ratio = 0.0, 0.0
    for k, st_k in res.stderr_stat.items():
        st_k = np.atleast_1d(np.asarray(st_k, dtype=np.float64))
        sy_k, di_k = (np.broadcast_to(np.asarray(part.get(k, 0.0), dtype=np.float64), st_k.shape)
                      for part in (res.stderr_sys, res.stderr_disc))
        for a, b, c in zip(st_k, sy_k, di_k):
            if a > 0 and np.isfinite(b) and b / a > sys_ratio:
                sys_ratio, disc_ratio = b / a, c / a
    return stat * sys_ratio, stat * disc_ratio

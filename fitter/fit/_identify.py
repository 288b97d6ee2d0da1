"""Identifiability: which parameters the fitted pixels cannot constrain.

Three checks on the Jacobian (or its R factor, which has the same column
norms, singular values and J^T J): a column without effect, a direction the
image cannot separate, and a standard error wider than the box; plus the
multi-start check, another start as good but elsewhere.
"""

from __future__ import annotations

import time

import numpy as np

from ..bsdf.derived import inputs
from ..material import lobe_params
from ._covariance import covariance, fit_coordinates, residual_variance
from ._problem import Spec, blocks_of, format_value, frame

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
#: Another start within this joint confidence level of the best one, but
#: beyond that region's reach in a parameter, makes that parameter
#: unidentifiable (``ambiguous``).
AMBIGUOUS_LEVEL = 0.95
#: Smallest eigenvalue of the correlation matrix below which a fit from one
#: start is re-solved from several (``weak_direction``): the combination along
#: that eigenvector is determined 1/sqrt(eig) times worse than its parameters
#: alone, a valley a single start may stop anywhere in. Measured on the
#: shipped Mitsuba cases: 0.18-0.67, except a conductor's eta/k (1.3e-5).
WEAK_EIG = 1e-3


def dead_columns(spec: Spec, z, J) -> np.ndarray:
    """Coordinates whose parameter cannot change the fitted pixels (bool (n,)).

    ``J``: the Jacobian (N, n) or its R factor (same column norms).

    Each column is measured in user units times the parameter's natural scale
    (``transforms.natural_scale``), so a coordinate saturated near a box edge
    is not mistaken for a parameter without effect.
    """
    # float64 throughout: in float32 the 1e-300 guard below would round to 0.
    _, dxdz, scale, _ = frame(spec, z)
    J = np.asarray(J, dtype=np.float64)
    effect = np.linalg.norm(J, axis=0) / np.maximum(dxdz, 1e-300) * scale
    # A coordinate run off to a box edge has no slope left; that is "at bound"
    # (reported as such), not evidence that the parameter has no effect.
    saturated = np.abs(np.asarray(z, dtype=np.float64)) > SATURATED_Z
    return (effect <= ZERO_COLUMN * max(effect.max(), 1e-300)) & ~saturated


def unidentifiable_at(spec: Spec, z, J, s2: float):
    """Blocks without usable information at ``z``: (keys, reasons) or None; the
    caller says where it holds them.

    ``s2``: the residual variance of the covariance (``residual_variance``).
    """
    keys, reasons = [], []
    J = np.asarray(J, dtype=np.float64)
    if not np.all(np.isfinite(J)):
        return None
    norms = np.linalg.norm(J, axis=0)
    dead = dead_columns(spec, z, J)
    for k in blocks_of(spec, dead):
        keys.append(k)
        reasons.append(f"{k} does not change the fitted pixels at the solution")
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
            for k in blocks_of(spec, flag):
                if k not in keys:
                    keys.append(k)
                    reasons.append(f"{k} is not separable from the other parameters "
                                   f"(Jacobian condition number {cond:.2g})")
    if s2 > 0 and not keys:
        _, _, span = covariance(spec, z, J, s2)
        loose = span > MAX_SPAN
        for k in blocks_of(spec, loose):
            keys.append(k)
            reasons.append(f"{k} is not constrained by the image (standard error larger than "
                           "its whole range)")
    return (keys, reasons) if keys else None


def ambiguous(spec: Spec, z, J, s2: float, cost: float, alternatives):
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
    alternatives = [(za, ca) for za, ca in alternatives
                    if np.isfinite(ca) and np.all(np.isfinite(za))]
    if not alternatives:
        return None
    if not s2 > 0:
        return None
    from scipy.special import chdtri  # 0.1 s to import: only with other starts

    cov, sd, _ = covariance(spec, z, J, s2)
    level = chdtri(spec.n, 1.0 - AMBIGUOUS_LEVEL)  # chi2.ppf(AMBIGUOUS_LEVEL, n)
    # Were the cost quadratic, no point of the region would lie further than
    # sqrt(level) standard errors from the best in any coordinate (the
    # projection of the ellipsoid): beyond that is evidence, not chance.
    reach = np.sqrt(level * np.diag(cov))
    x = frame(spec, z)[0]
    slices = {blk.key: sl for blk, sl in spec.slices()}
    keys, reasons = [], []
    for za, ca in alternatives:
        if ca - cost > 0.5 * s2 * level:
            continue
        xa = frame(spec, za)[0]
        far = np.abs(fit_coordinates(spec, z, za)) > reach
        for key in blocks_of(spec, far):
            if key in keys:
                continue
            sl = slices[key]
            keys.append(key)
            reasons.append(f"{key} is not determined by the image: another start fits as well "
                           f"(chi^2 {2.0 * (ca - cost) / s2:+.2g}) at {format_value(xa[sl])} "
                           f"against {format_value(x[sl])} +- {format_value(sd[sl])}")
    return (keys, reasons) if keys else None


def known_valley(spec: Spec, along: list[str], values: dict) -> bool:
    """Whether every block of a weak direction ``along`` is an input of its
    lobe's derived quantities (``fitter.bsdf.derived``: a conductor's eta, k
    along the curve of equal F0) at the fit's user ``values``: a valley the
    report already names, with the quantity the image does determine, which
    several starts would only walk (measured: gold under a sky, 64^2, four
    starts 100 s, each 150-200 steps along it, none lower in cost)."""
    if not along:
        return False
    named = set()
    for lobe in spec.material.lobe_objects:
        named |= {f"{lobe.name}.{k}" for k in inputs(
            lobe, spec.material.options_of(lobe.name), lobe_params(values, lobe.name))}
    return all(key in named for key in along)


def weak_direction(spec: Spec, J) -> tuple[float, list[str]]:
    """(smallest eigenvalue of the correlation matrix of (J^T J)^-1, the blocks
    with the largest weight in its eigenvector): a local look for a valley of
    the cost that several starts should explore (``WEAK_EIG``)."""
    J = np.asarray(J, dtype=np.float64)
    if J.shape[1] < 2 or not np.all(np.isfinite(J)):
        return 1.0, []
    cov = np.linalg.pinv(J.T @ J, hermitian=True)
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    w, v = np.linalg.eigh(cov / np.outer(d, d))
    big = np.abs(v[:, 0]) >= 0.3 * np.abs(v[:, 0]).max()
    return float(w[0]), blocks_of(spec, big)


#: Profile of the cost along the weakest direction (``profile``): points at
#: these multiples of the stated error along it, both ways, each step capped
#: at ``PROFILE_MAX_STEP`` in the fit's coordinates (about a box's width).
PROFILE_T = (3.0, 10.0, 30.0)
PROFILE_MAX_STEP = 4.0
#: A profile point whose chi^2 rise is below this fraction of the quadratic
#: model's (t^2) while that model puts it outside the 95 % region is a flat
#: valley; a point below the best cost is another basin.
PROFILE_FLAT = 0.25
#: Chi^2 that rounding may move a profile point's rise by, beyond which the
#: profile says nothing (``rounding_rise``). On noiseless targets
#: (residuals ~1e-16) every point had "fallen" by chi^2 ~1e2-1e4 and
#: converged fits were re-solved from 6 starts as "another basin" or "a
#: flat valley"; at noise 2e-3 (256^2) rounding moves it by ~1e-7.
PROFILE_RESOLUTION = 1.0
#: Rounding of a residual assumed by ``rounding_rise``, in ulps of the rms
#: weighted target. Measured between the solver's residuals and the profile's
#: at one point: rms 0.1-0.5 ulp (40^2, six lobe sets), 14 ulp (256^2 after a
#: coarse-to-fine solve, 170 at most).
ROUNDING_ULPS = 16.0


def profile_points(spec: Spec, z, J, s2: float):
    """Points along the weakest direction of the covariance at ``z``, then
    along each coordinate's own profile direction: [(t, z_t)].

    The weakest direction is the correlation matrix's smallest eigenvector v
    scaled by the standard errors D (a step a D v raises chi^2 by a^2 / w, w
    its eigenvalue, were the cost quadratic), so z_t = z + t sqrt(w) D v is t
    stated errors out along it. Coordinate i's profile direction C e_i / d_i
    moves it by its standard error d_i with the others at their conditional
    best, raising chi^2 by 1 (were the cost quadratic): it checks the stated
    error of each parameter itself. Measured at m = 1e-3, 32^2 (sub-pixel
    highlight): the weakest direction (eigenvalue 0.86) rose as quadratic,
    while eta = 1.0017 +- 0.095 had another fit at 1.32 (chi^2 +0.3).
    """
    J = np.asarray(J, dtype=np.float64)
    if J.shape[1] < 1 or not np.all(np.isfinite(J)) or not s2 > 0:
        return []
    cov = covariance(spec, z, J, s2)[0]
    if not np.all(np.isfinite(cov)):
        return []
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    w, v = np.linalg.eigh(cov / np.outer(d, d))
    if np.any(frame(spec, z)[3]):  # a value at its bound: its coordinate is not z
        return []
    steps = [np.sqrt(max(w[0], 0.0)) * d * v[:, 0]] + [cov[:, i] / d[i] for i in range(len(d))]
    out = []
    for step in steps:
        for t in PROFILE_T:
            for sign in (1.0, -1.0):
                dz = sign * t * step
                big = np.max(np.abs(dz))
                if big > PROFILE_MAX_STEP:
                    dz = dz * (PROFILE_MAX_STEP / big)
                out.append((sign * t * min(1.0, PROFILE_MAX_STEP / max(big, 1e-300)),
                            np.asarray(z, dtype=np.float64) + dz))
    return out


def profile_size(n: int) -> int:
    """How many points ``profile_points`` gives for n coordinates (when it gives any)."""
    return (n + 1) * len(PROFILE_T) * 2


def chi2_1dof_level() -> float:
    """The ``AMBIGUOUS_LEVEL`` quantile of chi^2 with 1 dof, z^2 of the normal's
    (``scipy.special.chdtri(1, 1 - level)`` to 1e-15 relative, without its
    0.1 s import on every fit)."""
    from statistics import NormalDist

    return NormalDist().inv_cdf(0.5 + 0.5 * AMBIGUOUS_LEVEL) ** 2


def rounding_rise(data, r, s2: float) -> float:
    """The chi^2 by which rounding may move a profile point's rise: each
    residual off by d = ``ROUNDING_ULPS`` eps |weighted target|_rms, the cost by
    r . d + |d|^2 / 2, so (2 sqrt(N) |r|_rms d + N d^2) / s2."""
    t = np.asarray(data.target)
    tw = t * np.asarray(data.weights, dtype=np.float64).reshape(len(t), -1)
    r = np.asarray(r, dtype=np.float64)
    d = ROUNDING_ULPS * np.finfo(t.dtype).eps * float(np.sqrt(np.mean(tw * tw)))
    n = r.size
    return (2.0 * np.sqrt(n) * float(np.sqrt(np.mean(r * r))) * d + n * d * d) / s2


def profile_verdict(s2: float, cost: float, profile) -> tuple[str | None, list]:
    """(why the profile calls for several starts or None, the points to start from).

    ``profile``: [(t, z_t, cost_t)] from ``profile_points`` and the cost there.
    Were the cost quadratic, cost_t - cost = s2 t^2 / 2. A point below the best
    cost is another basin; one whose rise is below ``PROFILE_FLAT`` of that
    while t^2 exceeds the 95 % chi^2 quantile is a flat valley.
    """
    level = chi2_1dof_level()
    why, starts = None, []
    for t, zt, ct in profile:
        if not np.isfinite(ct):
            continue
        rise = 2.0 * (ct - cost) / s2  # delta chi^2
        if rise < 0:
            why = why or f"another basin {abs(t):.3g} standard errors out (chi^2 {rise:+.3g})"
            starts.append(zt)
        elif t * t > level and rise < PROFILE_FLAT * t * t:
            why = why or (f"a flat valley: chi^2 rises {rise:.3g} at {abs(t):.3g} standard "
                          f"errors out, not {t * t:.3g}")
            starts.append(zt)
    return why, starts


def weak_profile(spec: Spec, data, z, J, r, noise_sigma):
    """The cost profile along the weakest direction of a one-start fit:
    (why several starts are needed or None, start points (k, n), seconds).

    ``J``: the Jacobian's R factor at ``z``, ``r`` the residuals there. The
    points cost one residual evaluation each, in one compiled call
    (``_compile.costs_at``; no Jacobian); where the solver's whole Jacobian at
    ``z`` is at hand (``_compile.jac_full`` of a remembered solution), on the
    pixel subset of ``_profile.subset_costs`` (exact where the model is linear
    in z, guarded by its standard error elsewhere; ``_profile.ENABLED``).

    The points are centred on the Gauss-Newton minimum z* = z + dz (``newton_step``)
    and their rises measured from the quadratic model's cost there: the solver
    stops at its tolerance, which on a near noise-free target is many stated errors
    from the minimum (measured: 40 at 32^2, where the rises at -+3 were -30 and +48).
    Where rounding may move the rises by more than ``PROFILE_RESOLUTION``
    (``rounding_rise``: residuals near rounding, a noiseless target), they
    are not resolved and the profile finds nothing.
    """
    from ._compile import costs_at
    from ._profile import subset_costs

    t0 = time.perf_counter()
    r = np.asarray(r, dtype=np.float64)
    s2 = residual_variance(noise_sigma, data, r, spec)
    cost = 0.5 * float(r @ r)
    points = profile_points(spec, z, J, s2)
    none = np.zeros((0, np.size(z)))
    if not points or not rounding_rise(data, r, s2) <= PROFILE_RESOLUTION:
        return None, none, time.perf_counter() - t0
    J_full, same = _remembered_jacobian(spec, z, data, r)
    g = J_full.T @ r
    dz = newton_step(J, g)  # zero where g is not finite
    points = [(t, zt + dz) for t, zt in points]
    # (J^T J from the R factor: R^T R, not a pass over J's rows)
    costs = subset_costs(spec, data, z, J_full if same else None, r, s2, cost, points,
                         chi2_1dof_level(), PROFILE_FLAT, grad=g, gram=J.T @ J)
    if costs is None:
        costs = costs_at(spec, np.stack([zt for _, zt in points]), data)
    evaluated = [(t, zt, float(c)) for (t, zt), c in zip(points, costs)]
    # The cost at z + dz were it quadratic: cost + g . dz / 2 (dz = -(J^T J)^-1 g).
    drop = 0.5 * float(g @ dz) if np.all(np.isfinite(g)) else 0.0
    why, starts = profile_verdict(s2, cost + drop, evaluated)
    return why, np.asarray(starts).reshape(-1, np.size(z)), time.perf_counter() - t0


def newton_step(R, g) -> np.ndarray:
    """The Gauss-Newton step (n,) to the minimum of the cost's quadratic model,
    -(R^T R)^-1 g, from the Jacobian's R factor (n, n) and the gradient
    ``g`` = J^T r (n,); zero where not finite. Two solves with R, not one with
    R^T R (whose condition number is R's squared)."""
    R = np.asarray(R, dtype=np.float64)
    y = np.linalg.lstsq(R.T, -np.asarray(g, dtype=np.float64), rcond=None)[0]
    dz = np.linalg.lstsq(R, y, rcond=None)[0]
    return dz if np.all(np.isfinite(dz)) else np.zeros_like(dz)


def _remembered_jacobian(spec: Spec, z, data, r):
    """(the whole Jacobian (N, n) at ``z``, whether its residuals are ``r``):
    the solver's, which the drivers remember (linearised anew otherwise), and
    left remembered for the verdict's sandwich."""
    from ._compile import jac_full, remember_jacobian

    J, r_known, _ = jac_full(spec, z, data)
    remember_jacobian(spec, z, data, J, r_known)
    return J, np.shape(r_known) == np.shape(r) and np.array_equal(r_known, r)

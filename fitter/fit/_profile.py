"""The post-fit cost profile (``_identify.weak_profile``) on a pixel subset.

The profile's points are 6(n+1) full residual evaluations, most of a compiled
fit's time at 256^2. The cost rise at a point splits, per pixel p with model
change dm_p = J_p dz + a_p, into the Gauss-Newton quadratic

    q = sum_p r_p . J_p dz + |J_p dz|^2 / 2        (exact, from the solver's J)

and a remainder e = sum_p e_p, e_p = r_p . a_p + (J_p dz) . a_p + |a_p|^2 / 2,
which is zero where the model is linear in z. Only the remainder is estimated
from a subset of pixels: every body pixel whose linear response stands out
(``standing_out``: weight 1), every ``HIGHLIGHT_STRIDE``-th highlight and
``RIM_STRIDE``-th rim pixel (where the model is sharp,
``_adequacy.pixel_regions``) and every ``BODY_STRIDE``-th body pixel, each
weighted by its region's pixels per pick: a Horvitz-Thompson sum with variance
estimate sum_picked W (W - 1) e_p^2 (Horvitz & Thompson 1952; Poisson
sampling with inclusion probability 1 / W). So the estimated rise equals the
full one exactly when the residuals are linear in z, and a point whose
estimate lies within ``GUARD`` estimated standard errors of a verdict's
threshold (its error in quadrature with ``SE_FLOOR``) is evaluated on the
whole image (``costs_at``), as before.
"""

from __future__ import annotations

import jax
import numpy as np

from .._math import finite_rows, to_device

#: The subset on (benchmarks/profile_subset.py compares it with every pixel).
ENABLED = True
#: The subset's residuals in float32 (256^2 plastic's profile points 14.5 -> 9.0
#: ms in a compiled fit, one point more), float32's error measured at z and taken off
#: (``estimated_rises``' ``centre``); a point where that leaves the verdict in
#: doubt (``GUARD``) or float32 is not finite is evaluated in float64 on every
#: pixel. Not under environment samples (their subset is compiled ahead,
#: ``ahead``) nor for a lobe without ``single_precision`` (where float32's error
#: sends many points to every pixel: the 128^2 dielectric's profile 0.26 ->
#: 1.14 s). ``benchmarks/profile_subset.py``, the estimates' largest errors in
#: guarded standard errors, float64 -> float32: 256^2 plastic 0.92 -> 0.93,
#: the quickstart 0.18 -> 0.70, sharp Beckmann m = 0.01 0.72 -> 0.52.
SINGLE = True
#: Below this many fitted pixels the profile runs on all of them (the subset
#: would save little and cost a compile of its own).
MIN_PIXELS = 4096
#: Body pixels (away from highlights and the rim) the subset keeps: every this
#: many-th, each standing for this many. Measured (``benchmarks/profile_subset.py``,
#: stride 8 / 16): estimated rises off by at most 0.61 / 0.62 (256^2 plastic) and
#: 0.84 / 0.87 (128^2 dielectric) of their guarded standard errors (``GUARD``).
BODY_STRIDE = 16
#: A point whose estimated chi^2 rise is within this many of its estimated
#: standard errors of a threshold of ``profile_verdict`` (0, and
#: ``PROFILE_FLAT`` t^2) is evaluated on every pixel instead.
GUARD = 4.0
#: Added (in quadrature) to the estimated standard error, in chi^2: the
#: Poisson variance misses structure of the remainder (measured on the 128^2
#: dielectric, stride 8: errors up to 0.14 where it stated 0.02; 4-40 at
#: rises of 900 where it stated 3-50).
SE_FLOOR = 0.5
#: Every this many-th highlight and rim pixel, each standing for this many
#: (``strata``: there a pixel standing out is strided too). Under a
#: sky a rim pixel held 16 env samples when these were measured (the limb's 4 x 4;
#: k points across the limb now, 4 at 4 x 4, ``geometry.LIMB_NODES``) and a
#: highlight pixel the sun's full sampling, each the cost of ~16 body pixels
#: (the rim held 90 % of env_plastic's subset's samples when taken whole);
#: point-lit, highlight and rim held 80 % of 256^2 plastic's subset.
#: ``benchmarks/profile_subset.py``, the estimated rises' largest error against
#: every pixel's, in guarded standard errors (``GUARD``), (highlight, rim)
#: strides (1, 1) -> (2, 8) -> (4, 8): env_plastic 1.74 -> 0.81 -> 0.77, env_phong 0.81
#: -> 0.66 -> 1.02, env_oren_nayar 0.61 -> 0.27 -> 0.34, env_point 0.92 -> 1.12
#: -> 1.01, 256^2 plastic 0.62 -> 0.64 -> 0.38, 128^2 dielectric 0.87 -> 1.27 ->
#: 1.27; sharp highlights (``_sharp``) Beckmann m = 0.05 / 0.02 at 128^2, 0.01
#: at 192^2: 0.81 / 0.89 / 0.37 at 2, 1.25 / 1.13 / 0.72 at 4. 256^2 plastic's
#: compiled fit 0.117 -> 0.098 s from 2 to 4 (profile 29 -> 21 ms, same run).
HIGHLIGHT_STRIDE, RIM_STRIDE = 4, 8
#: A body pixel whose linear response to a profile step is this many times
#: the step's mean response is taken whole (``standing_out``, ``strata``).
STAND_OUT = 10.0


def standing_out(J, dzs) -> np.ndarray:
    """(P,) bool: pixels whose linear response |J_p dz|^2 to some profile step
    dz exceeds ``STAND_OUT`` times that step's mean over the pixels: a
    feature (a refracted sun, an edge) the body's stride would under-sample.
    ``J`` (3P, n), ``dzs`` (k, n)."""
    J = np.asarray(J, dtype=np.float64)
    dzs = np.asarray(dzs, dtype=np.float64)
    # The ratio does not change with the step's length or sign: one per direction.
    dirs = dzs / np.maximum(np.linalg.norm(dzs, axis=1, keepdims=True), 1e-300)
    lead = np.take_along_axis(dirs, np.argmax(np.abs(dirs), axis=1)[:, None], axis=1)
    dirs = np.unique(np.round(dirs * np.sign(lead), 9), axis=0)
    # Direction-major (k, 3P): each pass below runs over contiguous rows (pixel-major
    # (3P, k) took 8 ms at 256^2 in strided sums and a reduction over k).
    v = dirs @ J.T
    v *= v
    v = v.reshape(len(dirs), -1, 3) @ np.ones(3)  # (k, P); NumPy's sum over 3 is ~10x slower
    limit = STAND_OUT * np.maximum(v.mean(axis=1), 1e-300)
    out = np.zeros(v.shape[1], dtype=bool)
    for row, lim in zip(v, limit):
        out |= row > lim
    return out


def strata(geometry, J=None, dzs=None) -> np.ndarray:
    """(P,) stratum of each fitted pixel for ``subset_rows``: its region (0 body,
    1 highlight, 2 rim: ``_adequacy.pixel_regions``), or 3 for a body pixel
    that stands out (``standing_out``), where a pick stands for
    ``BODY_STRIDE``; without ``J`` (before the fit: ``ahead``) the regions
    alone, the strata where no pixel stands out. Measured (``benchmarks/profile_subset.py``, the six
    cases in one session): also taking the highlight's and rim's whole made
    env_plastic's profile 0.31 -> 0.34 s and the estimates' largest errors
    0.27-1.24 guarded standard errors, against 0.27-1.27: no gain."""
    from ._adequacy import pixel_regions

    labels = pixel_regions(geometry).copy()  # the kept labels are read-only
    if J is not None:
        labels[standing_out(J, dzs) & (labels == 0)] = 3
    return labels


def subset_rows(labels, stride: int = BODY_STRIDE, highlight_stride: int = HIGHLIGHT_STRIDE,
                rim_stride: int = RIM_STRIDE):
    """(rows (M,), weights (M,)) of the fitted pixels the profile evaluates:
    every ``highlight_stride``-th highlight and ``rim_stride``-th rim pixel
    (``labels`` 1, 2), every
    pixel standing out (``labels`` 3), every ``stride``-th body pixel (0),
    each weighted by its stratum's pixels per pick; then padded with unpicked
    pixels of weight 0 to a size of 2^(k/8) pixels (one compile serves fits
    of similar subsets). None when the subset would not be smaller."""
    labels = np.asarray(labels)
    rows, weight, spare = [], [], []
    for lab, step in ((0, stride), (1, highlight_stride), (2, rim_stride), (3, 1)):
        all_ = np.nonzero(labels == lab)[0]
        picked = all_[::step]
        rows.append(picked)
        weight.append(np.full(picked.size, all_.size / max(picked.size, 1)))
        unpicked = np.ones(all_.size, dtype=bool)
        unpicked[::step] = False
        spare.append(all_[unpicked])  # (setdiff1d's sort: 4x slower)
    m = sum(a.size for a in rows)
    size = int(np.ceil(2.0 ** (np.ceil(8.0 * np.log2(max(m, 1))) / 8.0)))
    spare = np.concatenate(spare)
    if size > 0.5 * labels.size or size - m > spare.size:
        return None
    rows = np.concatenate(rows + [spare[:size - m]])
    weight = np.concatenate(weight + [np.zeros(size - m)])
    order = np.argsort(rows)
    return rows[order], weight[order]


def subset_data(data, rows, geometry=None):
    """``data`` with the fitted pixels ``rows`` only (arrays of the same dtypes),
    with their own env samples and sky-table rows (``Geometry.subset``);
    ``geometry``: that subset's geometry if made already (``ahead``)."""
    if geometry is None:
        geo = data.geometry
        # The fit's geometry drops pixel_index (``_setup``); subset indexes it.
        geo = geo._replace(pixel_index=np.zeros(np.shape(data.target)[0], np.int64))
        # Picked on the host and put on the device (``to_device``): indexing device arrays
        # and ``jnp.asarray`` compiled 14 small kernels on a first run (0.2 s at 128^2).
        geometry = jax.tree_util.tree_map(to_device, geo.subset(rows, own_samples=True)._replace(
            pixel_index=None))
    return data._replace(geometry=geometry, target=to_device(np.asarray(data.target)[rows]),
                         weights=to_device(np.asarray(data.weights)[rows]))


#: The subset ``ahead`` made for the fit running now: [(the fit's geometry, rows,
#: the subset's geometry)], taken by ``subset_costs``.
_AHEAD: list = []


def ahead(spec, data, n_points: int) -> None:
    """Under environment samples (the subset's evaluation is compiled for its own
    shapes), pick the profile's pixels as ``subset_costs`` will where no pixel
    stands out (``strata`` without the Jacobian), make
    their geometry and start compiling their evaluation at ``n_points`` points
    behind the compiles already started (``_compile.compile_ahead``): the profile
    of a first env fit then compiles nothing (env_plastic: ~1.2 s of tracing and
    compiling at its end). Where a pixel does stand out, ``subset_costs`` picks
    other pixels and compiles as before (the pick, hence the values, never
    depend on this)."""
    from ._compile import compile_ahead

    _AHEAD.clear()
    if (not ENABLED or not data.geometry.has_env_samples
            or np.shape(data.target)[0] < MIN_PIXELS):
        return
    picks = subset_rows(strata(data.geometry))
    if picks is None:
        return
    sub = subset_data(data, picks[0])
    zs = to_device(np.zeros((n_points, spec.n)), data.target.dtype)
    compile_ahead("residuals", spec, (zs, sub), behind=True)
    _AHEAD.append((data.geometry, picks[0], sub.geometry))


def forget() -> None:
    """Drop what ``ahead`` made (env_plastic's subset geometry: 92 MB, most of it
    sky-table rows): a fit whose profile did not run leaves nothing behind."""
    _AHEAD.clear()


def _made_ahead(data, rows):
    """The subset geometry ``ahead`` made for these rows of this fit, else None."""
    made = _AHEAD.pop() if _AHEAD else None
    if made is None or made[0] is not data.geometry or not np.array_equal(made[1], rows):
        return None
    return made[2]


def estimated_rises(J, r, dzs, r_sub, rows, weight, s2: float, grad=None, gram=None,
                    centre=None):
    """(estimated chi^2 rises (k,), their standard errors (k,)) at z + dz.

    ``J`` (N, n), ``r`` (N,): the whole Jacobian and residuals at z (3 per
    pixel, channel fastest); ``dzs`` (k, n); ``r_sub`` (k, 3M): the residuals
    of the pixels ``rows`` (M,) at each point, ``weight`` (M,) theirs;
    ``grad``, ``gram``: J^T r and J^T J (= R^T R) where the caller has them.
    ``centre``: where ``r_sub`` is float32's (``residuals``' ``single``), (its
    residuals (3M,) at z + dz_c, dz_c (n,)), ``dzs`` and dz_c the points' own
    (``single_coordinates``). The residuals' difference from the linearised
    ones there, d, is float32's own error: taken off every point, and what may
    be left of it (up to sqrt(2) |d| a residual, as if independent between
    points and pixels) moves e_p by up to |r_sub,p| |d_p|, which the standard
    errors include.
    """
    J = np.asarray(J, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    dzs = np.asarray(dzs, dtype=np.float64)
    grad = J.T @ r if grad is None else np.asarray(grad, dtype=np.float64)
    gram = J.T @ J if gram is None else np.asarray(gram, dtype=np.float64)
    # The whole quadratic (k,) from J^T r and J^T J: no (k, N) array.
    quad = dzs @ grad + 0.5 * np.einsum("ki,ij,kj->k", dzs, gram, dzs)
    idx = (3 * rows[:, None] + np.arange(3)).reshape(-1)
    J_sub = J[idx]
    r0, lin = r[idx], dzs @ J_sub.T
    k = len(dzs)
    # Per picked pixel: the rise minus its quadratic part, e_p (k, M).
    lin += r0  # the linearised residuals at each point
    off = None
    if centre is not None:  # compared with lin + off: float32's own error taken off
        off = centre[0] - r0 - J_sub @ centre[1]
        lin += off
    # (r_sub - lin)(r_sub + lin), not r_sub^2 - lin^2 (they nearly cancel), in two
    # (k, 3M) arrays: each new one costs ~4 ms of page faults at 256^2.
    e = r_sub - lin
    lin += r_sub
    if off is not None:
        lin -= 2.0 * off
    e *= lin
    e = e.reshape(k, -1, 3) @ np.full(3, 0.5)  # (k, M); NumPy's sum over 3 is ~10x slower
    rest = e @ weight
    var = (e * e) @ (weight * np.maximum(weight - 1.0, 0.0))
    if off is not None:  # (sum_c |s_c d_c|)^2 <= |s|^2 |d|^2 per pixel
        d2 = (off * off).reshape(-1, 3) @ np.ones(3)
        var += 2.0 * ((r_sub * r_sub) @ np.repeat(weight * weight * d2, 3))
    return 2.0 * (quad + rest) / s2, 2.0 * np.sqrt(var) / s2


def near_threshold(t: float, rise: float, se: float, level: float, flat: float) -> bool:
    """Whether the verdict at a point could change within ``GUARD`` standard
    errors of its estimated rise (thresholds of ``profile_verdict``)."""
    thresholds = [0.0] + ([flat * t * t] if t * t > level else [])
    se = np.hypot(se, SE_FLOOR)
    return any(abs(rise - th) <= GUARD * se for th in thresholds)


def subset_costs(spec, data, z, J, r, s2: float, cost: float, points, level: float,
                 flat: float, stride: int = BODY_STRIDE, grad=None, gram=None):
    """Costs (k,) at ``points`` [(t, z_t)] for ``profile_verdict``: cost +
    s2 / 2 times the estimated rise, or the whole image's cost where the
    estimate is too close to a threshold; None when the subset does not apply
    (too few pixels, or no whole Jacobian ``J``). ``grad``, ``gram``: as
    ``estimated_rises``'."""
    from ._compile import costs_at, residuals_at_points, residuals_of_rows
    from ._problem import single_coordinates

    if (not ENABLED or J is None or np.shape(J)[0] != np.size(r)
            or np.shape(data.target)[0] < MIN_PIXELS):
        return None
    zs = np.stack([zt for _, zt in points])
    dzs = zs - np.asarray(z, dtype=np.float64)
    picks = subset_rows(strata(data.geometry, J, dzs), stride)
    if picks is None:
        return None
    rows, weight = picks
    env = data.geometry.has_env_samples
    single = (SINGLE and not env and np.dtype(data.target.dtype) == np.float64
              and spec.material.single_precision)
    at = np.concatenate([zs, np.asarray(z, dtype=np.float64)[None]]) if single else zs
    if env:  # their rows are remapped on the host
        r_at = residuals_at_points(spec, at, subset_data(data, rows, _made_ahead(data, rows)),
                                   single)
    else:
        r_at = residuals_of_rows(spec, at, data, rows, single)
    r_sub, centre = r_at, None
    if single:  # the points float32 evaluated
        moved = single_coordinates(spec, at) - np.asarray(z, dtype=np.float64)
        dzs, r_sub, centre = moved[:-1], r_at[:-1], (r_at[-1], moved[-1])
    rise, se = estimated_rises(J, r, dzs, r_sub, rows, weight, s2, grad, gram, centre)
    costs = cost + 0.5 * s2 * rise
    finite = finite_rows(r_sub)
    if single:  # float32's NaN or overflow may not be the image's: evaluated again
        finite &= bool(np.all(np.isfinite(centre[0])))
        costs[~finite] = np.inf
    else:
        costs[~finite] = np.nan  # a subset pixel's NaN is the image's
    redo = [i for i, (t, _) in enumerate(points)
            if (single and not np.isfinite(costs[i]))
            or (np.isfinite(costs[i]) and near_threshold(t, rise[i], se[i], level, flat))]
    if redo:
        costs[redo] = costs_at(spec, zs[redo], data)
    return costs

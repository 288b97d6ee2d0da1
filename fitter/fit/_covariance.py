"""Covariance of a fit: s^2 (J^T J)^-1 in the fit's coordinates, and the
standard errors it gives each parameter."""

from __future__ import annotations

import numpy as np

from .. import transforms
from ._adequacy import block_threshold, pixel_threshold
from ._problem import Data, Spec, frame, user_values


def degrees_of_freedom(data: Data, spec: Spec) -> int:
    """Observations less free coordinates (at least 1); values with weight 0
    are not observations."""
    return max(int(np.count_nonzero(np.asarray(data.weights))) - spec.n, 1)


def residual_variance(noise_sigma: float | None, data: Data, r, spec: Spec) -> float:
    """s^2 of the covariance s^2 (J^T J)^-1: 1 when the residuals were divided
    by a known noise sigma, else chi^2 per degree of freedom."""
    if noise_sigma is not None:
        return 1.0
    return float(r @ r) / degrees_of_freedom(data, spec)


def fit_coordinates(spec: Spec, z, za) -> np.ndarray:
    """``za - z`` in the coordinates of ``covariance`` at ``z``: z, or
    x / natural_scale for a value at its bound."""
    x, _, scale, edge = frame(spec, z)
    d = np.asarray(za, dtype=np.float64) - np.asarray(z, dtype=np.float64)
    return np.where(edge, (frame(spec, za)[0] - x) / scale, d)


def covariance(spec: Spec, z, J, s2: float):
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
    J = np.asarray(J, dtype=np.float64)
    key = None
    if J.shape[0] == J.shape[1]:  # an R factor: compared by value (n^2 numbers)
        key = (z.tobytes(), J.tobytes(), float(s2))
        last = _LAST[0] if _LAST else None  # (one read: another thread may replace it)
        if last is not None and last[1] == key and last[0] == spec:
            return tuple(a.copy() for a in last[2])
    J = scaled_jacobian(spec, z, J)
    cov = s2 * np.linalg.pinv(J.T @ J, hermitian=True)
    blind = np.linalg.norm(J, axis=0) == 0
    cov[blind, :] = cov[:, blind] = 0.0
    cov[blind, blind] = np.inf
    out = (cov, *intervals(spec, z, cov))
    if key is not None:
        _LAST[:] = [(spec, key, tuple(a.copy() for a in out))]
    return out


#: The last ``covariance`` of an R factor, [(spec, (z, R, s2) bytes, (cov, stderr,
#: span))]: a fit's checks ask for the same one three or four times (~1 ms each).
_LAST: list = []


def scaled_jacobian(spec: Spec, z, J) -> np.ndarray:
    """J (or its R factor) in the coordinates of ``covariance``: the column of a
    value at its bound divided by dx/dz, times its natural scale."""
    x, dxdz, scale, edge = frame(spec, np.asarray(z, dtype=np.float64))
    if not np.any(edge):  # nothing to rescale: J itself, not a copy (3 MB at 256^2)
        return np.asarray(J, dtype=np.float64)
    J = np.array(J, dtype=np.float64)
    J[:, edge] *= (scale / np.where(dxdz > 0, dxdz, np.inf))[edge]
    return J


def intervals(spec: Spec, z, cov):
    """(stderr (n,), span (n,)) of a covariance of the coordinates at ``z``, as
    ``covariance`` describes."""
    z = np.asarray(z, dtype=np.float64)
    x, _, scale, edge = frame(spec, z)
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
    return np.where(finite, 0.5 * (hi - lo), np.inf), np.where(finite, span, 1.0)


def along(g, gn, pix, n_eff, hac, n_blocks: int, disc):
    """Variance (k,) of the k quantities whose gradients are the columns of
    ``g`` (n, k), by the rules the coordinates' stated errors follow, applied
    along each gradient instead of per coordinate: the Gauss-Newton ``gn``
    plus the pixel sandwich's significant excess (``pix``, threshold from the
    fewest effective pixels ``n_eff`` among the coordinates it depends on),
    plus the block sandwich's over that (``hac``), plus the discretisation
    term ``disc``, each (n, n). For a quantity that is one coordinate this is
    that coordinate's stated variance, linearised. Per coordinate, the excess
    of a conductor's eta and k is lost in the valley along which they trade,
    while along F0 the pixel sandwich was 10-15 times the Gauss-Newton
    variance (gold under a one-texel sun, five seeds: F0 up to 13 stated
    errors off; 2.5 at most now).
    """
    g = np.asarray(g, dtype=np.float64)

    def var(c):
        return np.maximum(np.einsum("ik,ij,jk->k", g, c, g), 0.0)

    used = np.abs(g) > 0
    fewest = np.array([np.min(n_eff[u]) if u.any() else 1.0 for u in used.T])
    stat = var(gn)
    vp = var(pix)
    stat = np.where(vp > pixel_threshold(fewest) * stat, vp, stat)
    vh = var(hac)
    sys = np.where(vh > block_threshold(n_blocks) * stat, vh - stat, 0.0)
    return stat + sys + var(disc)


def propagator(spec: Spec, z, fixed: dict, spread: tuple):
    """``variance(fun) -> stderr``: the stated error of ``fun(params)`` (a user
    value of the fit's ``{"lobe.param": value}``, scalar or (k,)) by ``along``,
    its gradient by central differences in the covariance's coordinates.
    ``spread``: ``along``'s matrices (gn, pix, n_eff, hac, n_blocks, disc)."""
    z = np.asarray(z, dtype=np.float64)
    _, dxdz, scale, edge = frame(spec, z)
    t = np.where(edge, scale, dxdz)  # user units per covariance coordinate
    base = user_values(spec, z, fixed)
    h = 1e-6

    def variance(fun):
        cols, j = [], 0
        for blk, sl in spec.slices():
            for i in range(blk.size):
                up, dn = dict(base), dict(base)
                x = np.atleast_1d(np.array(base[blk.key], dtype=np.float64))
                step = h * t[j] * np.eye(blk.size)[i]
                up[blk.key] = (x + step).reshape(np.shape(base[blk.key]))
                dn[blk.key] = (x - step).reshape(np.shape(base[blk.key]))
                cols.append(np.atleast_1d((np.asarray(fun(up), dtype=np.float64)
                                           - np.asarray(fun(dn), dtype=np.float64)) / (2 * h)))
                j += 1
        value = np.asarray(fun(base))
        return np.sqrt(along(np.stack(cols), *spread)).reshape(value.shape)

    return variance

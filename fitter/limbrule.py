"""A limb pixel's sky term as a Gauss rule across the limb (NumPy, float64).

Near the limb the environment's sky term on a glossy lobe rises steeply across
one pixel (Fresnel, the lobe's horizon cut: cos theta_o falls like the square
root of the distance to the silhouette) and hardly changes along the limb (the
normal turns by 1 / R per pixel there, R the sphere's radius in pixels). So the
pixel's box-filtered value is, to second order in that slow direction, a 1-D
integral across the limb: over s, the offset from the pixel's centre along the
unit direction u (in pixel units) in which cos theta_o falls, against the
density of s = u . (x, y) for (x, y) uniform on the pixel -- the sum of two
uniform variables of widths |u_x| and |u_y|, a trapezoid. Its m-point Gauss
rule (Golub & Welsch, "Calculation of Gauss quadrature rules", Math. Comp. 23,
1969, from the trapezoid's moments) is exact for polynomials in s of degree
2m - 1; on a pixel axis (u = (1, 0)) it is the m-point Gauss-Legendre rule, the
resolution across the limb of the m x m product rule at m points instead of m^2.
Each point lies on its chord {u . x = s} of the pixel, at the chord's middle
moved along u to where cos theta_o takes its mean over the chord (the iso-lines
are circles about the sphere's centre, not lines across the pixel), so the
variation along the limb enters to second order too (``across_limb``).
"""

from __future__ import annotations

from math import comb

import numpy as np


#: The move along u to the chord's mean cos theta_o is at most this (pixel units): the
#: quadratic fitted to the sub-samples holds within the pixel, not beyond it.
MAX_MOVE = 0.25


def _moments(a, b, n: int) -> np.ndarray:
    """E[s^j] (..., n + 1) for j = 0..n of s = a X + b Y, X, Y ~ U(-1/2, 1/2) independent."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    # E[X^i] = 2^-i / (i + 1) for even i, 0 for odd i.
    ex = [(0.5**i / (i + 1)) if i % 2 == 0 else 0.0 for i in range(n + 1)]
    out = np.zeros(a.shape + (n + 1,))
    for j in range(n + 1):
        for i in range(0, j + 1, 2):
            if (j - i) % 2 == 0:
                out[..., j] += comb(j, i) * a**i * b ** (j - i) * ex[i] * ex[j - i]
    return out


def trapezoid_rule(a, b, m: int):
    """(nodes (..., m), weights (..., m)) of the m-point Gauss rule for the density
    of s = a X + b Y, X, Y ~ U(-1/2, 1/2) (a, b (...) >= 0, not both 0): the
    Jacobi matrix from the Cholesky factor of the moments' Hankel matrix
    (Golub & Welsch 1969). The weights sum to 1."""
    mu = _moments(a, b, 2 * m)
    hankel = mu[..., np.arange(m + 1)[:, None] + np.arange(m + 1)[None, :]]
    r = np.swapaxes(np.linalg.cholesky(hankel), -1, -2)  # upper: H = R^T R
    d = np.diagonal(r, axis1=-2, axis2=-1)
    up = np.diagonal(r, offset=1, axis1=-2, axis2=-1)  # r_{j, j+1}
    ratio = up / d[..., :-1]
    alpha = ratio - np.concatenate([np.zeros(ratio.shape[:-1] + (1,)), ratio[..., :-1]], -1)
    beta = d[..., 1:m] / d[..., :m - 1]
    jac = np.zeros(alpha.shape[:-1] + (m, m))
    i = np.arange(m)
    jac[..., i, i] = alpha
    jac[..., i[:-1], i[1:]] = beta
    jac[..., i[1:], i[:-1]] = beta
    nodes, vec = np.linalg.eigh(jac)
    return nodes, mu[..., :1] * vec[..., 0, :] ** 2


def across_limb(cos_o, weight, sub, m: int):
    """Offsets (P, m, 2) from each pixel's centre, in pixel units (column, row), and
    weights (P, m) of ``trapezoid_rule``'s m points across the limb.

    ``cos_o`` (P, k^2): cos theta_o at the pixel's k x k sub-pixel samples (index
    ky * k + kx, as ``camera.film_samples``), ``weight`` (k^2,) their weights and
    ``sub`` (k,) their offsets within the pixel (``camera.pixel_rule``), to which
    a quadratic q(x) is fitted (weighted least squares; a plane for k < 3). u is
    the direction in which q falls at the centre (where it is flat, (1, 0)). The
    point of node s is on the chord {x in the pixel: u . x = s}, at its middle
    moved along u to where q equals q's mean over the chord (the iso-lines of
    cos theta_o are circles about the sphere's centre, not lines across the
    pixel: on the chord's middle a 64^2 sphere's limb pixels were 5e-4 off).
    """
    k = np.size(sub)
    sub = np.asarray(sub, np.float64) - 0.5
    x, y = np.tile(sub, k), np.repeat(sub, k)
    terms = [np.ones_like(x), x, y] + ([x * x, x * y, y * y] if k > 2 else [])
    design = np.stack(terms, -1)  # (k^2, 6), or (k^2, 3): 2 x 2 samples fit a plane only
    wd = design * np.asarray(weight, np.float64)[:, None]
    coef = np.asarray(cos_o, np.float64) @ np.linalg.solve(design.T @ wd, wd.T).T
    coef = np.concatenate([coef, np.zeros((coef.shape[0], 6 - coef.shape[1]))], -1)
    g = coef[:, 1:3]
    hess = np.stack([np.stack([2 * coef[:, 3], coef[:, 4]], -1),
                     np.stack([coef[:, 4], 2 * coef[:, 5]], -1)], -2)  # (P, 2, 2)
    norm = np.linalg.norm(g, axis=-1, keepdims=True)
    u = np.where(norm > 0, -g / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0]))
    v = np.stack([-u[:, 1], u[:, 0]], -1)  # along the limb
    nodes, w = trapezoid_rule(np.abs(u[:, 0]), np.abs(u[:, 1]), m)
    mid, length = _chords(nodes, u, v)  # (P, m) each
    x0 = nodes[..., None] * u[:, None] + mid[..., None] * v[:, None]  # (P, m, 2)
    # q along the chord: its mean exceeds q at the middle by q_vv L^2 / 24
    q_vv = np.einsum("pi,pij,pj->p", v, hess, v)
    slope = np.einsum("pi,pmi->pm", u, g[:, None] + np.einsum("pij,pmj->pmi", hess, x0))
    rise = q_vv[:, None] * length**2 / 24.0
    step = np.where(slope < 0, rise / np.where(slope < 0, slope, -1.0), 0.0)
    return x0 + np.clip(step, -MAX_MOVE, MAX_MOVE)[..., None] * u[:, None], w


def _chords(s, u, v):
    """(middle, length) (P, m) of the chords {s u + t v: t} of the unit pixel
    [-1/2, 1/2]^2 at the offsets ``s`` (P, m) along the unit directions ``u``
    (P, 2), ``v`` their perpendiculars."""
    lo = np.full(s.shape, -np.inf)
    hi = np.full(s.shape, np.inf)
    for a in range(2):
        c, d = s * u[:, a, None], v[:, a, None]  # |c + t d| <= 1/2
        flat = np.abs(d) < 1e-12
        d = np.where(flat, 1.0, d)
        t1, t2 = (-0.5 - c) / d, (0.5 - c) / d
        lo = np.where(flat, lo, np.maximum(lo, np.minimum(t1, t2)))
        hi = np.where(flat, hi, np.minimum(hi, np.maximum(t1, t2)))
    length = np.maximum(hi - lo, 0.0)
    return np.where(length > 0, 0.5 * (lo + hi), 0.0), length

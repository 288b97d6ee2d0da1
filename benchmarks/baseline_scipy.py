"""Baseline A: a hand-written NumPy model + ``scipy.optimize.least_squares``.

What a user would write without the project: a straightforward NumPy port of
``lambert + torrance_sparrow`` (Smith G, Beckmann D, dielectric Fresnel) with
the same k x k Gauss-Legendre pixel quadrature and the same "interior" pixel
mask, fitted in the raw parameters (rho_d RGB, m, eta) with box bounds,
``method="trf"``, ``x_scale="jac"`` and the default 2-point finite-difference
Jacobian. The material-independent geometry is computed once, as any user
would. Run by ``benchmarks/run.py``; not part of the package.

References: Walter et al. (2007) for the Smith G1 rational approximation and
the normalised Beckmann D (as Mitsuba 3's ``roughconductor``).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares

KEYS = ("lambert.rho_d", "torrance_sparrow.m", "torrance_sparrow.eta")
LOWER = np.array([0.0, 0.0, 0.0, 1e-3, 1.0])
UPPER = np.array([1.0, 1.0, 1.0, 1.0, 4.0])


def geometry(scene):
    """Interior pixels' samples: (index (P,), weights (K,), n (P,K,3), v (P,K,3), lights)."""
    k, w, h = scene.supersampling, scene.width, scene.height
    x, wt = np.polynomial.legendre.leggauss(k)
    sub, wt = 0.5 * (x + 1.0), 0.5 * wt
    sx = (np.arange(w)[:, None] + sub)[None, :, None, :]
    sy = (np.arange(h)[:, None] + sub)[:, None, :, None]
    fx = np.broadcast_to(2.0 * sx / w - 1.0, (h, w, k, k)).reshape(h * w, k * k)
    fy = np.broadcast_to((1.0 - 2.0 * sy / h) * (h / w), (h, w, k, k)).reshape(h * w, k * k)
    cam = scene.camera
    o = np.asarray(cam.origin, float)
    fwd = np.subtract(cam.target, o)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, cam.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    t = np.tan(np.radians(cam.fov) / 2)
    d = fwd + (t * fx)[..., None] * right + (t * fy)[..., None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    c, r = np.asarray(scene.sphere.center, float), scene.sphere.radius
    oc = o - c
    b = d @ oc
    disc = b * b - (oc @ oc - r * r)
    hit = disc > 0
    tt = -b - np.sqrt(np.where(hit, disc, 0.0))
    interior = hit.all(axis=1) & (tt > 0).all(axis=1)
    idx = np.nonzero(interior)[0]
    d, tt = d[idx], tt[idx]
    pos = o + tt[..., None] * d
    n = (pos - c) / r
    lights = []
    for light in scene.lights:
        lp = np.asarray(light.position, float)
        to = lp - pos
        dist2 = np.sum(to * to, axis=-1)
        lights.append((to / np.sqrt(dist2)[..., None], np.asarray(light.intensity, float),
                       1.0 / dist2))
    return idx, (wt[:, None] * wt[None, :]).reshape(-1), n, -d, lights


def _g1(c, m):
    tan = np.sqrt(np.maximum(1.0 - c * c, 0.0)) / c
    a = np.minimum(1.0 / np.maximum(m * tan, 1e-300), 1.6)
    g = (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
    return np.where(a >= 1.6, 1.0, g)


def _fresnel(ci, eta):
    ct2 = 1.0 - (1.0 - ci * ci) / (eta * eta)
    ct = np.sqrt(np.maximum(ct2, 0.0))
    rp = (eta * ci - ct) / (eta * ci + ct)
    rs = (ci - eta * ct) / (ci + eta * ct)
    return np.where(ct2 > 0, 0.5 * (rp * rp + rs * rs), 1.0)


def model(x, geo):
    """(P, 3) pixel values for x = (rho_r, rho_g, rho_b, m, eta)."""
    _, wt, n, v, lights = geo
    rho, m, eta = x[:3], x[3], x[4]
    co = np.sum(n * v, axis=-1)
    out = np.zeros(n.shape[:1] + (3,))
    for l, intensity, falloff in lights:
        ci = np.sum(n * l, axis=-1)
        ok = (ci > 0) & (co > 0)
        hv = l + v
        hv /= np.linalg.norm(hv, axis=-1, keepdims=True)
        ch = np.sum(n * hv, axis=-1)
        tan2 = (1.0 - ch * ch) / (ch * ch)
        d = np.exp(-tan2 / (m * m)) / (np.pi * m * m * ch ** 4)
        g = _g1(np.where(ok, ci, 1.0), m) * _g1(np.where(ok, co, 1.0), m)
        f = _fresnel(np.clip(np.sum(v * hv, axis=-1), 0.0, 1.0), eta)
        spec = np.where(ok, d * g * f / (4.0 * np.where(ok, ci * co, 1.0)), 0.0)
        e = np.where(ok, ci * falloff, 0.0)  # irradiance per unit intensity
        diffuse = (e @ wt)[:, None] * rho / np.pi
        specular = ((spec * e) @ wt)[:, None]
        out += (diffuse + specular) * intensity
    return out


def fit(target, scene, x0, truth_vec, *, max_nfev=None, record=None):
    """Fit with scipy; returns (x, seconds, nfev, samples).

    ``record(x, t)`` is called after each iteration (scipy's callback) with the
    elapsed seconds, excluding the recording itself.
    """
    geo = geometry(scene)
    flat = np.asarray(target, float).reshape(-1, 3)[geo[0]]

    def res(x):
        return (model(x, geo) - flat).reshape(-1)

    paused = [0.0]
    t0 = time.perf_counter()

    def callback(intermediate_result):
        if record is not None:
            ta = time.perf_counter()
            record(np.array(intermediate_result.x), ta - t0 - paused[0])
            paused[0] += time.perf_counter() - ta

    sol = least_squares(res, np.asarray(x0, float), bounds=(LOWER, UPPER), method="trf",
                        x_scale="jac", max_nfev=max_nfev, callback=callback)
    return sol.x, time.perf_counter() - t0 - paused[0], sol.nfev, geo

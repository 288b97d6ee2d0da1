"""Lobes against references written independently from the lecture's angle forms.

Each reference here is NumPy, forms angles (theta, phi) or traces rays itself,
and calls no formula of ``fitter``: a wrong identity in the model (or the same
mistake repeated in its Mitsuba plugin) shows here.

References:
    Teschner, *Materials 3*, "Oren-Nayar diffuse material":
        f = rho/pi (A + B max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta)),
        A = 1 - sigma^2/(2(sigma^2 + 0.33)), B = 0.45 sigma^2/(sigma^2 + 0.09),
        alpha = max(theta_i, theta_o), beta = min(theta_i, theta_o).
    Teschner, *Materials 2*, "Mixed diffuse / specular reflection":
        f = rho_s ((2 (n.wi) n - wi).wo)^e, a lobe about the mirror direction;
        reflectance rho(wi) = int_{2pi} f cos(theta_o) dwo.
    Teschner, *Materials 3*, "Snell's law", "Fresnel", "Total internal
        reflection", "Light attenuation" (Beer-Lambert L_a = c^d L_b).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitter
from fitter.bsdf import LOBES

#: float64 agreement of the same formula evaluated through different
#: identities (angles via arccos/arctan2 vs dot products): arccos near 1 loses
#: ~sqrt(ulp) in the angle, so a few 1e-9 relative; 1e-8 leaves a margin of ~3.
REL_TOL = 1e-8
#: Gauss-Legendre reference integral, 400 x 800 nodes on the hemisphere about n
#: (smooth integrand, the horizon is the domain's edge): measured |Q_400 -
#: Q_800| < 1e-11; the lobe's own quadrature (about the mirror axis, cut at
#: the horizon) converges as N^-2 there: 7e-5 (``test_bsdf_properties``).
INTEGRAL_TOL = 2e-4


def _random_pairs(seed, n):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v[:, 2] = np.abs(v[:, 2]) + 1e-3
        out.append(v / np.linalg.norm(v, axis=1, keepdims=True))
    return out


def _model(lobe, params, opts, wi, wo):
    """fitter's f(wi, wo), red channel, about n = +z."""
    n = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0]), wo.shape)
    wi = jnp.broadcast_to(jnp.asarray(wi), wo.shape)
    p = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in params.items()}
    return np.asarray(jax.jit(lambda p, n, a, b: LOBES[lobe].eval(p, opts, n, a, b)[..., 0])(
        p, n, wi, jnp.asarray(wo)))


def _angles(v):
    return np.arccos(np.clip(v[..., 2], -1.0, 1.0)), np.arctan2(v[..., 1], v[..., 0])


def oren_nayar_reference(rho, sigma, wi, wo):
    """The lecture's angle form, literally."""
    ti, pi_ = _angles(wi)
    to, po = _angles(wo)
    s2 = sigma**2
    a = 1.0 - s2 / (2.0 * (s2 + 0.33))
    b = 0.45 * s2 / (s2 + 0.09)
    alpha, beta = np.maximum(ti, to), np.minimum(ti, to)
    return rho / np.pi * (a + b * np.maximum(0.0, np.cos(pi_ - po)) * np.sin(alpha) * np.tan(beta))


@pytest.mark.parametrize("sigma", [0.2, 0.6, 1.2])
def test_oren_nayar_matches_angle_form(sigma):
    wi, wo = _random_pairs(1, 4000)
    got = _model("oren_nayar", {"rho_d": np.full(3, 0.7), "sigma": sigma}, {}, wi, wo)
    np.testing.assert_allclose(got, oren_nayar_reference(0.7, sigma, wi, wo), rtol=REL_TOL,
                               atol=1e-14)
    # The reference discriminates: a cos(phi) without max(0, .) or sigma for sigma^2 differ.
    assert np.max(np.abs(oren_nayar_reference(0.7, sigma**0.5, wi, wo) - got)) > 1e-3


def phong_reference(rho_s, e, wi, wo):
    """rho_s (r.wo)^e with r built from angles: (theta_i, phi_i + pi)."""
    ti, pi_ = _angles(wi)
    r = np.stack([np.sin(ti) * np.cos(pi_ + np.pi), np.sin(ti) * np.sin(pi_ + np.pi),
                  np.cos(ti)], -1)
    c = np.sum(r * wo, axis=-1)
    return rho_s * np.where(c > 0, np.abs(c) ** e, 0.0)


def _hemisphere_integral(f, n_theta):
    """int_{2pi} f(wo) cos(theta_o) dwo, Gauss-Legendre in theta, midpoint in phi."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    theta = 0.25 * np.pi * (x + 1.0)
    wt = 0.25 * np.pi * w * np.sin(theta) * np.cos(theta)
    phi = (np.arange(2 * n_theta) + 0.5) * np.pi / n_theta
    wo = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.sin(theta)[:, None] * np.sin(phi),
                   np.cos(theta)[:, None] + 0 * phi], -1).reshape(-1, 3)
    return float(np.sum(f(wo).reshape(n_theta, -1) * wt[:, None]) * np.pi / n_theta)


@pytest.mark.parametrize("theta_i", [0.8, 1.2])
def test_phong_oblique_pointwise_and_integral(theta_i):
    """At oblique incidence the lobe about the mirror direction and one about n
    differ; the model's values and its reflectance follow the mirror form."""
    e, rho_s = 20.0, 0.8
    wi, wo = _random_pairs(2, 4000)
    got = _model("phong", {"rho_s": np.full(3, rho_s), "e": e}, {"normalized": False}, wi, wo)
    np.testing.assert_allclose(got, phong_reference(rho_s, e, wi, wo), rtol=REL_TOL, atol=1e-14)

    w1 = np.array([np.sin(theta_i), 0.0, np.cos(theta_i)])
    ref = _hemisphere_integral(lambda wo: phong_reference(rho_s, e, w1[None], wo), 400)
    ref2 = _hemisphere_integral(lambda wo: phong_reference(rho_s, e, w1[None], wo), 800)
    assert abs(ref - ref2) < 1e-9
    model = _hemisphere_integral(
        lambda wo: _model("phong", {"rho_s": np.full(3, rho_s), "e": e}, {"normalized": False},
                          w1, wo), 400)
    assert abs(model - ref) < INTEGRAL_TOL * ref, (model, ref)
    # A lobe about n has reflectance rho_s 2pi/(e+2) at every incidence: far off here.
    about_n = rho_s * 2.0 * np.pi / (e + 2.0)
    assert abs(about_n - ref) > 0.1 * ref


# --- Dielectric sphere under a textured envmap, traced ray by ray ------------

def _env_lookup(img, d):
    """Bilinear lat-long lookup, Mitsuba's envmap convention (u from atan2(x, -z),
    theta from +y), written here for the reference."""
    h, w = img.shape[:2]
    u = np.arctan2(d[0], -d[2]) / (2 * np.pi) % 1.0
    v = np.arctan2(np.hypot(d[0], d[2]), d[1]) / np.pi
    fx, fy = u * w - 0.5, v * (h - 1)
    x0, y0 = int(np.floor(fx)), int(min(max(np.floor(fy), 0), h - 2))
    wx, wy = fx - x0, fy - y0
    x0, x1 = x0 % w, (x0 + 1) % w
    top = img[y0, x0] * (1 - wx) + img[y0, x1] * wx
    bot = img[y0 + 1, x0] * (1 - wx) + img[y0 + 1, x1] * wx
    return top * (1 - wy) + bot * wy


def _fresnel_snell(d, n, eta):
    """(F, refracted direction or None under TIR) for unit d hitting a surface
    with unit normal n facing d's origin, relative index eta (far / near side)."""
    cos_i = -float(d @ n)
    sin_t2 = (1.0 - cos_i**2) / eta**2
    if sin_t2 >= 1.0:
        return 1.0, None
    cos_t = np.sqrt(1.0 - sin_t2)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return 0.5 * (rs**2 + rp**2), d / eta + (cos_i / eta - cos_t) * n


def trace_dielectric(p, d, eta, att, r, img, bounces):
    """Explicit path sum for one camera ray hitting the centred sphere at p."""
    n = p / r
    f0, t = _fresnel_snell(d, n, eta)
    out = f0 * _env_lookup(img, d - 2 * (d @ n) * n)
    weight = (1.0 - f0) * eta**2 * np.ones(3)  # radiance gain entering
    for _ in range(bounces + 1):
        s = -2.0 * float(p @ t)  # chord to the far side of the sphere
        p = p + s * t
        n_in = -p / r  # normal facing the ray, inside
        weight = weight * att**s
        f, t_out = _fresnel_snell(t, n_in, 1.0 / eta)
        if t_out is not None:
            out = out + weight * (1.0 - f) / eta**2 * _env_lookup(img, t_out)
        weight = weight * f
        t = t - 2.0 * float(t @ n_in) * n_in
    return out


@pytest.mark.parametrize("eta", [1.5, 2.4])
def test_dielectric_rotation_matches_explicit_trace(eta, tmp_path):
    from fitter.imageio import read_image
    from fitter.mitsuba.synth import make_envmap

    env = str(tmp_path / "env.exr")
    make_envmap(env)
    img = np.asarray(read_image(env), dtype=np.float64)
    r, size, hw, bounces = 0.79, 15, 1.2, 4
    att = np.array([0.6, 0.8, 0.95])
    scene = fitter.Scene(width=size, height=size, supersampling=1,
                         camera=fitter.Camera(type="orthographic", origin=(0.0, 0.0, 4.0),
                                              half_width=hw),
                         sphere=fitter.Sphere(radius=r),
                         environment=fitter.Environment(type="envmap", file=env))
    got = np.asarray(fitter.render({"dielectric.eta": eta, "dielectric.attenuation": att,
                                    "dielectric.bounces": bounces}, scene))
    d = np.array([0.0, 0.0, -1.0])
    checked = 0
    for i, j in [(7, 7), (3, 7), (7, 11), (5, 5), (9, 4), (4, 9), (10, 10), (6, 3)]:
        x = hw * ((j + 0.5) * 2.0 / size - 1.0)
        y = hw * (1.0 - (i + 0.5) * 2.0 / size)
        rho2 = x * x + y * y
        if rho2 >= r * r:
            continue
        p = np.array([x, y, np.sqrt(r * r - rho2)])
        ref = trace_dielectric(p, d, eta, att, r, img, bounces)
        np.testing.assert_allclose(got[i, j], ref, rtol=1e-9, err_msg=f"pixel {(i, j)}")
        checked += 1
    assert checked == 8

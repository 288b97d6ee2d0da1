"""Closed forms from the lecture, checked against the model's building blocks.

References (Teschner, *Advanced Computer Graphics, Materials 1-3*):
    solid angle: int_{2pi} d omega = 2pi, int_{2pi} cos^n d omega = 2pi/(n+1);
    Lambert: L_o = rho E / pi;
    Fresnel: F_r = 1/2 (r_p^2 + r_s^2), F_r(normal) = ((eta-1)/(eta+1))^2
        (0.04 for eta = 1.5), F_r(grazing) = 1, total internal reflection for
        eta < 1 beyond the critical angle (cos_t^2 < 0);
    Snell: sin(theta_i) / sin(theta_t) = eta, t = w/eta - (cos_t - cos_i/eta) n;
    Oren-Nayar: sigma = 0 gives A = 1, B = 0 (Lambert);
    Beer-Lambert: L_a = c^d L_b;
    specular transmission: L_t = (eta_t/eta_i)^2 L_i, which cancels on a full
        pass through a sphere.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitter
from fitter.bsdf import LOBES
from fitter.bsdf.fresnel import fresnel_dielectric, refract
from conftest import fresnel_reference, spherical_quadrature

#: The quadrature used by the energy tests, at its resolution there.
N_THETA = 100
#: Its error on these smooth integrands (measured: < 1e-13).
QUAD_TOL = 1e-12
#: Float64 agreement of closed forms evaluated two ways (a few ulps).
EXACT = 1e-12

ORTHO = fitter.Camera(type="orthographic", origin=(0.0, 0.0, 4.0), half_width=1.2)


def test_hemisphere_solid_angle_and_cos_power():
    """int_{2pi} d omega = 2pi, int_{4pi} d omega = 4pi, int_{2pi} cos^n = 2pi/(n+1)."""
    axis = np.array([0.3, -0.2, 0.9])  # any axis: the rule is rotation invariant
    dirs, w = spherical_quadrature(axis, N_THETA, 2 * N_THETA)
    assert abs(w.sum() - 2 * np.pi) < QUAD_TOL
    _, w4 = spherical_quadrature(axis, N_THETA, 4, theta_max=np.pi)
    assert abs(w4.sum() - 4 * np.pi) < QUAD_TOL
    cos = dirs @ (axis / np.linalg.norm(axis))
    for n in (1, 2, 5, 20, 100):
        assert abs(np.sum(w * cos**n) - 2 * np.pi / (n + 1)) < QUAD_TOL, n


def _dirs(rng, n):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    return jnp.asarray(v)


def test_lambert_brdf_and_radiance():
    """f = rho/pi for every pair; a surface facing a distant light of irradiance
    E has L = rho E / pi (centre pixel of an orthographic view along the light)."""
    rng = np.random.default_rng(0)
    wi, wo = _dirs(rng, 500), _dirs(rng, 500)
    n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), wi.shape)
    rho = np.array([0.6, 0.3, 0.1])
    f = np.asarray(LOBES["lambert"].eval({"rho_d": jnp.asarray(rho)}, {}, n, wi, wo))
    np.testing.assert_allclose(f, np.broadcast_to(rho / np.pi, f.shape), rtol=EXACT)

    E = np.array([2.0, 3.0, 5.0])
    scene = fitter.Scene(width=9, height=9, supersampling=1, camera=ORTHO,
                         lights=(fitter.DirectionalLight((0.0, 0.0, -1.0), tuple(E)),))
    img = np.asarray(fitter.render({"lambert.rho_d": rho}, scene))
    np.testing.assert_allclose(img[4, 4], rho * E / np.pi, rtol=EXACT)


def test_oren_nayar_sigma_zero_is_lambert():
    rng = np.random.default_rng(1)
    wi, wo = _dirs(rng, 2000), _dirs(rng, 2000)
    n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), wi.shape)
    rho = jnp.array([0.7, 0.5, 0.2])
    on = LOBES["oren_nayar"].eval({"rho_d": rho, "sigma": jnp.asarray(0.0)}, {}, n, wi, wo)
    lam = LOBES["lambert"].eval({"rho_d": rho}, {}, n, wi, wo)
    np.testing.assert_array_equal(np.asarray(on), np.asarray(lam))


# --- Fresnel ---------------------------------------------------------------

def F(cos_i, eta):
    return np.asarray(fresnel_dielectric(jnp.asarray(cos_i, dtype=jnp.float64),
                                         jnp.asarray(eta, dtype=jnp.float64)))


def test_fresnel_normal_grazing_and_general():
    assert abs(F(1.0, 1.5) - 0.04) < EXACT
    for eta in (1.0, 1.2, 1.5, 2.0, 4.0, 0.5, 1 / 1.5):
        assert abs(F(1.0, eta) - ((eta - 1) / (eta + 1)) ** 2) < EXACT, eta
        assert F(0.0, eta) == 1.0, eta
    c = np.linspace(0.0, 1.0, 101)
    for eta in (1.2, 1.5, 2.5, 4.0):
        np.testing.assert_allclose(F(c, eta), fresnel_reference(c, eta), rtol=EXACT, atol=EXACT)
        assert np.all((F(c, eta) >= 0) & (F(c, eta) <= 1))


def test_fresnel_eta_one_is_transparent():
    c = np.linspace(1e-3, 1.0, 200)
    np.testing.assert_allclose(F(c, 1.0), 0.0, atol=EXACT)


@pytest.mark.parametrize("eta", [1 / 1.5, 1 / 2.0, 0.9])
def test_total_internal_reflection_and_continuity(eta):
    """eta < 1: F = 1 for theta_i > theta_c = arcsin(eta), and F -> 1 continuously
    as theta_i -> theta_c from below (1 - F ~ sqrt(cos_t^2) -> 0)."""
    cos_c = np.sqrt(1.0 - eta**2)
    beyond = np.linspace(0.0, cos_c, 50, endpoint=False)
    np.testing.assert_array_equal(F(beyond, eta), 1.0)
    assert F(cos_c * (1 - 1e-15), eta) == 1.0
    gaps = [1.0 - F(cos_c + d, eta) for d in (1e-4, 1e-6, 1e-8, 1e-10)]
    assert all(g > 0 for g in gaps) and gaps[-1] < 1e-3
    assert all(b < a for a, b in zip(gaps, gaps[1:]))
    inside = np.linspace(cos_c + 1e-3, 1.0, 50)
    np.testing.assert_allclose(F(inside, eta), fresnel_reference(inside, eta), rtol=EXACT)
    grad = jax.vmap(jax.grad(fresnel_dielectric, argnums=(0, 1)), in_axes=(0, None))(
        jnp.linspace(0.0, 1.0, 64), jnp.asarray(eta))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grad)


def test_snell_refraction():
    """t is unit, into the surface, coplanar with d and n, sin_i = eta sin_t."""
    rng = np.random.default_rng(2)
    n = np.array([0.0, 0.0, 1.0])
    d = -np.asarray(_dirs(rng, 500))  # travelling into the surface
    for eta in (1.0, 1.33, 1.5, 2.4):
        t, tir = refract(jnp.asarray(d), jnp.broadcast_to(jnp.asarray(n), d.shape), eta)
        t = np.asarray(t)
        assert not np.any(np.asarray(tir))
        np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0, atol=EXACT)
        assert np.all(t @ n < 0)
        np.testing.assert_allclose(np.linalg.det(np.stack([d, np.broadcast_to(n, d.shape), t], 1)),
                                   0.0, atol=EXACT)
        sin_i = np.linalg.norm(np.cross(d, n), axis=1)
        sin_t = np.linalg.norm(np.cross(t, n), axis=1)
        np.testing.assert_allclose(sin_i, eta * sin_t, atol=EXACT)
        if eta == 1.0:
            np.testing.assert_allclose(t, d, atol=EXACT)


# --- Dielectric sphere: Beer-Lambert and energy conservation -------------------

def _ortho_hits(scene):
    """Independent ray-sphere test of pixel centres (orthographic along -z, k = 1):
    (hit mask (H, W), squared distance rho^2 of the ray from the sphere axis)."""
    w, h, hw = scene.width, scene.height, scene.camera.half_width
    x = hw * ((np.arange(w) + 0.5) * 2.0 / w - 1.0)
    y = hw * (1.0 - (np.arange(h) + 0.5) * 2.0 / h) * h / w
    rho2 = x[None, :] ** 2 + y[:, None] ** 2
    return rho2 < scene.sphere.radius**2, rho2


def test_beer_lambert_through_sphere():
    """eta = 1: no refraction, F = 0; a ray at distance rho from the axis crosses
    a chord 2 sqrt(r^2 - rho^2) and arrives attenuated by c^chord."""
    L = np.array([1.5, 2.0, 0.5])
    c = np.array([0.5, 0.2, 0.9])
    r = 0.79  # no pixel centre within rounding of the silhouette (0.8 would hit 0.48, 0.64)
    scene = fitter.Scene(width=15, height=15, supersampling=1, camera=ORTHO,
                         sphere=fitter.Sphere(radius=r),
                         environment=fitter.Environment(type="constant", radiance=tuple(L)))
    img = np.asarray(fitter.render({"dielectric.eta": 1.0, "dielectric.attenuation": c}, scene))
    hit, rho2 = _ortho_hits(scene)
    chord = 2.0 * np.sqrt(np.where(hit, r * r - rho2, 0.0))
    expected = np.where(hit[..., None], c ** chord[..., None] * L, L)
    np.testing.assert_allclose(img, expected, rtol=1e-10)
    np.testing.assert_allclose(img[7, 7], c ** (2 * r) * L, rtol=1e-10)  # centre pixel


@pytest.mark.parametrize("eta", [1.2, 1.5, 2.5])
def test_lossless_dielectric_sphere_conserves_radiance(eta):
    """A lossless sphere in a constant environment L: reflection F plus the
    transmitted series (1-F)^2 sum_k F^k (eta^2 in, eta^-2 out cancel; on a
    sphere every internal hit has the same Fresnel F as the entry) gives
    L (1 - (1-F) F^(B+1)) with B internal bounces, -> L as B grows."""
    L = np.array([1.0, 2.0, 3.0])
    r = 0.79
    scene = fitter.Scene(width=15, height=15, supersampling=1, camera=ORTHO,
                         sphere=fitter.Sphere(radius=r),
                         environment=fitter.Environment(type="constant", radiance=tuple(L)))
    hit, rho2 = _ortho_hits(scene)
    cos_i = np.sqrt(np.where(hit, 1.0 - rho2 / r**2, 1.0))
    Fr = fresnel_reference(cos_i, eta)
    for bounces in (0, 3, 64):
        img = np.asarray(fitter.render({"dielectric.eta": eta, "dielectric.attenuation": 1.0,
                                        "dielectric.bounces": bounces}, scene))
        kept = np.where(hit, 1.0 - (1.0 - Fr) * Fr ** (bounces + 1), 1.0)  # misses see L
        expected = L * kept[..., None]
        np.testing.assert_allclose(img, expected, rtol=1e-10)
    inner = img[hit & (cos_i > 0.2)]  # F < 0.6 there: F^65 < 1e-14
    np.testing.assert_allclose(inner, np.broadcast_to(L, inner.shape), rtol=EXACT)


@pytest.mark.parametrize("eta", [1.33, 2.0])
def test_absorbing_dielectric_sphere_series(eta):
    """Refraction and Beer-Lambert together. On a sphere every internal chord has
    the same length s = 2 r cos_t and every internal hit the same F as the
    entry, so with T = c^s the traced sum is the geometric series
    L (F + (1-F)^2 T (1 - (F T)^(B+1)) / (1 - F T))."""
    L = np.array([1.0, 2.0, 3.0])
    c = np.array([0.3, 0.6, 0.9])
    r, bounces = 0.79, 5
    scene = fitter.Scene(width=15, height=15, supersampling=1, camera=ORTHO,
                         sphere=fitter.Sphere(radius=r),
                         environment=fitter.Environment(type="constant", radiance=tuple(L)))
    img = np.asarray(fitter.render({"dielectric.eta": eta, "dielectric.attenuation": c,
                                    "dielectric.bounces": bounces}, scene))
    hit, rho2 = _ortho_hits(scene)
    cos_i = np.sqrt(np.where(hit, 1.0 - rho2 / r**2, 1.0))
    Fr = fresnel_reference(cos_i, eta)[..., None]
    cos_t = np.sqrt(1.0 - (1.0 - cos_i**2) / eta**2)
    T = c ** (2.0 * r * cos_t)[..., None]
    series = Fr + (1 - Fr) ** 2 * T * (1 - (Fr * T) ** (bounces + 1)) / (1 - Fr * T)
    expected = np.where(hit[..., None], L * series, L)
    np.testing.assert_allclose(img, expected, rtol=1e-10)

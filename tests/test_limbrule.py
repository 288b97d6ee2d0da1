"""A limb pixel's env samples: the Gauss rule across the limb (``fitter.limbrule``)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fitter import geometry
from fitter.camera import camera_rays, film_samples
from fitter.limbrule import across_limb, trapezoid_rule
from fitter.scene import Scene

#: Nodes and weights against NumPy's Gauss-Legendre (a different algorithm): float64
#: rounding of the Hankel matrix's Cholesky factor.
RULE_ATOL = 1e-10
#: Moments of degree < 10 of a unit pixel's offset (at most 2^-j): float64 rounding.
MOMENT_ATOL = 1e-12
#: Against a 64 x 64 midpoint grid over wholly covered limb pixels (64^2 sphere, 4 x 4
#: Gauss sub-samples): the rule across the limb was 6.8e-5 off at most (the 4 x 4 grid it
#: replaces 2.7e-5; on the chord's middles, without the iso-lines' curvature, 4.9e-4).
LIMB_RTOL = 1.5e-4


@pytest.mark.parametrize("m", [2, 3, 4, 6, 8])
@pytest.mark.parametrize("axis", [(1.0, 0.0), (0.0, 1.0)])
def test_rule_on_a_pixel_axis_is_gauss_legendre(m, axis):
    """Across a pixel's edge the density of the offset is uniform on [-1/2, 1/2]:
    its Gauss rule is Gauss-Legendre's, scaled (NumPy's, by Golub-Welsch on the
    Legendre recurrence, not from moments)."""
    nodes, weights = trapezoid_rule(*axis, m)
    x, w = np.polynomial.legendre.leggauss(m)
    np.testing.assert_allclose(nodes, x / 2, atol=RULE_ATOL)
    np.testing.assert_allclose(weights, w / 2, atol=RULE_ATOL)


@settings(max_examples=30, deadline=None)
@given(st.floats(0.0, np.pi / 2), st.integers(2, 5))
def test_rule_integrates_polynomials_across_a_turned_pixel(phi, m):
    """int over the unit pixel of (x cos phi + y sin phi)^j dx dy for j < 2m, as an
    8 x 8 Gauss-Legendre product over the square computes it (exact to degree 15)."""
    a, b = np.cos(phi), np.sin(phi)
    nodes, weights = trapezoid_rule(a, b, m)
    x, w = np.polynomial.legendre.leggauss(8)
    s = (a * x[:, None] + b * x[None, :]) / 2
    ww = np.outer(w, w) / 4
    for j in range(2 * m):
        assert np.sum(weights * nodes**j) == pytest.approx(np.sum(ww * s**j), abs=MOMENT_ATOL)
    assert np.all(np.abs(nodes) <= (a + b) / 2)  # inside the density's support


def test_points_follow_the_fall_of_cos_theta_o():
    """A linear cos theta_o falling to the right puts every point on the row
    through the pixel's centre, at Gauss-Legendre's offsets."""
    nodes, w1 = np.polynomial.legendre.leggauss(4)
    sub = (nodes + 1) / 2  # the 4 x 4 Gauss sub-samples' offsets in the pixel
    x = np.tile(sub, 4) - 0.5  # (column offsets, index ky * k + kx)
    cos_o = (0.3 - 0.1 * x)[None]
    weight = np.outer(w1 / 2, w1 / 2).reshape(-1)
    off, w = across_limb(cos_o, weight, sub, 4)
    np.testing.assert_allclose(off[0, :, 1], 0.0, atol=RULE_ATOL)
    np.testing.assert_allclose(off[0, :, 0], nodes / 2, atol=RULE_ATOL)
    assert w.sum() == pytest.approx(1.0)


def _env_samples(scene, nodes, monkeypatch):
    """(rows, normals, views, weights) of ``geometry.env_samples`` with
    ``LIMB_NODES`` = ``nodes``, the traced pixels' flat indices and which of
    them every sub-pixel sample sees on the sphere."""
    monkeypatch.setattr(geometry, "LIMB_NODES", nodes)
    o, d = camera_rays(scene)
    h, w, k2, _ = d.shape
    t = geometry.intersect_sphere(o, d, scene.sphere.center, scene.sphere.radius)
    hit_all = np.isfinite(t).reshape(h * w, k2)
    idx = np.nonzero(hit_all.any(1))[0]
    hit = hit_all[idx]
    wt = film_samples(scene, np.zeros(1, np.int64))[2]
    out = geometry.env_samples(
        scene, hit, np.where(hit, t.reshape(h * w, k2)[idx], 0.0),
        o.reshape(h * w, k2, 3)[idx], d.reshape(h * w, k2, 3)[idx], wt, idx)
    return out, idx, hit.all(1)


def _per_pixel(samples, f, n_pixels):
    """Each pixel's weighted sum of f(normal, view) over its env samples."""
    rows, n, v, ww = samples
    return np.bincount(rows, ww * f(n, v), minlength=n_pixels)


def _steep(n, v):
    """Schlick's Fresnel factor plus a square root: steep in cos theta_o at the limb."""
    c = np.clip(np.sum(n * v, -1), 0.0, 1.0)
    return (1.0 - c) ** 5 + np.sqrt(c)


def test_limb_pixels_integrate_a_steep_function_of_the_view_angle(monkeypatch):
    """Reference: each pixel's box average by a 64 x 64 midpoint grid (independent
    of the sub-pixel rule), over the limb pixels (centre cos theta_o < 0.35) that
    it sees wholly on the sphere; the rule across the limb (k = 4 points) against it,
    and, as a control, the pixel centre alone is far off."""
    scene = Scene(width=64, height=64, supersampling=4)
    samples, idx, full = _env_samples(scene, None, monkeypatch)
    val = _per_pixel(samples, _steep, idx.size)
    dense = scene.replace(supersampling=64, pixel_rule="midpoint")
    o, d = camera_rays(dense, idx)
    t = geometry.intersect_sphere(o, d, scene.sphere.center, scene.sphere.radius)
    hit = np.isfinite(t)
    n = (o + np.where(hit, t, 0.0)[..., None] * d - np.asarray(scene.sphere.center))
    ref = np.where(hit, _steep(n / scene.sphere.radius, -d), 0.0).mean(axis=(1, 2))
    oc, dc = camera_rays(scene.replace(supersampling=1, pixel_rule="midpoint"), idx)
    tc = geometry.intersect_sphere(oc, dc, scene.sphere.center, scene.sphere.radius)
    nc = (oc + tc[..., None] * dc - np.asarray(scene.sphere.center)) / scene.sphere.radius
    cos_c = -np.sum(nc * dc, -1).reshape(-1)
    limb = full & hit.reshape(idx.size, -1).all(1) & (cos_c < geometry.ENV_LIMB_COS)
    assert limb.sum() > 100
    err = np.abs(val - ref)[limb] / ref[limb]
    assert err.max() < LIMB_RTOL
    centre = _steep(nc.reshape(-1, 3), -dc.reshape(-1, 3))
    assert (np.abs(centre - ref)[limb] / ref[limb]).max() > 20 * LIMB_RTOL


@pytest.mark.parametrize("k, rule", [(1, "gauss"), (2, "gauss"), (3, "midpoint"), (4, "gauss")])
def test_limb_samples_are_fewer_and_weigh_each_pixel_once(k, rule, monkeypatch):
    """The rule across the limb: k samples per limb pixel instead of k^2 (one, the
    centre, for k = 1), the weights of each pixel wholly on the sphere summing to
    1 either way (a pixel where a point misses keeps its sub-samples)."""
    scene = Scene(width=64, height=64, supersampling=k, pixel_rule=rule)
    counts = {}
    for nodes in (0, None):
        samples, idx, full = _env_samples(scene, nodes, monkeypatch)
        weights = _per_pixel(samples, lambda n, v: np.ones(len(n)), idx.size)
        np.testing.assert_allclose(weights[full], 1.0, rtol=1e-12)
        counts[nodes] = np.bincount(samples[0], minlength=idx.size)
    fewer = counts[None] != counts[0]
    if k == 1:
        assert not fewer.any()
    else:
        assert fewer.sum() > 30
        assert np.all(counts[None][fewer] == k) and np.all(counts[0][fewer] == k * k)

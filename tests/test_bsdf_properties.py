"""Physical properties of every BRDF lobe: positivity, reciprocity, energy, linearity.

References:
    Teschner, *Materials 2*, "Properties of BRDFs": Helmholtz reciprocity,
        energy conservation  for all wi: int_{2pi} f(wi, wo) cos(theta_o) dwo <= 1,
        linearity of BRDFs; "Example - glossy reflection" (Phong).
    Teschner, *Materials 3*, "Torrance-Sparrow", "Beckmann distribution".
    Walter et al. (2007), EGSR, eq. 27: Beckmann Smith G1 rational form.

Reflectances are computed by the quadrature of ``conftest.spherical_quadrature``
(Gauss-Legendre in theta, midpoint in phi). Each integral is done at two
resolutions (N and 2N nodes in theta); their difference is the stated
quadrature-error estimate and must itself be below ``QUAD_TOL``.
"""

from __future__ import annotations

import functools
import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitter
from fitter.bsdf import LOBES, tables
from fitter.bsdf.microfacet import beckmann_d_lecture
from conftest import fresnel_reference, spherical_quadrature

#: Quadrature error allowed on a directional-hemispherical reflectance. The
#: measured |Q_N - Q_2N| reach 7e-5 where the horizon cuts a broad lobe (a kink
#: the rule converges on as N^-2; normalised Phong e = 1 at grazing incidence)
#: and are ~1e-14 where it does not (Lambert, Phong at normal incidence).
QUAD_TOL = 1e-4
#: Reciprocity / closed-form comparisons in float64: a few ulps of the
#: arithmetic in the lobe formulas ...
REL_TOL = 1e-12
#: ... plus an absolute floor (1/sr) for values that are rounding noise
#: (F at eta = 1 is ~1e-33, not symmetric in its last bit) or subnormal.
ABS_FLOOR = 1e-14
N_THETA = 100  # Gauss-Legendre nodes in theta; phi uses 2 * N_THETA midpoints
NORMAL = np.array([0.0, 0.0, 1.0])
THETA_I = (0.0, 0.5, 1.0, 1.4, 1.55)  # incident angles, radians


def _p(d):
    return {k: jnp.asarray(v, dtype=jnp.float64) for k, v in d.items()}


def property_cases(lobes=None, conserving_only=False):
    """(id, lobe, params, options) of every BRDF lobe's ``hints.points`` (at the
    top of their reflectance box: rho = 1), read from the registry when called."""
    lobes = LOBES if lobes is None else lobes
    return [(pt.id, name, dict(pt.params), dict(pt.options))
            for name, lobe in lobes.items() if lobe.kind == "brdf"
            for pt in lobe.hints.points if pt.conserving or not conserving_only]


ALL_BRDFS = property_cases()
CONSERVING = property_cases(conserving_only=True)
RECIPROCAL = [c for c in ALL_BRDFS if LOBES[c[1]].hints.reciprocal]


@functools.lru_cache(maxsize=None)
def _compiled(lobe, opts_items):
    # Keyed by the Lobe itself, not its name: a test may register a throwaway lobe.
    opts = dict(opts_items)
    return jax.jit(lambda p, n, wi, wo: lobe.eval(p, opts, n, wi, wo)[..., 0])


def _eval(lobe, params, opts, wi, wo):
    """f(wi, wo) of the red channel about n = +z; wi (3,) or (N, 3), wo (N, 3)."""
    n = jnp.broadcast_to(jnp.asarray(NORMAL), jnp.shape(wo))
    wi = jnp.broadcast_to(jnp.asarray(wi), jnp.shape(wo))
    fn = _compiled(LOBES[lobe], tuple(sorted(opts.items())))
    return np.asarray(fn(_p(params), n, wi, jnp.asarray(wo)))


def _wi(theta):
    return np.array([np.sin(theta), 0.0, np.cos(theta)])


def reflectance(lobe, params, opts, theta_i, n_theta, f_scale=None):
    """rho(wi, 2pi) = int f(wi, wo) cos(theta_o) dwo, by quadrature.

    The nodes follow the lobe's peak, as its ``hints.quadrature`` says: over
    wo about n (diffuse), over wo about the mirror direction (Phong), or over
    the half vector h with dwo = 4 (wo.h) dwh (microfacet), each within a cap
    holding the lobe's mass. ``f_scale`` optionally divides f (white furnace).
    """
    wi = _wi(theta_i)
    q = LOBES[lobe].hints.quadrature(params)
    n_theta *= q.refine
    if q.axis == "mirror":
        r = 2.0 * wi[2] * NORMAL - wi
        wo, w = spherical_quadrature(r, n_theta, 2 * n_theta, q.cap)
        jac = np.ones(len(w))
    elif q.axis == "half":
        h, w = spherical_quadrature(NORMAL, n_theta, 2 * n_theta, q.cap)
        ih = h @ wi
        wo = 2.0 * ih[:, None] * h - wi
        jac = np.where(ih > 0, 4.0 * ih, 0.0)
    else:
        wo, w = spherical_quadrature(NORMAL, n_theta, 2 * n_theta, q.cap)
        jac = np.ones(len(w))
    f = _eval(lobe, params, opts, wi, wo)
    if f_scale is not None:
        f = f / f_scale(wi, wo)
    co = wo @ NORMAL
    return float(np.sum(np.where(co > 0, w * jac * f * co, 0.0)))


def reflectance_checked(*args, **kw):
    """(reflectance, quadrature-error estimate |Q_N - Q_2N|)."""
    q1 = reflectance(*args, N_THETA, **kw)
    q2 = reflectance(*args, 2 * N_THETA, **kw)
    return q2, abs(q2 - q1)


def _random_pairs(rng, n, upper=True):
    def dirs():
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        if upper:
            v[:, 2] = np.abs(v[:, 2])
        return v
    return dirs(), dirs()


@pytest.mark.parametrize("case", ALL_BRDFS, ids=[c[0] for c in ALL_BRDFS])
def test_positive_and_finite(case):
    _, lobe, params, opts = case
    rng = np.random.default_rng(1)
    wi, wo = _random_pairs(rng, 4000, upper=True)
    f = _eval(lobe, params, opts, wi, wo)
    assert np.all(np.isfinite(f)) and np.all(f >= 0.0)
    wi, wo = _random_pairs(rng, 4000, upper=False)  # below the horizon: finite (masked later)
    assert np.all(np.isfinite(_eval(lobe, params, opts, wi, wo)))


@pytest.mark.parametrize("case", RECIPROCAL, ids=[c[0] for c in RECIPROCAL])
def test_helmholtz_reciprocity(case):
    _, lobe, params, opts = case
    wi, wo = _random_pairs(np.random.default_rng(2), 4000)
    np.testing.assert_allclose(_eval(lobe, params, opts, wi, wo),
                               _eval(lobe, params, opts, wo, wi), rtol=REL_TOL, atol=ABS_FLOOR)


@pytest.mark.parametrize("case", CONSERVING, ids=[c[0] for c in CONSERVING])
def test_energy_conservation(case):
    """int f cos dwo <= 1 for rho = 1 at several incident angles (lecture's bound)."""
    _, lobe, params, opts = case
    for theta_i in THETA_I:
        rho, err = reflectance_checked(lobe, params, opts, theta_i)
        assert err < QUAD_TOL, (theta_i, err)
        assert 0.0 < rho <= 1.0 + QUAD_TOL, (theta_i, rho)


def test_lambert_reflectance_is_rho():
    """rho_d/pi * int cos dw = rho_d/pi * pi = rho_d (lecture: int cos dw = pi)."""
    for theta_i in THETA_I:
        rho, err = reflectance_checked("lambert", {"rho_d": np.full(3, 0.7)}, {}, theta_i)
        assert err < QUAD_TOL and abs(rho - 0.7) < QUAD_TOL


@pytest.mark.parametrize("e", [1.0, 2.0, 10.0, 100.0, 1e4])
def test_phong_normalisation_at_normal_incidence(e):
    """At wi = n, r = n and int cos^e cos dw = 2pi/(e+2) (lecture, n = e+1).

    Lecture's form: reflectance rho_s 2pi/(e+2); normalised: exactly rho_s.
    """
    rho_s = 0.8
    closed = 2.0 * np.pi / (e + 2.0)
    for normalized, expected in ((False, rho_s * closed), (True, rho_s)):
        rho, err = reflectance_checked("phong", {"rho_s": np.full(3, rho_s), "e": e},
                                       {"normalized": normalized}, 0.0)
        assert err < QUAD_TOL
        assert abs(rho - expected) < QUAD_TOL * max(1.0, expected), (normalized, rho, expected)


def test_lecture_phong_violates_energy_conservation():
    """Documents the lecture's un-normalised Phong: rho_s = 1, e = 1 reflects
    2pi/3 = 2.09 times the incident energy at normal incidence (> 1)."""
    rho, err = reflectance_checked("phong", {"rho_s": np.ones(3), "e": 1.0},
                                   {"normalized": False}, 0.0)
    assert err < QUAD_TOL
    assert abs(rho - 2.0 * np.pi / 3.0) < QUAD_TOL
    assert rho > 1.0


# --- Torrance-Sparrow against an independent transcription -----------------

def beckmann_dn(cos_h, m):
    """Normalised Beckmann D_n = exp(-tan^2/m^2) / (pi m^2 cos^4) (Mitsuba/pbrt form)."""
    tan2 = (1.0 - cos_h**2) / cos_h**2
    return np.exp(-tan2 / m**2) / (np.pi * m**2 * cos_h**4)


def smith_g1(cos_w, m):
    """Walter et al. (2007) eq. 27, as in Mitsuba's Beckmann."""
    a = cos_w / (m * np.sqrt(1.0 - cos_w**2))
    return np.where(a >= 1.6, 1.0, (3.535 * a + 2.181 * a**2) / (1 + 2.276 * a + 2.577 * a**2))


def test_cosines_cotangents():
    """Cosines.cot_i, cot_o = cot(theta) of wi's and wo's angles to n, reference
    1 / tan(arccos(cos)) (trigonometry, not the cos / sin the code takes), in
    both code paths (NumPy for the tabulated geometry, JAX); COT_NORMAL along n,
    where Smith's G1 is 1."""
    from fitter.bsdf.base import COT_NORMAL, cosines
    from fitter.bsdf.microfacet import smith_g1_beckmann

    wi, wo = _random_pairs(np.random.default_rng(5), 500, upper=False)
    wi[0] = wo[1] = NORMAL
    n = np.broadcast_to(NORMAL, wi.shape)
    with np.errstate(divide="ignore"):
        want_i, want_o = (1.0 / np.tan(np.arccos(w[:, 2])) for w in (wi, wo))
    for c in (cosines(n, wi, wo), cosines(jnp.asarray(n), jnp.asarray(wi), jnp.asarray(wo))):
        for got, want in ((c.cot_i, want_i), (c.cot_o, want_o)):
            got = np.asarray(got)
            along = ~np.isfinite(want)
            assert along.sum() == 1 and np.all(got[along] == COT_NORMAL)
            np.testing.assert_allclose(got[~along], want[~along], rtol=1e-10, atol=1e-12)
    assert float(smith_g1_beckmann(COT_NORMAL, 1e-4)) == 1.0
    # Without tabulated cotangents (the sun's cells) the lobe takes them from the
    # cosines: the same shape and derivatives.
    lobe = LOBES["torrance_sparrow"]
    p = {"m": jnp.float64(0.2), "eta": jnp.float64(1.5), "rho_s": jnp.float64(1.0)}
    c = cosines(jnp.asarray(n), jnp.asarray(wi), jnp.asarray(wo))
    bare = c._replace(cot_i=None, cot_o=None)
    opts = {"geometry": "smith"}
    np.testing.assert_allclose(lobe.shape(p, opts, bare), lobe.shape(p, opts, c), rtol=1e-13,
                               atol=1e-15)
    (g0, d0), (g1, d1) = lobe.shape_grad(p, opts, bare), lobe.shape_grad(p, opts, c)
    np.testing.assert_allclose(g0, g1, rtol=1e-13, atol=1e-15)
    for k in d1:
        np.testing.assert_allclose(d0[k], d1[k], rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("geometry", ["v_groove", "smith"])
@pytest.mark.parametrize("m,eta", [(0.05, 1.5), (0.3, 1.0), (0.7, 2.5), (1.0, 4.0)])
def test_torrance_sparrow_matches_closed_form(geometry, m, eta):
    """f = rho_s D_n G F(wo.h) / (4 cos_i cos_o): lecture's D G F/(pi ci co) with
    the lecture's D = (pi/4) D_n."""
    wi, wo = _random_pairs(np.random.default_rng(3), 3000)
    ci, co = wi[:, 2], wo[:, 2]
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    ch, oh = h[:, 2], np.sum(wo * h, axis=1)
    if geometry == "v_groove":
        g = np.minimum(1.0, np.minimum(2 * ch * co / oh, 2 * ch * ci / oh))
    else:
        g = smith_g1(ci, m) * smith_g1(co, m)
    rho_s = 0.9
    expected = rho_s * beckmann_dn(ch, m) * g * fresnel_reference(oh, eta) / (4.0 * ci * co)
    got = _eval("torrance_sparrow", {"m": m, "eta": eta, "rho_s": rho_s},
                {"geometry": geometry}, wi, wo)
    np.testing.assert_allclose(got, expected, rtol=REL_TOL, atol=ABS_FLOOR)


@pytest.mark.parametrize("m", [0.05, 0.2, 0.5])
def test_beckmann_is_normalised(m):
    """int D_n(h) cos(theta_h) dwh = 1 (projected microfacet area = macro area).

    The model's lecture-form D is (pi/4) D_n; both checked by quadrature.
    """
    def integral(n_theta):
        h, w = spherical_quadrature(NORMAL, n_theta, 8)  # D is isotropic
        cos_h = h[:, 2]
        tan2_h = (h[:, 0] ** 2 + h[:, 1] ** 2) / cos_h**2
        d = np.asarray(beckmann_d_lecture(jnp.asarray(cos_h), jnp.asarray(tan2_h), m))
        np.testing.assert_allclose(d, np.pi / 4 * beckmann_dn(h[:, 2], m), rtol=REL_TOL,
                                   atol=ABS_FLOOR)
        return np.sum(w * d * h[:, 2]) * 4.0 / np.pi
    q1, q2 = integral(N_THETA), integral(2 * N_THETA)
    assert abs(q2 - q1) < QUAD_TOL and abs(q2 - 1.0) < QUAD_TOL


@pytest.mark.parametrize("geometry", ["v_groove", "smith"])
@pytest.mark.parametrize("m", [0.01, 0.1, 0.4, 1.0])
def test_torrance_sparrow_white_furnace(geometry, m):
    """With F replaced by 1 (a perfect reflector), int D_n G /(4 ci co) cos_o dwo <= 1:
    shadowing-masking may lose energy but never create it. Near 1 for small m
    away from grazing, where G ~ 1 and D_n is normalised."""
    def f_fresnel(wi, wo):
        h = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
        return fresnel_reference(np.clip(h @ wi, 0.0, 1.0), 4.0)

    params = {"m": m, "eta": 4.0, "rho_s": 1.0}
    for theta_i in THETA_I:
        rho, err = reflectance_checked("torrance_sparrow", params, {"geometry": geometry},
                                       theta_i, f_scale=f_fresnel)
        assert err < QUAD_TOL and rho <= 1.0 + QUAD_TOL, (theta_i, rho, err)
        if m <= 0.1 and theta_i <= 1.0:
            assert rho > 0.99, (theta_i, rho)


def test_linearity_of_lobes():
    """Render of lambert+phong = render of lambert + render of phong (same scene)."""
    scene = fitter.Scene(width=16, height=16, supersampling=2, lights=(
        fitter.PointLight((3.0, 4.0, 5.0), (40.0, 30.0, 20.0)),
        fitter.DirectionalLight((0.5, -0.2, -1.0), (1.0, 2.0, 3.0))))
    lam = {"lambert.rho_d": [0.6, 0.4, 0.2]}
    pho = {"phong.rho_s": [0.3, 0.5, 0.7], "phong.e": 30.0}
    both = np.asarray(fitter.render({**lam, **pho}, scene))
    parts = np.asarray(fitter.render(lam, scene)) + np.asarray(fitter.render(pho, scene))
    assert both.max() > 0.1
    # Same terms, summed in another order: float64 rounding only.
    np.testing.assert_allclose(both, parts, rtol=1e-13, atol=1e-15)


def test_every_brdf_lobe_has_property_points():
    """A lobe without ``hints.points`` would skip the tests above silently."""
    for name, lobe in LOBES.items():
        if lobe.kind == "brdf":
            assert any(pt.conserving for pt in lobe.hints.points), name


# --- the READMEs' lobe tables are the lobes' own docs -------------------------

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _table(path, header):
    """The body rows of the markdown table whose header line is ``header``."""
    lines = (ROOT / path).read_text(encoding="utf-8").splitlines()
    i = lines.index(header) + 2  # header, separator
    rows = []
    while i < len(lines) and lines[i].startswith("|"):
        rows.append(lines[i])
        i += 1
    return rows


@pytest.mark.parametrize("path,header,rows", [
    ("README.md", "| lobe | parameters (valid box) | model |", tables.lobe_rows),
    ("configs/README.md", "| key | size | default | valid box | meaning |", tables.param_rows),
    ("configs/README.md", "| key | values | default | meaning |", tables.option_rows),
])
def test_readme_tables_match_lobe_docs(path, header, rows):
    """Rows written from ``Lobe.doc``/``Param``/``Option`` (print them with
    ``python -m fitter.bsdf.tables``)."""
    assert _table(path, header) == rows(LOBES.values())


def test_configs_readme_lists_every_lobe():
    text = (ROOT / "configs/README.md").read_text(encoding="utf-8")
    row = next(r for r in text.splitlines() if r.startswith("| `lobes` |"))
    assert re.findall(r"`(\w+)`", row.split("|")[4]) == list(LOBES)

"""The Python Mitsuba BSDFs, direction by direction.

Reference: each lobe's JAX ``eval`` (the lecture's formula, itself checked
against closed forms in ``test_closed_forms.py``), and Mitsuba's own
``diffuse``/``roughconductor``/``conductor`` for the plugin-free lobes. Mitsuba
runs in float32, so values agree to FLOAT32_REL relative (plus FLOAT32_ABS
of the largest value, for cancellations such as 2 ci co - wi.wo).
"""

from __future__ import annotations

import numpy as np
import pytest

import fitter
from fitter.mitsuba import _variant, plugins
from fitter.mitsuba.translate import bsdf_dict

pytestmark = pytest.mark.mitsuba

N = 4000
FLOAT32_REL = 2e-4
FLOAT32_ABS = 1e-5
SAMPLE_REL = 1e-4  # weight * pdf vs eval for the same sampled direction

MATERIALS = {
    "lambert": ("lambert", {}, {"lambert.rho_d": [0.6, 0.4, 0.2]}),
    "oren_nayar": ("oren_nayar", {}, {"oren_nayar.rho_d": [0.6, 0.5, 0.4], "oren_nayar.sigma": 0.7}),
    "phong": ("phong", {}, {"phong.rho_s": [0.5, 0.4, 0.3], "phong.e": 40.0}),
    "phong_normalized": ("phong", {"phong.normalized": True},
                         {"phong.rho_s": [0.5, 0.4, 0.3], "phong.e": 40.0}),
    "ts_smith": ("torrance_sparrow", {"torrance_sparrow.geometry": "smith"},
                 {"torrance_sparrow.m": 0.3, "torrance_sparrow.eta": 1.7}),
    "ts_v_groove": ("torrance_sparrow", {}, {"torrance_sparrow.m": 0.3,
                                             "torrance_sparrow.eta": 1.7}),
    "sum": ("lambert+oren_nayar+phong", {}, {"phong.e": 10.0}),
}


@pytest.fixture(scope="module")
def mi():
    mi, _ = _variant.load(None)
    plugins.register(mi)
    return mi


def _directions(rng, n):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2]) * np.where(rng.uniform(size=n) < 0.1, -1, 1)  # some below
    return v


def _mitsuba_eval(mi, bsdf, wo_view, wi_light):
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, len(wo_view))
    si.wi = mi.Vector3f(*wo_view.T.astype(np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    val = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wi_light.T.astype(np.float32)))
    return np.array(val, dtype=np.float64).reshape(-1, 3) if np.array(val).shape[-1] == 3 \
        else np.array(val, dtype=np.float64).T


@pytest.mark.parametrize("name", list(MATERIALS))
def test_plugin_eval_matches_model(name, mi):
    lobes, options, params = MATERIALS[name]
    material = fitter.Material.make(lobes, options)
    bsdf = mi.load_dict(bsdf_dict(material, params))
    rng = np.random.default_rng(7)
    view, light = _directions(rng, N), _directions(rng, N)
    got = _mitsuba_eval(mi, bsdf, view, light)

    full = material.full_params(params)
    n = np.broadcast_to([0.0, 0.0, 1.0], view.shape)
    f = 0.0
    for lobe in material.lobe_objects:
        p = {k.split(".", 1)[1]: v for k, v in full.items() if k.startswith(lobe.name + ".")}
        f = f + np.asarray(lobe.eval(p, material.options_of(lobe.name), n, light, view))
    lit = (light[:, 2] > 0) & (view[:, 2] > 0)
    want = np.where(lit[:, None], f * light[:, 2:3], 0.0)
    tol = FLOAT32_REL * np.abs(want) + FLOAT32_ABS * np.abs(want).max()
    bad = np.abs(got - want) > tol
    assert not bad.any(), (f"{name}: {bad.any(axis=1).sum()} of {N} direction pairs differ, "
                           f"worst {np.abs(got - want).max():.3g}")


@pytest.mark.parametrize("name", ["oren_nayar", "phong", "ts_v_groove", "sum"])
def test_plugin_sample_weight_is_eval_over_pdf(name, mi):
    import drjit as dr

    lobes, options, params = MATERIALS[name]
    bsdf = mi.load_dict(bsdf_dict(fitter.Material.make(lobes, options), params))
    rng = np.random.default_rng(3)
    view = _directions(rng, N)
    view[:, 2] = np.abs(view[:, 2]) + 1e-3
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, N)
    si.wi = mi.Vector3f(*view.T.astype(np.float32))
    ctx = mi.BSDFContext()
    s1 = mi.Float(rng.uniform(size=N).astype(np.float32))
    s2 = mi.Point2f(*rng.uniform(size=(2, N)).astype(np.float32))
    bs, weight = bsdf.sample(ctx, si, s1, s2)
    value, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
    w = np.array(weight, dtype=np.float64).reshape(N, 3) if np.array(weight).shape == (N, 3) \
        else np.array(weight, dtype=np.float64).T
    v = np.array(value, dtype=np.float64).reshape(w.shape) if np.array(value).shape == w.shape \
        else np.array(value, dtype=np.float64).T
    p = np.array(pdf, dtype=np.float64)
    np.testing.assert_allclose(np.array(bs.pdf, dtype=np.float64), p, rtol=SAMPLE_REL, atol=1e-12)
    ok = p > 0
    np.testing.assert_allclose(w[ok] * p[ok, None], v[ok], rtol=SAMPLE_REL,
                               atol=SAMPLE_REL * np.abs(v).max())

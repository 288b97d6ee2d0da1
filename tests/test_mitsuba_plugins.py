"""The Python Mitsuba BSDFs, direction by direction.

Reference: each lobe's JAX ``eval`` (the lecture's formula, itself checked
against closed forms in ``test_closed_forms.py``), and Mitsuba's own
``diffuse``/``roughconductor``/``conductor`` for the plugin-free lobes. Every
BRDF lobe of the registry is checked at its ``hints.example`` under each of
its option settings. Mitsuba
runs in float32, so values agree to FLOAT32_REL relative (plus FLOAT32_ABS
of the largest value, for cancellations such as 2 ci co - wi.wo).
"""

from __future__ import annotations

import numpy as np
import pytest

import fitter
from fitter.material import lobe_params
from fitter.mitsuba import plugins, variant
from fitter.mitsuba.translate import bsdf_dict

pytestmark = pytest.mark.mitsuba

N = 4000
FLOAT32_REL = 2e-4
FLOAT32_ABS = 1e-5
SAMPLE_REL = 1e-4  # weight * pdf vs eval for the same sampled direction

def _option_settings(lobe):
    """Every combination of the lobe's discrete options (free-form ones at default)."""
    settings = [{}]
    for o in lobe.options:
        if o.choices is not None:
            settings = [{**s, f"{lobe.name}.{o.name}": c} for s in settings for c in o.choices]
    return settings


def materials(lobes=None):
    """(lobes, options, params) per case: each BRDF lobe at its ``hints.example``
    under every option setting, read from the registry when called."""
    lobes = fitter.LOBES if lobes is None else lobes
    out = {}
    for name, lobe in lobes.items():
        if lobe.kind != "brdf" or lobe.mitsuba is None:
            continue
        params = {f"{name}.{k}": v for k, v in lobe.hints.example.items()}
        for opts in _option_settings(lobe):
            case = "-".join([name] + [f"{k.split('.')[1]}={v}" for k, v in opts.items()])
            out[case] = (name, opts, params)
    return out


MATERIALS = {
    **materials(),
    "sum": ("lambert+oren_nayar+phong", {}, {"phong.e": 10.0}),
}


def _uses_plugin(case):
    """The case's BSDF is (or sums) a Python plugin: its sampler is ours to test."""
    lobes, options, params = case
    material = fitter.Material.make(lobes, options)
    return len(material.lobes) > 1 or bsdf_dict(material, params)["type"] in \
        material.lobe_objects[0].mitsuba.plugins


PLUGIN_CASES = [name for name, case in MATERIALS.items() if _uses_plugin(case)]


@pytest.fixture(scope="module")
def mi():
    mi, _ = variant.load(None)
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
    check_eval(name, MATERIALS[name], mi)


def check_eval(name, case, mi):
    """Mitsuba's eval of the case's BSDF dict = the lobes' summed JAX eval * cos."""
    lobes, options, params = case
    material = fitter.Material.make(lobes, options)
    bsdf = mi.load_dict(bsdf_dict(material, params))
    rng = np.random.default_rng(7)
    view, light = _directions(rng, N), _directions(rng, N)
    got = _mitsuba_eval(mi, bsdf, view, light)

    full = material.full_params(params)
    n = np.broadcast_to([0.0, 0.0, 1.0], view.shape)
    f = 0.0
    for lobe in material.lobe_objects:
        p = lobe_params(full, lobe.name)
        f = f + np.asarray(lobe.eval(p, material.options_of(lobe.name), n, light, view))
    lit = (light[:, 2] > 0) & (view[:, 2] > 0)
    want = np.where(lit[:, None], f * light[:, 2:3], 0.0)
    tol = FLOAT32_REL * np.abs(want) + FLOAT32_ABS * np.abs(want).max()
    bad = np.abs(got - want) > tol
    assert not bad.any(), (f"{name}: {bad.any(axis=1).sum()} of {N} direction pairs differ, "
                           f"worst {np.abs(got - want).max():.3g}")


@pytest.mark.parametrize("name", PLUGIN_CASES)
def test_plugin_sample_weight_is_eval_over_pdf(name, mi):
    check_sample(MATERIALS[name], mi)


def check_sample(case, mi):
    """The plugin's sample weight * pdf = eval for the sampled direction."""
    import drjit as dr

    lobes, options, params = case
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

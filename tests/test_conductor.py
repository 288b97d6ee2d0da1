"""Conductor Fresnel for torrance_sparrow (issue 13, item 1).

* ``fresnel_conductor`` against complex arithmetic (the Fresnel equations with
  a complex index, written independently with NumPy complex numbers), its
  limits (k = 0 is the dielectric; F0 closed form) and its hand derivatives.
* The lobe's conductor variant: RGB ``eta``/``k`` parameters, the renderer's
  RGB shape against Mitsuba's ``roughconductor`` and the plugin.
* Recovery: the shipped Mitsuba gold sphere under two point lights
  (``configs/metal_gold.toml``) gives F0 within 0.01 per channel and m within
  2 %, and the result says eta/k are not separately determined.

References: Born, Wolf, *Principles of Optics*, sec. 14.2 (metals: the Fresnel
formulas with a complex index); pbrt-v4 ``FrComplex``.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitter
from fitter import pipeline
from fitter.config import load_config
from fitter.bsdf.fresnel import (conductor_f0, fresnel_conductor, fresnel_conductor_grad,
                                 fresnel_dielectric)
from fitter.material import Material, MaterialError

#: Mitsuba 3.9's ``roughconductor`` with ``material = "Au"`` in the rgb variants.
AU = {"torrance_sparrow.eta": [0.143, 0.3753, 1.442], "torrance_sparrow.k": [3.983, 2.3856, 1.6034]}
CONDUCTOR = {"torrance_sparrow.fresnel": "conductor"}
LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
          fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0)))


def _complex_reference(c, eta, k):
    n = eta + 1j * k
    ct = np.sqrt(1.0 - (1.0 - c * c) / n**2 + 0j)
    rs = (c - n * ct) / (c + n * ct)
    rp = (n * c - ct) / (n * c + ct)
    return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


def test_conductor_fresnel_matches_complex_arithmetic():
    rng = np.random.default_rng(1)
    c = rng.uniform(0.0, 1.0, 2000)
    eta = np.exp(rng.uniform(np.log(1e-2), np.log(10.0), 2000))
    k = np.exp(rng.uniform(np.log(1e-3), np.log(20.0), 2000))
    np.testing.assert_allclose(fresnel_conductor(c, eta, k), _complex_reference(c, eta, k),
                               rtol=0, atol=1e-13)
    np.testing.assert_allclose(fresnel_conductor(1.0, eta, k), conductor_f0(eta, k), atol=1e-14)
    np.testing.assert_allclose(fresnel_conductor(0.0, eta, k), 1.0, atol=1e-14)
    # k = 0, eta >= 1: the dielectric interface.
    np.testing.assert_allclose(fresnel_conductor(c, 1.5, 0.0), fresnel_dielectric(c, 1.5),
                               atol=1e-14)


def test_conductor_fresnel_derivatives_match_autodiff():
    rng = np.random.default_rng(2)
    c = jnp.asarray(rng.uniform(0.0, 1.0, 500))
    eta = jnp.asarray(np.exp(rng.uniform(np.log(1e-2), np.log(10.0), 500)))
    k = jnp.asarray(np.exp(rng.uniform(np.log(1e-3), np.log(20.0), 500)))
    _, de, dk = fresnel_conductor_grad(c, eta, k)
    ref = jax.vmap(jax.grad(lambda a, b, d: jnp.asarray(_jax_reference(a, b, d)),
                            argnums=(1, 2)))(c, eta, k)
    np.testing.assert_allclose(de, ref[0], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(dk, ref[1], rtol=1e-8, atol=1e-12)


def _jax_reference(c, eta, k):
    """The same F in JAX complex arithmetic (an independent autodiff reference)."""
    n = jax.lax.complex(eta, k)
    c = jax.lax.complex(c, jnp.zeros_like(c))
    one = jnp.ones_like(c)
    ct = jnp.sqrt(one - (one - c * c) / (n * n))
    rs = (c - n * ct) / (c + n * ct)
    rp = (n * c - ct) / (n * c + ct)
    return 0.5 * (jnp.abs(rs) ** 2 + jnp.abs(rp) ** 2)


def test_conductor_parameters_are_rgb_and_named_by_the_option():
    plain = Material.make(["torrance_sparrow"])
    metal = Material.make(["torrance_sparrow"], CONDUCTOR)
    assert plain.param_specs()["torrance_sparrow.eta"].size == 1
    assert "torrance_sparrow.k" not in plain.param_specs()
    specs = metal.param_specs()
    assert specs["torrance_sparrow.eta"].size == 3 and specs["torrance_sparrow.k"].size == 3
    full = metal.full_params(AU)
    assert full["torrance_sparrow.eta"].shape == (3,)
    with pytest.raises(MaterialError, match="torrance_sparrow.k"):
        plain.full_params({"torrance_sparrow.k": 1.0})


@pytest.mark.mitsuba
@pytest.mark.parametrize("geometry", ["smith", "v_groove"])
def test_conductor_render_matches_mitsuba(geometry):
    """roughconductor (smith) and the plugin (v_groove) against the JAX model."""
    import fitter.mitsuba as fm

    scene = fitter.Scene(width=32, height=32, supersampling=4, lights=LIGHTS)
    mat = Material.make(["torrance_sparrow"], {**CONDUCTOR, "torrance_sparrow.geometry": geometry})
    p = {**AU, "torrance_sparrow.m": 0.3}
    model = np.asarray(fitter.render(p, scene, mat))
    ref = np.asarray(fm.render(scene, mat, p, spp=64, seed=3))
    inner = np.zeros((32, 32), bool)
    inner[8:24, 8:24] = True
    rel = model[inner].mean(axis=0) / ref[inner].mean(axis=0) - 1.0
    assert np.all(np.abs(rel) < 2e-3), rel


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def gold_outcome():
    """The shipped case ``metal_gold``: Mitsuba's gold roughconductor, 64^2, 1024 spp."""
    job = load_config(os.path.join(ROOT, "configs", "metal_gold.toml"))
    job = job.replace(fit=job.fit.replace(validate=False))
    target, saturated = pipeline.read_target(job.fit.target, job.scene)
    return job, pipeline.run_job(job, target, saturated)


@pytest.mark.mitsuba
def test_gold_sphere_recovers_f0_and_roughness(gold_outcome):
    job, out = gold_outcome
    res, truth = out.fit, job.truth
    assert res.converged, res.message
    eta, k = (np.asarray(res.params[f"torrance_sparrow.{n}"]) for n in ("eta", "k"))
    assert eta.shape == (3,) and k.shape == (3,)
    f0_true = conductor_f0(np.asarray(truth["torrance_sparrow.eta"]),
                           np.asarray(truth["torrance_sparrow.k"]))
    np.testing.assert_allclose(conductor_f0(eta, k), f0_true, atol=0.01)
    assert res.params["torrance_sparrow.m"] == pytest.approx(truth["torrance_sparrow.m"],
                                                             rel=0.02)
    d = out.to_dict()
    assert isinstance(d["params"]["torrance_sparrow.eta"], list)
    assert isinstance(d["params"]["torrance_sparrow.m"], float)
    f0 = d["derived"]["torrance_sparrow.F0"]
    np.testing.assert_allclose(f0["value"], f0_true, atol=0.01)
    assert f0["stderr"] is not None and max(f0["stderr"]) < 0.01
    # eta and k trade along the curve of equal F0: the result says so, and lists
    # them unidentifiable (measured 8 and 5 stated errors off when listed
    # identifiable); F0 keeps its error. The fit engine reports it (fitter.fit
    # from Python too); the pipeline's JSON is the fit's.
    assert any("curve of equal F0" in w for w in d["warnings"]), d["warnings"]
    assert {"torrance_sparrow.eta", "torrance_sparrow.k"} <= set(res.unidentifiable)
    assert "torrance_sparrow.eta" not in res.stderr and "torrance_sparrow.m" in res.stderr
    np.testing.assert_allclose(res.derived["torrance_sparrow.F0"]["value"], f0_true, atol=0.01)

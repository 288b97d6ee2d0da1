"""Adding a lobe is one module + one registry entry: a throwaway lobe proves it.

``MATTE`` below is everything a new lobe writes -- formula, parameter and
docs, Mitsuba plugin, test hints -- and ``fitter.bsdf.registered`` stands in
for its registry entry, for this module only. With no other code touched it
must render, fit, pass the BSDF property tests, load as a config, translate to
Mitsuba and render there like the JAX model.

The lobe: a scaled Lambert, f = k / pi with a grey albedo k (Teschner,
*Materials 1*, "BRDF for diffuse reflecting material").
"""

from __future__ import annotations

import math
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

import fitter
from fitter.bsdf import Hints, Lobe, MitsubaMapping, Param, Point, registered
from fitter.bsdf.mitsuba_map import cosine_sampled
import test_bsdf_properties as props

#: Relative error allowed on the recovered k (as ``test_fit_recovery``).
RECOVERY_RTOL = 1e-6
#: Interior mean, Mitsuba vs the model: the crosscheck's bound on mean relative
#: differences (the estimate here is far closer: point lights, pixel jitter only).
MEAN_REL_TOL = 0.01
SPP = 16


def _shape(p, opts, c):
    return jnp.full_like(c.cos_i, 1.0 / jnp.pi)


def _plugin(mi):
    base = cosine_sampled(mi)

    class Matte(base):
        """k / pi, as ``_shape`` * k."""

        def __init__(self, props):
            base.__init__(self, props)
            self.k = mi.Float(float(props.get("k", 0.5)))

        def _value(self, wi, wo):
            return mi.Color3f(self.k / math.pi)

    return Matte


MATTE = Lobe(
    name="test_matte",
    kind="brdf",
    params=(Param("k", 1, 0.5, 0.0, 1.0, "logit", "grey albedo"),),
    scale="k",
    shape=_shape,
    doc="k/π",
    mitsuba=MitsubaMapping(lambda p, opts: {"type": "test_matte", "k": float(p["k"])},
                           plugins={"test_matte": _plugin}),
    hints=Hints(points=(Point("test_matte", {"k": 1.0}),), example={"k": 0.7}),
)

SCENE = fitter.Scene(width=24, height=24, supersampling=4, lights=(
    fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
    fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0))))
TRUTH = {"test_matte.k": 0.7}


@pytest.fixture(scope="module", autouse=True)
def matte_registered():
    with registered(MATTE) as lobes:
        yield lobes
    assert MATTE.name not in fitter.LOBES


def test_registry_is_restored_and_names_are_not_reused():
    with pytest.raises(ValueError, match="already registered"):
        with registered(MATTE):
            pass
    assert fitter.LOBES[MATTE.name] is MATTE


def test_renders_as_scaled_lambert():
    img = np.asarray(fitter.render(TRUTH, SCENE))
    lam = np.asarray(fitter.render({"lambert.rho_d": 0.7}, SCENE))
    assert img.max() > 0.1
    np.testing.assert_array_equal(img, lam)  # the same products: bit-identical


def test_fit_recovers_k():
    target = np.asarray(fitter.render(TRUTH, SCENE))
    result = fitter.fit(target, SCENE, MATTE.name, init={"test_matte.k": 0.3})
    assert result.status == "converged", result.message
    np.testing.assert_allclose(result.params["test_matte.k"], 0.7, rtol=RECOVERY_RTOL)


@pytest.mark.parametrize("check", [props.test_positive_and_finite,
                                   props.test_helmholtz_reciprocity,
                                   props.test_energy_conservation])
def test_bsdf_properties(check):
    cases = props.property_cases({MATTE.name: MATTE})
    assert cases
    for case in cases:
        check(case)


def test_config_accepts_it():
    from fitter.config import job_from_dict

    job = job_from_dict({"scene": {}, "material": {"lobes": [MATTE.name], "truth": TRUTH}})
    assert job.material.lobes == (MATTE.name,)


@pytest.mark.mitsuba
def test_mitsuba_plugin_and_render():
    """The plugin's eval matches the model's (``test_mitsuba_plugins``), and a
    Mitsuba render's interior mean matches the JAX render."""
    import test_mitsuba_plugins as plug

    import fitter.mitsuba as fm
    from fitter.mitsuba import plugins, variant

    mi, _ = variant.load(None)
    plugins.register(mi)
    case = (MATTE.name, {}, TRUTH)
    plug.check_eval(MATTE.name, case, mi)
    plug.check_sample(case, mi)

    material = fitter.Material.make(MATTE.name)
    d = fm.scene_dict(SCENE, material, TRUTH, spp=SPP, seed=0)
    assert d["sphere"]["bsdf"] == {"type": "test_matte", "k": 0.7}
    ours = np.asarray(fitter.render(TRUTH, SCENE, material))
    theirs = fm.render(SCENE, material, TRUTH, spp=SPP, seed=0)
    r = fitter.Renderer(SCENE, material)
    cover = np.zeros(SCENE.width * SCENE.height)
    cover[r.pixel_index] = np.asarray(r.geometry.hit).mean(axis=1)
    interior = cover.reshape(SCENE.height, SCENE.width) == 1.0
    rel = abs(theirs[interior].mean() / ours[interior].mean() - 1.0)
    assert rel < MEAN_REL_TOL, rel


def test_lobe_modules_do_not_import_mitsuba():
    """Mitsuba mappings live in the lobe modules, yet Mitsuba and drjit load only
    when ``fitter.mitsuba`` is used (style: ``import fitter`` stays fast)."""
    code = ("import sys, fitter, fitter.bsdf, fitter.bsdf.tables; "
            "print([m for m in sys.modules if m.split('.')[0] in ('mitsuba', 'drjit')])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"

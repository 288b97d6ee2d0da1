"""The exposure / light-scale parameter (issue 13, item 3).

``"exposure"`` multiplies the whole rendered radiance (lights, environment,
background). References: the forward model's own image times the scalar
(exposure is a linear scale, so ``render(exposure = x) = x render`` exactly),
Mitsuba renders of the same scene (emitters scaled, an independent renderer),
and the truth used to render a target. Tolerances are the issue's (rho 0.005,
m 2 %) and 1 % on the exposure.
"""

from __future__ import annotations

import copy
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from small_case import SMALL, write_case

import fitter
from fitter.cli import main
from fitter.config import ConfigError, job_from_dict, job_to_dict
from fitter.errors import FitterError
from fitter.fit._setup import Problem
from fitter.material import EXPOSURE_KEY, Material

EXPOSURE_REL, RHO_ABS, M_REL = 0.01, 0.005, 0.02
LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
          fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0)))
SCENE = fitter.Scene(width=32, height=32, supersampling=2, lights=LIGHTS)
PLASTIC = Material.make(["lambert", "torrance_sparrow"], {"torrance_sparrow.geometry": "smith"})
TRUTH = {"lambert.rho_d": [0.2, 0.3, 0.6], "torrance_sparrow.m": 0.2,
         "torrance_sparrow.eta": 1.5}


def test_exposure_multiplies_the_whole_image_background_included():
    """Sphere and background alike (a constant sky: the background is not 0)."""
    scene = SCENE.replace(environment=fitter.Environment(type="constant",
                                                         radiance=(0.3, 0.4, 0.5)))
    plain = np.asarray(fitter.render(TRUTH, scene, PLASTIC))
    exposed = np.asarray(fitter.render({**TRUTH, "exposure": 2.5}, scene, PLASTIC))
    assert np.all(plain[0, 0] > 0)  # a background pixel
    np.testing.assert_allclose(exposed, 2.5 * plain, rtol=1e-14, atol=0)
    # exposure 1 is today's image, bit for bit
    np.testing.assert_array_equal(np.asarray(fitter.render({**TRUTH, "exposure": 1.0}, scene,
                                                           PLASTIC)), plain)


def test_off_by_default_adds_no_parameter():
    """A material or fit that does not name the exposure has no such parameter."""
    assert EXPOSURE_KEY not in PLASTIC.param_specs()
    target = np.asarray(fitter.render(TRUTH, SCENE, PLASTIC))
    problem = Problem.make(target[None], SCENE, PLASTIC)
    assert not problem.material.exposure
    assert EXPOSURE_KEY not in problem.init_full
    assert EXPOSURE_KEY not in [b.key for b in problem.blocks]
    # named: fixed at 1 (like torrance_sparrow.rho_s) unless given in init
    fixed = Problem.make(target[None], SCENE, PLASTIC, fixed={"exposure": 2.0})
    assert EXPOSURE_KEY not in [b.key for b in fixed.blocks]
    assert float(fixed.init_full[EXPOSURE_KEY]) == 2.0
    free = Problem.make(target[None], SCENE, PLASTIC, init={"exposure": 1.0})
    assert [b.key for b in free.blocks][-1] == EXPOSURE_KEY


def test_gradients_in_the_exposure_are_finite_and_exact():
    def total(x, rho):
        return jnp.sum(fitter.render({**TRUTH, "lambert.rho_d": rho, "exposure": x}, SCENE,
                                     PLASTIC))

    x, rho = 1.7, jnp.array([0.2, 0.3, 0.6])
    gx, grho = jax.grad(total, argnums=(0, 1))(x, rho)
    assert np.isfinite(gx) and np.all(np.isfinite(np.asarray(grho)))
    # d/dx (x I) = I: the exposure's derivative is the unexposed image's sum
    np.testing.assert_allclose(float(gx), float(total(1.0, rho)), rtol=1e-12)
    assert np.all(np.asarray(grho) > 0)


@pytest.mark.parametrize("lobes,fixed,named", [
    (["lambert"], {}, "lambert.rho_d"),
    (["phong"], {}, "phong.rho_s"),
    (["oren_nayar", "phong"], {}, "oren_nayar.rho_d, phong.rho_s"),
    (["lambert", "torrance_sparrow"], {"torrance_sparrow.rho_s": 0.8},
     "lambert.rho_d, torrance_sparrow.rho_s"),
])
def test_an_exposure_every_lobe_scale_can_absorb_is_refused(lobes, fixed, named):
    init = {"exposure": 1.0}
    if "torrance_sparrow.rho_s" in fixed:  # freed: every lobe's scale is free
        init, fixed = {**init, **fixed}, {}
    with pytest.raises(FitterError) as exc:
        fitter.fit(np.zeros((32, 32, 3)), SCENE, lobes, init=init, fixed=fixed)
    msg = str(exc.value)
    assert msg.startswith("exposure is free, but so is every lobe's brightness scale "
                          f"({named})"), msg
    assert "fix exposure" in msg and "material.fixed" in msg


def test_a_fixed_scale_or_the_sky_behind_the_rim_is_a_reference():
    target = np.zeros((32, 32, 3))
    # a reflectance fixed at a known value is the reference
    Problem.make(target[None], SCENE, "lambert", init={"exposure": 1.0},
                 fixed={"lambert.rho_d": 0.5})
    sky = SCENE.replace(environment=fitter.Environment(type="constant", radiance=(0.5,) * 3))
    with pytest.raises(FitterError):
        Problem.make(target[None], sky, "lambert", init={"exposure": 1.0}, mask="interior")
    # the sky behind the rim pixels ("active" mask) is light of known scale: a
    # white patch of sorts, which pins the exposure (noise 0.01, known)
    truth = {"lambert.rho_d": [0.2, 0.3, 0.6], "exposure": 2.0}
    image = np.asarray(fitter.render(truth, sky))
    image = image + np.random.default_rng(0).normal(0.0, 0.01, image.shape)
    res = fitter.fit(image, sky, "lambert", init={"exposure": 1.0}, mask="active",
                     noise_sigma=0.01)
    assert res.converged, res.message
    err = abs(res.params["exposure"] - 2.0)
    assert err < EXPOSURE_REL * 2.0 and err < 3 * res.stderr["exposure"]


def test_config_reads_and_writes_the_exposure():
    data = copy.deepcopy(SMALL)
    data["material"]["init"]["exposure"] = 1.0
    job = job_from_dict(data)
    assert job.material.exposure and job.init["exposure"] == 1.0
    again = job_from_dict(job_to_dict(job))
    assert again.material == job.material and again.init == job.init
    data["material"]["init"]["exposure"] = 0.0
    with pytest.raises(ConfigError, match=r"material\.init\.exposure.*outside"):
        job_from_dict(data)
    data = copy.deepcopy(SMALL)
    data["scene"]["exposure"] = 2.0  # where a user may look for it first
    with pytest.raises(ConfigError, match=r"scene\.exposure: unknown key.*\[material\.fixed\] "
                                          r"exposure = x if known"):
        job_from_dict(data)


def _exposed_case():
    data = copy.deepcopy(SMALL)
    mat = data["material"]
    mat["truth"] = {**mat["truth"], "exposure": 2.0}
    mat["init"] = {"torrance_sparrow.m": 0.3, "lambert.rho_d": 0.5, "exposure": 1.0}
    mat["fixed"] = {**mat["fixed"], "torrance_sparrow.eta": 1.5}  # the known reference
    data["fit"] = {**data["fit"], "validate": True, "validate_spp": 64}
    return data


@pytest.mark.mitsuba
def test_cli_recovers_exposure_2_and_reports_it(tmp_path, capsys):
    """A forward-model target at exposure 2, eta fixed as the reference: the fit
    recovers the exposure (JSON, table, truth error) and the Mitsuba validation
    re-renders the exposed image (it would be half as bright otherwise)."""
    config = write_case(str(tmp_path / "case"), _exposed_case())
    code = main(["fit", config, "--out", str(tmp_path / "out"), "--json", "--quiet"])
    out, err = capsys.readouterr()
    assert code == 0, err
    res = json.loads(out)
    assert res["status"] == "converged", res["message"]
    assert abs(res["params"]["exposure"] / 2.0 - 1) < EXPOSURE_REL
    assert res["stderr"]["exposure"] > 0
    assert res["truth_error"]["exposure"]["truth"] == 2.0
    assert np.max(res["truth_error"]["lambert.rho_d"]["abs"]) < RHO_ABS
    assert res["truth_error"]["torrance_sparrow.m"]["rel"] < M_REL
    # the Mitsuba re-render is the exposed image: a 2x error would be ~ -6 dB of the mean
    assert res["validation"]["psnr_db"] > 30, res["validation"]
    xml = open(tmp_path / "out" / "scene.xml", encoding="utf-8").read()
    assert "exposure" in xml.split("<scene")[0]
    code = main(["fit", config, "--out", str(tmp_path / "out2"), "--no-validate", "--quiet"])
    table = capsys.readouterr().out
    assert code == 0 and "exposure" in table


def test_cli_refuses_a_degenerate_exposure_with_exit_2(tmp_path, capsys):
    data = copy.deepcopy(SMALL)
    data["material"] = {"lobes": ["lambert"], "init": {"exposure": 1.0}}
    config = write_case(str(tmp_path / "case"), data)
    out = tmp_path / "out"
    code = main(["fit", config, "--out", str(out), "--quiet"])
    _, err = capsys.readouterr()
    assert code == 2
    assert err.count("\n") == 1 and "exposure is free" in err and "lambert.rho_d" in err
    assert not out.exists()


@pytest.mark.mitsuba
def test_mitsuba_target_at_exposure_2_is_recovered():
    """Independent renderer: Mitsuba's exposed image is its image times 2 (emitters
    scaled), and the fit recovers exposure, rho_d and m from it with eta known."""
    from fitter import mitsuba

    scene = SCENE.replace(width=48, height=48, supersampling=4)
    mat = PLASTIC.with_exposure()
    img = np.asarray(mitsuba.render(scene, mat, {**TRUTH, "exposure": 2.0}, spp=1024, seed=0),
                     dtype=np.float64)
    one = np.asarray(mitsuba.render(scene, mat, {**TRUTH, "exposure": 1.0}, spp=1024, seed=0),
                     dtype=np.float64)
    np.testing.assert_allclose(img, 2.0 * one, rtol=1e-6, atol=1e-7)
    res = fitter.fit(img, scene, mat, init={"exposure": 1.0, "lambert.rho_d": 0.5,
                                            "torrance_sparrow.m": 0.3},
                     fixed={"torrance_sparrow.eta": 1.5})
    assert res.status == "converged", res.message
    assert abs(res.params["exposure"] / 2.0 - 1) < EXPOSURE_REL
    assert np.max(np.abs(res.params["lambert.rho_d"] - TRUTH["lambert.rho_d"])) < RHO_ABS
    assert abs(res.params["torrance_sparrow.m"] / 0.2 - 1) < M_REL


def test_a_weakly_identified_exposure_is_not_a_confident_wrong_value():
    """eta free too: the highlight's Fresnel level trades with the exposure
    (the user story's eta at its bound). With pixel noise the fit must either
    hold the exposure or state an error that covers the truth (3 sigma)."""
    target = np.asarray(fitter.render({**TRUTH, "exposure": 2.0}, SCENE, PLASTIC))
    noisy = target + np.random.default_rng(1).normal(0.0, 0.01, target.shape)
    res = fitter.fit(noisy, SCENE, PLASTIC, noise_sigma=0.01,
                     init={"exposure": 1.0, "lambert.rho_d": 0.5, "torrance_sparrow.m": 0.3})
    for key, truth in (("exposure", 2.0), ("torrance_sparrow.eta", 1.5)):
        if res.converged and key not in res.unidentifiable:
            err = abs(res.params[key] - truth)
            assert err <= 3 * res.stderr[key], (key, res.params[key], res.stderr[key])

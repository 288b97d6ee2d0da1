"""Recover the true parameters of the shipped Mitsuba targets (``data_synthetic/``).

The targets are independent renders (Mitsuba 3, box-filtered pixel areas,
1024-4096 spp); the fit uses the JAX model with the case's 4 x 4
supersampling, one start from the lobe defaults. Tolerances are the
project's recovery targets: rho within 0.005 absolute per channel, sigma
0.02, m 2 % relative, e 3 % relative, eta 0.005, attenuation 0.01. Extreme
cases state their own (model-side quadrature limits: a highlight about a
pixel wide is integrated by only 4 x 4 sub-pixel samples).
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import fitter
from fitter import config
from fitter.imageio import read_image
from fitter.cases import CASES

pytestmark = pytest.mark.mitsuba

ROOT = os.path.join(os.path.dirname(__file__), os.pardir, "data_synthetic")

RHO_ABS = 0.005
SIGMA_ABS = 0.02
M_REL = 0.02
E_REL = 0.03
ETA_ABS = 0.005
ATTENUATION_ABS = 0.01

#: (absolute, relative) tolerance per parameter name.
TOLERANCES = {"rho_d": (RHO_ABS, 0.0), "rho_s": (RHO_ABS, 0.0), "rho_m": (RHO_ABS, 0.0),
              "sigma": (SIGMA_ABS, 0.0), "m": (0.0, M_REL), "e": (0.0, E_REL),
              "eta": (ETA_ABS, 0.0), "attenuation": (ATTENUATION_ABS, 0.0),
              "k": (ETA_ABS, 0.0)}  # a conductor's k, the imaginary part of its index
#: Extreme cases: looser, stated tolerances (measured errors in the comments).
EXTREME = {
    # e = 2000: highlight ~2 pixels wide, 4 x 4 sub-pixel samples; measured rho_s
    # off by 0.004-0.006 and e by 0.3 %.
    "extreme_sharp_phong": {"phong.rho_s": (0.01, 0.0)},
    # eta = 1.02: the specular lobe is ~1e-4 of the diffuse; measured m off 2.1 %.
    "extreme_low_eta": {"torrance_sparrow.m": (0.0, 0.05)},
    # Issue 11 (environment light on opaque lobes): the env_* cases meet the project's
    # targets (env_plastic's eta measured -0.0048 since the sky stencil averages the
    # lobe over each cell: it was -0.0064 with one point per cell).
    # A conductor's eta and k trade along the curve of equal F0 (measured red eta
    # 0.037 vs 0.143, k 1.82 vs 3.98 at F0 within 3e-4): tests/test_conductor.py
    # checks F0 (0.01) and m (2 %) of this case.
    "metal_gold": {"torrance_sparrow.eta": (np.inf, 0.0), "torrance_sparrow.k": (np.inf, 0.0)},
}
#: The env cases (issue 11) are off by at most this many stated errors (measured
#: at most 2.2: env_phong's rho_s; without the sky stencil's ring error in the
#: stated errors env_plastic's eta was off by 3.6, env_oren_nayar's sigma by 4.2).
STATED_COVERS = 3.0
#: Cases whose best fit lies on a box edge the solver approaches without
#: reaching (sigma = 0, where Oren-Nayar's slope in sigma vanishes): the fit
#: runs out of steps and is refit with the value on the edge (``fit._edge``).
AT_BOX_EDGE = {"extreme_sigma0": ("oren_nayar.sigma", 0.0)}


def _load(name):
    folder = os.path.join(ROOT, name)
    case = json.load(open(os.path.join(folder, "case.json")))
    job = config.job_from_dict({"scene": case["scene"], "material": case["material"]},
                               base_dir=folder)
    return job, case["truth"], read_image(os.path.join(folder, "target.exr")), folder


@pytest.mark.parametrize("name", list(CASES))
def test_recovers_truth(name):
    job, truth, target, folder = _load(name)
    res = fitter.fit(target, job.scene, job.material, base_dir=folder)
    assert res.status == "converged", f"{name}: {res.status}: {res.message}"
    if name in AT_BOX_EDGE:
        key, edge = AT_BOX_EDGE[name]
        assert res.params[key] == edge and key in res.free and key in res.stderr
        assert any(w.startswith(f"{key} is on the edge of its box") for w in res.warnings)
    for key in res.free:
        abs_tol, rel_tol = EXTREME.get(name, {}).get(key, TOLERANCES[key.split(".", 1)[1]])
        want = np.asarray(truth[key])
        got = np.asarray(res.params[key])
        bound = abs_tol + rel_tol * np.abs(want)
        assert np.all(np.abs(got - want) <= bound), (
            f"{name}: {key} = {got.tolist()} vs truth {want.tolist()} (tolerance {bound})")
        if name.startswith("env_"):  # their stated errors cover what they are off by
            se = np.asarray(res.stderr[key])
            assert np.all(np.abs(got - want) <= STATED_COVERS * se), (
                f"{name}: {key} = {got.tolist()} vs truth {want.tolist()}: off by more than "
                f"{STATED_COVERS:g} x its stated error {se.tolist()}")


#: A probe this wide for ``test_a_wide_probe_is_recovered``: its ~3 deg sun is ~17
#: texels across (~250 over the sun threshold), where the shipped probe's is one.
WIDE_PROBE = 2048


@pytest.fixture(scope="module")
def wide_probe(tmp_path_factory):
    """The shipped probe's scene made WIDE_PROBE wide (a point a texel: 8 x 8 took 3 GB)."""
    from fitter.mitsuba.synth import make_probe

    path = str(tmp_path_factory.mktemp("wide") / "probe.exr")
    make_probe(path, WIDE_PROBE, WIDE_PROBE // 2, sub=1)
    return path


@pytest.mark.parametrize("name", ["env_phong", "env_plastic"])
def test_a_wide_probe_is_recovered(tmp_path, wide_probe, name):
    # The shipped case under a wide probe, rendered by Mitsuba from the whole map. The
    # opaque lobes are lit from its first level at most envlight.LIGHT_WIDTH wide
    # (before that, lit from the map itself, env_phong's e came out 4 % low at 7.8
    # stated errors, and a fit took 3.9 GB).
    _recovered_under(tmp_path, name, wide_probe)


def _recovered_under(tmp_path, name, probe, size=None):
    """The shipped case ``name`` under the envmap ``probe`` (at ``size``: film width,
    supersampling), rendered by Mitsuba from the whole map (4096 spp), fitted, and each
    free parameter within its tolerance and ``STATED_COVERS`` stated errors."""
    from fitter.mitsuba.synth import write_case
    from fitter.pipeline import truth_params

    spec = json.loads(json.dumps(CASES[name]))
    spec["scene"]["environment"]["file"] = probe
    if size:
        spec["scene"].update(width=size[0], height=size[0], supersampling=size[1])
    job = config.job_from_dict({"scene": spec["scene"], "material": spec["material"]},
                               base_dir=str(tmp_path))
    truth = truth_params(job)
    write_case(str(tmp_path / "case"), job.scene, job.material, truth, spp=4096, seed=0)
    target = read_image(str(tmp_path / "case" / "target.exr"))
    res = fitter.fit(target, job.scene, job.material, fixed=job.fixed)
    assert res.status == "converged", res.message
    for key in res.free:
        abs_tol, rel_tol = TOLERANCES[key.split(".", 1)[1]]
        want, got = np.asarray(truth[key]), np.asarray(res.params[key])
        assert np.all(np.abs(got - want) <= abs_tol + rel_tol * np.abs(want)), (key, got, want)
        assert np.all(np.abs(got - want) <= STATED_COVERS * np.asarray(res.stderr[key])), (
            key, got, want, res.stderr[key])


#: Bright sources unlike the probe's 3 deg sun: itself 20 deg wide (a studio softbox),
#: a second 3 deg sun 80 deg from it (a lamp beside a window), and the sun at the zenith
#: (noon: the map's pole row).
BRIGHT_SOURCES = {"wide": (("probe", 20.0, 300.0),),
                  "two": (("probe", 3.0, 300.0), ((-0.5, 0.6, 0.6), 3.0, 300.0)),
                  "zenith": (((0.0, 1.0, 0.0), 3.0, 300.0),)}


@pytest.mark.parametrize("case, sources, size", [
    ("env_plastic", "wide", (64, 2)), ("env_phong", "two", (64, 2)),
    ("env_plastic", "zenith", (128, 4))])  # (at 64^2 x 2^2 its m, eta: 3 %, 0.009 stated)
def test_bright_sources_unlike_the_probe_sun_are_recovered(tmp_path, case, sources, size):
    # The shipped probe with those sources, Mitsuba from the whole map, at ``size`` (film
    # width, supersampling; 64^2 x 2^2 for the wide source's memory, its ~300 cells,
    # where the pixels still pin every parameter). Before suncells.clusters the samples far
    # from the highlight saw every sun cell as one light at their centroid: at 128^2
    # under the wide source rho_d came out 0.0036 low at 12.7 stated errors and eta
    # 0.004 at 11.7; under the two suns env_phong's rho_d 0.012 low at 5.6 (converged).
    # Before the sun's texel cap counted solid angle (envlight._row_shares) half the
    # zenith sun stayed in the sky stencil: env_plastic's rho_d 0.017 low at 4.8. (A
    # sharp lobe under it needs a Mitsuba target of ~250 k spp: benchmarks/README.md.)
    from fitter.mitsuba.synth import PROBE_SUN, make_probe

    probe = str(tmp_path / "probe.exr")
    make_probe(probe, suns=tuple((PROBE_SUN[0] if d == "probe" else d, diam, ratio)
                                 for d, diam, ratio in BRIGHT_SOURCES[sources]))
    _recovered_under(tmp_path, case, probe, size)

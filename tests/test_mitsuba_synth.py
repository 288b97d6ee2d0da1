"""Synthetic targets, image metrics, the translator's refusals and the variant choice."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

import fitter
import fitter.mitsuba as fm
from fitter import config
from fitter.imageio import read_image
from fitter.metrics import compare
from fitter.mitsuba import variant
from fitter.cases import CASES, NOTES
from fitter.mitsuba.synth import make_envmap, make_probe, write_case
from fitter.mitsuba.translate import medium_dict, stratified_spp

SCENE = fitter.Scene(width=24, height=16, supersampling=2,
                     lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),))
PLASTIC = fitter.Material.make("lambert+torrance_sparrow")
PARAMS = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15}
EXACT = 0.0
CLOSE = 1e-12  # float64 rounding of closed forms


# ------------------------------------------------------------------ write_case


@pytest.mark.mitsuba
def test_write_case_is_reproducible_bit_for_bit(tmp_path):
    files = ("target.exr", "preview.png", "case.json")
    out = []
    for run in ("a", "b"):
        write_case(str(tmp_path / run), SCENE, PLASTIC, PARAMS, spp=16, seed=3)
        out.append([(tmp_path / run / f).read_bytes() for f in files])
    for name, x, y in zip(files, *out):
        assert x == y, f"{name} differs between two identical renders"
    leftovers = [f for f in os.listdir(tmp_path / "a") if f.startswith(".tmp")]
    assert not leftovers


@pytest.mark.mitsuba
def test_write_case_contents(tmp_path):
    case = write_case(str(tmp_path), SCENE, PLASTIC, PARAMS, spp=16, seed=3,
                      extra={"name": "t"})
    img = read_image(str(tmp_path / "target.exr"))
    assert img.shape == (16, 24, 3) and np.all(np.isfinite(img)) and img.max() > 0
    data = json.loads((tmp_path / "case.json").read_text())
    assert data == json.loads(json.dumps({k: v for k, v in case.items()
                                          if k != "render_time_s"}))
    assert data["mitsuba"]["spp"] == 16 and data["mitsuba"]["seed"] == 3
    assert data["mitsuba"]["integrator"]["type"] == "direct"
    assert data["truth"]["torrance_sparrow.eta"] == 1.5  # the lobe default, recorded
    # The JSON is a valid config: it rebuilds the same scene and material.
    job = config.job_from_dict({"scene": data["scene"], "material": data["material"]},
                               base_dir=str(tmp_path))
    assert job.scene == SCENE and job.material == PLASTIC


# ------------------------------------------------------------------ the case table


@pytest.mark.parametrize("name", list(CASES))
def test_case_table_is_valid_config(name, tmp_path):
    make_envmap(str(tmp_path / "envmap.exr"))
    make_probe(str(tmp_path / "probe.exr"))
    case_dir = tmp_path / name
    case_dir.mkdir()
    job = config.job_from_dict(CASES[name], base_dir=str(case_dir))
    size = {"metal_gold": 64, "bright_phong": 96}.get(name, 128)  # small cases (issue 13)
    assert job.scene.width == size and job.scene.supersampling == 4
    assert NOTES[name]
    fm.translate.check_translatable(job.scene, job.material)


def test_shipped_cases_are_present_and_small():
    root = os.path.join(os.path.dirname(__file__), os.pardir, "data_synthetic")
    total = 0
    for name in CASES:
        for f in ("target.exr", "preview.png", "case.json"):
            path = os.path.join(root, name, f)
            assert os.path.isfile(path), f"missing {path}; run data_synthetic/generate.py"
            total += os.path.getsize(path)
        data = json.load(open(os.path.join(root, name, "case.json")))
        assert data["material"]["truth"] == config.material_to_dict(
            fitter.Material.make(data["material"]["lobes"]), truth=data["truth"])["truth"]
    assert total < 5e6


# ------------------------------------------------------------------ translation


def test_opaque_lobe_under_environment_is_rendered_by_path():
    # Issue 11: the environment lights opaque lobes in both renderers (was refused).
    scene = SCENE.replace(environment=fitter.Environment(type="constant", radiance=(1, 1, 1)))
    fm.translate.check_translatable(scene, PLASTIC)
    integ = fm.translate.integrator_dict(PLASTIC, scene)
    assert integ["type"] == "path" and integ["max_depth"] == 2


def test_dielectric_sum_is_refused():
    with pytest.raises(fm.MitsubaError, match="dielectric"):
        fm.translate.check_translatable(SCENE, fitter.Material.make("dielectric+lambert"))


def test_medium_sigma_is_minus_log_attenuation():
    # Beer-Lambert c^d = exp(-sigma d)  =>  sigma = -ln c (Teschner, Materials 3).
    med = medium_dict([0.9, 0.5, 0.25])
    sigma = np.array(med["sigma_t"]["value"]) * med["scale"]
    np.testing.assert_allclose(sigma, -np.log([0.9, 0.5, 0.25]), rtol=CLOSE)
    assert max(med["sigma_t"]["value"]) == 1.0  # Mitsuba rejects RGB sigma_t > 1
    assert medium_dict([1.0, 1.0, 1.0]) is None
    assert np.isfinite(medium_dict([0.0, 0.5, 1.0])["scale"])


def test_stratified_spp_rounds_up_to_a_square():
    assert [stratified_spp(n) for n in (1, 2, 4, 5, 256, 1000)] == [1, 4, 4, 9, 256, 1024]


def test_every_lobe_has_a_mitsuba_mapping():
    for lobe in fitter.LOBES.values():
        full = fitter.Material.make([lobe.name]).full_params()
        p = {k.split(".", 1)[1]: v for k, v in full.items()}
        opts = fitter.Material.make([lobe.name]).options_of(lobe.name)
        d = lobe.mitsuba(p, opts)
        assert isinstance(d["type"], str)
        json.dumps(d)  # plain data only


# ------------------------------------------------------------------ variant / LLVM


def test_variant_choice(monkeypatch):
    monkeypatch.delenv(variant.ENV_VAR, raising=False)
    monkeypatch.setattr(variant, "_gpu_present", lambda: False)
    assert variant.choose_variant() == "llvm_ad_rgb"
    monkeypatch.setattr(variant, "_gpu_present", lambda: True)
    assert variant.choose_variant() == "cuda_ad_rgb"
    monkeypatch.setenv(variant.ENV_VAR, "scalar_rgb")
    assert variant.choose_variant() == "scalar_rgb"
    assert variant.choose_variant("llvm_ad_rgb") == "llvm_ad_rgb"


def test_unknown_variant_is_one_sentence():
    with pytest.raises(fm.MitsubaError, match="not available"):
        variant.load("no_such_variant")


def test_find_libllvm_picks_newest_at_least_16(tmp_path):
    for name in ("libLLVM-14.so.1", "libLLVM-15.so", "libLLVM.so.19.1", "libLLVM-17.so"):
        (tmp_path / name).write_bytes(b"")
    assert os.path.basename(variant.find_libllvm([str(tmp_path)])) == "libLLVM.so.19.1"
    (tmp_path / "libLLVM.so.19.1").unlink()
    (tmp_path / "libLLVM-17.so").unlink()
    assert variant.find_libllvm([str(tmp_path)]) is None


# ------------------------------------------------------------------ metrics


def test_compare_identical_images():
    rng = np.random.default_rng(0)
    img = rng.uniform(0.0, 1.0, (8, 9, 3))
    m = compare(img, img)
    assert m["rmse"] == EXACT and m["psnr_db"] == math.inf
    assert m["delta_e2000_mean"] == EXACT and m["delta_e2000_max"] == EXACT
    assert m["n_pixels"] == 72


def test_compare_constant_offset_closed_form():
    # RMSE of a constant offset c is c; PSNR = 20 log10(peak / c).
    rng = np.random.default_rng(1)
    target = rng.uniform(0.1, 0.8, (6, 7, 3))
    c = 0.01
    m = compare(target, target + c)
    assert abs(m["rmse"] - c) < CLOSE
    assert abs(m["psnr_db"] - 20.0 * math.log10(target.max() / c)) < 1e-9
    assert m["delta_e2000_mean"] > 0


def test_compare_delta_e_of_white_and_black_is_100():
    # White (L* = 100) vs black (L* = 0), a* = b* = 0: CIEDE2000 reduces to
    # dL' / S_L with S_L = 1 at mean L' = 50 (Sharma et al. 2005, eq. 15), so 100.
    white, black = np.ones((1, 1, 3)), np.zeros((1, 1, 3))
    m = compare(white, black)
    assert abs(m["delta_e2000_mean"] - 100.0) < 1e-6
    assert abs(m["rmse"] - 1.0) < CLOSE and m["psnr_db"] == 0.0


def test_compare_mask_and_clipping():
    target = np.zeros((2, 2, 3))
    image = target.copy()
    image[0, 0] = 5.0  # outside the mask
    mask = np.array([[False, True], [True, True]])
    assert compare(target, image, mask)["rmse"] == EXACT
    # Display range is clipped to [0, 1] for ΔE only.
    m = compare(np.ones((1, 1, 3)), np.full((1, 1, 3), 3.0))
    assert m["delta_e2000_max"] == EXACT and abs(m["rmse"] - 2.0) < CLOSE
    with pytest.raises(ValueError, match="mask"):
        compare(target, image, np.zeros((2, 2), bool))


OLD_LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so"


@pytest.mark.skipif(not os.path.exists(OLD_LLVM), reason="needs an LLVM 15 library to load")
def test_old_llvm_is_a_clear_error_not_an_abort():
    # drjit with LLVM 15 aborts the process on roughconductor kernels
    # ("LLVM ERROR: Cannot select ... fmaximum"); we must stop before that.
    import subprocess
    import sys

    code = ("import fitter, fitter.mitsuba as fm\n"
            "sc = fitter.Scene(width=8, height=8, lights=(fitter.PointLight((3., 4., 5.), "
            "(50., 50., 50.)),))\n"
            "m = fitter.Material.make('torrance_sparrow', {'torrance_sparrow.geometry': 'smith'})\n"
            "try:\n    fm.render(sc, m, {}, spp=4)\n"
            "except fm.MitsubaError as e:\n    print('MitsubaError:', e)\n")
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": OLD_LLVM, variant.ENV_VAR: "llvm_ad_rgb"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-500:]
    assert "MitsubaError: drjit loaded LLVM 15" in out.stdout
    assert "apt-get install -y libllvm19" in out.stdout


@pytest.mark.mitsuba
def test_case_json_envmap_path_is_relative_to_the_final_folder(tmp_path):
    make_envmap(str(tmp_path / "env.exr"))
    scene = SCENE.replace(lights=(), environment=fitter.Environment(type="envmap",
                                                                    file="env.exr"))
    final = tmp_path / "cases" / "m"
    write_case(str(final / ".stage"), scene, fitter.Material.make("mirror"), {}, spp=4, seed=0,
               base_dir=str(tmp_path), paths_relative_to=str(final))
    data = json.loads((final / ".stage" / "case.json").read_text())
    assert data["scene"]["environment"]["file"] == "../../env.exr"
    assert (final / data["scene"]["environment"]["file"]).resolve() == (tmp_path / "env.exr")

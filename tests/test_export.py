"""scene.xml: a fit as a Mitsuba 3 scene that stock Mitsuba loads (issue 13, item 4).

Each exported file is loaded by ``mi.load_file`` in a fresh Python that never
imports fitter (checked), rendered at low spp, and its interior mean compared
with the JAX forward model within the cross-check tolerance
(``test_mitsuba_crosscheck.MEAN_REL_TOL``, 1 %). Sums become stock
``blendbsdf``s; the absorbing dielectric a ``homogeneous`` medium under
``volpathmis``; a lobe without a built-in names the fitter plugin and the
file says how to register it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import fitter
from fitter.material import Material
from fitter.mitsuba.export import PLUGIN_IMPORT, export_scene

pytestmark = pytest.mark.mitsuba

MEAN_REL_TOL = 0.01
SIZE = 32
LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
          fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0)))
SCENE = fitter.Scene(width=SIZE, height=SIZE, supersampling=4, lights=LIGHTS)
#: Pixels wholly on the unit sphere at the default camera, 32^2.
INNER = (slice(10, 22), slice(10, 22))


def _stock_render(xml: str, out: str, prelude: str = "") -> subprocess.CompletedProcess:
    """Render ``xml`` in a fresh interpreter; the image goes to ``out`` (.npy)."""
    code = (f"import sys\n{prelude}\nimport mitsuba as mi, numpy as np\n"
            "mi.set_variant('llvm_ad_rgb')\n"
            f"img = np.array(mi.render(mi.load_file({xml!r})))\n"
            f"np.save({out!r}, img)\n"
            "print('fitter imported' if 'fitter' in sys.modules else 'fitter not imported')\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, cwd=os.path.dirname(xml))


def _check(tmp_path, scene, material, params, spp=16, tol=MEAN_REL_TOL):
    xml = str(tmp_path / "scene.xml")
    plugins = export_scene(xml, scene, material, params, spp=spp, seed=3)
    assert plugins == []
    run = _stock_render(xml, str(tmp_path / "img.npy"))
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "fitter not imported"
    ref = np.load(tmp_path / "img.npy")
    model = np.asarray(fitter.render(params, scene, material))
    rel = model[INNER].mean(axis=(0, 1)) / ref[INNER].mean(axis=(0, 1)) - 1.0
    assert np.all(np.abs(rel) < tol), rel
    return open(xml, encoding="utf-8").read()


def test_sum_of_builtins_is_a_stock_blend(tmp_path):
    mat = Material.make(["lambert", "torrance_sparrow"], {"torrance_sparrow.geometry": "smith"})
    text = _check(tmp_path, SCENE, mat, {"lambert.rho_d": [0.6, 0.4, 0.2],
                                         "torrance_sparrow.m": 0.2})
    assert 'type="blendbsdf"' in text and "fitter_" not in text


THREE = Material.make(["lambert", "mirror", "torrance_sparrow"],
                      {"torrance_sparrow.geometry": "smith", "torrance_sparrow.fresnel":
                       "conductor"})
THREE_PARAMS = {"lambert.rho_d": [0.3, 0.2, 0.1], "mirror.rho_m": 0.2, "torrance_sparrow.m": 0.3,
                "torrance_sparrow.eta": [0.143, 0.375, 1.442],
                "torrance_sparrow.k": [3.983, 2.386, 1.603]}


def test_three_builtins_and_a_conductor(tmp_path):
    text = _check(tmp_path, SCENE, THREE, THREE_PARAMS)
    assert text.count('type="blendbsdf"') == 2


def test_delta_lobe_in_a_sampled_sum_stays_the_plugin_sum(tmp_path):
    """Mitsuba's blendbsdf of a mirror and a smooth BSDF is biased under path/MIS."""
    scene = SCENE.replace(environment=fitter.Environment(type="constant",
                                                         radiance=(0.3, 0.3, 0.3)))
    xml = str(tmp_path / "scene.xml")
    assert export_scene(xml, scene, THREE, THREE_PARAMS, spp=16, seed=1) == ["fitter_sum"]
    assert PLUGIN_IMPORT in open(xml, encoding="utf-8").read()


def test_absorbing_dielectric_is_a_medium_under_volpath(tmp_path):
    scene = SCENE.replace(lights=(), environment=fitter.Environment(
        type="constant", radiance=(1.0, 1.0, 1.0)))
    mat = Material.make(["dielectric"])
    params = {"dielectric.eta": 1.5, "dielectric.attenuation": [0.5, 0.7, 0.9]}
    text = _check(tmp_path, scene, mat, params, spp=64, tol=0.02)
    assert 'type="homogeneous"' in text and 'type="volpathmis"' in text


def test_envmap_is_copied_beside_the_scene(tmp_path):
    from fitter.mitsuba.synth import make_envmap

    env_dir = tmp_path / "maps"
    env_dir.mkdir()
    make_envmap(str(env_dir / "sky.exr"))
    scene = SCENE.replace(lights=(), environment=fitter.Environment(
        type="envmap", file=str(env_dir / "sky.exr")))
    out = tmp_path / "out"
    out.mkdir()
    text = _check(out, scene, Material.make(["lambert"]), {"lambert.rho_d": 0.5}, spp=256,
                  tol=0.03)
    assert (out / "sky.exr").is_file() and 'value="sky.exr"' in text


def test_plugin_lobe_names_the_import_that_registers_it(tmp_path):
    mat = Material.make(["lambert", "phong"])
    params = {"lambert.rho_d": [0.5, 0.4, 0.3], "phong.rho_s": 0.3, "phong.e": 40.0}
    xml = str(tmp_path / "scene.xml")
    assert export_scene(xml, SCENE, mat, params, spp=16, seed=1) == ["fitter_phong", "fitter_sum"]
    text = open(xml, encoding="utf-8").read()
    assert PLUGIN_IMPORT in text
    stock = _stock_render(xml, str(tmp_path / "a.npy"))
    assert stock.returncode != 0  # stock Mitsuba does not know fitter_phong
    run = _stock_render(xml, str(tmp_path / "b.npy"), prelude=PLUGIN_IMPORT.replace("; ", "\n"))
    assert run.returncode == 0, run.stderr
    ref = np.load(tmp_path / "b.npy")
    model = np.asarray(fitter.render(params, SCENE, mat))
    rel = model[INNER].mean(axis=(0, 1)) / ref[INNER].mean(axis=(0, 1)) - 1.0
    assert np.all(np.abs(rel) < MEAN_REL_TOL), rel


def test_fitter_export_command_on_an_output_folder(tmp_path):
    """`fitter fit` writes scene.xml; `fitter export OUTDIR` rewrites it plus material.json."""
    from small_case import write_case

    small = write_case(str(tmp_path / "case"))
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "fitter", "fit", small, "--out", str(out),
                          "--quiet"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert (out / "scene.xml").is_file()
    os.remove(out / "scene.xml")
    run = subprocess.run([sys.executable, "-m", "fitter", "export", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    material = json.loads((out / "material.json").read_text())
    result = json.loads((out / "result.json").read_text())
    assert material["lobes"] == ["lambert", "torrance_sparrow"]
    assert material["params"] == result["params"]
    assert material["options"]["torrance_sparrow.geometry"] == "smith"
    assert "blendbsdf" in (out / "scene.xml").read_text()

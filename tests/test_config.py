"""The TOML config layer: valid jobs parse, every mistake is one sentence naming file and key."""

import copy
import os
import tomllib

import pytest

import fitter
from fitter.config import (
    ConfigError,
    FitOptions,
    dumps_toml,
    job_from_dict,
    job_to_dict,
    load_config,
    scene_from_dict,
    scene_to_dict,
    solvers,
)

BASE = {
    "scene": {
        "width": 64, "height": 48, "supersampling": 2,
        "camera": {"type": "perspective", "origin": [0.0, 0.0, 4.0], "target": [0.0, 0.0, 0.0],
                   "up": [0.0, 1.0, 0.0], "fov": 35.0},
        "sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.0},
        "lights": [
            {"type": "point", "position": [3.0, 4.0, 5.0], "intensity": [50.0, 50.0, 50.0]},
            {"type": "directional", "direction": [-1.0, -1.0, -1.0], "irradiance": [2.0, 2.0, 2.0]},
        ],
        "environment": {"type": "black"},
    },
    "material": {
        "lobes": ["lambert", "torrance_sparrow"],
        "truth": {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
                  "torrance_sparrow.eta": 1.5},
        "init": {"torrance_sparrow.m": 0.3},
        "fixed": {"torrance_sparrow.geometry": "smith"},
    },
    "fit": {"target": "data/target.exr", "solver": "levenberg_marquardt"},
}


def _with(path, value):
    """A copy of BASE with the dotted ``path`` set to ``value`` (``...`` deletes it)."""
    data = copy.deepcopy(BASE)
    *parents, last = path
    node = data
    for p in parents:
        node = node[p]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return data


def test_base_config_maps_onto_the_dataclasses(tmp_path):
    path = str(tmp_path / "job.toml")
    job = job_from_dict(BASE, path)
    assert job.name == "job"
    assert job.base_dir == str(tmp_path)
    assert job.scene == fitter.Scene(
        width=64, height=48, supersampling=2,
        lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
                fitter.DirectionalLight((-1.0, -1.0, -1.0), (2.0, 2.0, 2.0))))
    assert job.material == fitter.Material.make(["lambert", "torrance_sparrow"],
                                                {"torrance_sparrow.geometry": "smith"})
    assert job.truth == {"lambert.rho_d": (0.6, 0.4, 0.2), "torrance_sparrow.m": 0.15,
                         "torrance_sparrow.eta": 1.5}
    assert job.init == {"torrance_sparrow.m": 0.3}
    assert job.fixed == {}
    # relative paths resolve against the config file's folder
    assert job.fit.target == str(tmp_path / "data" / "target.exr")
    assert job.fit.solver == "levenberg_marquardt"
    assert job.fit.validate is True


def test_defaults_fill_missing_optional_keys(tmp_path):
    job = job_from_dict({"scene": {}, "material": {"lobes": "lambert + phong"}},
                        str(tmp_path / "j.toml"))
    assert job.scene == fitter.Scene()
    assert job.material.lobes == ("lambert", "phong")
    assert job.fit == FitOptions()
    assert job.truth == job.init == job.fixed == {}


def test_toml_written_by_dumps_toml_reads_back_to_the_same_job(tmp_path):
    data = _with(("fit", "noise_sigma"), 0.01)
    data["material"]["fixed"]["lambert.rho_d"] = 0.5
    data["material"]["init"] = {"torrance_sparrow.eta": 1.7}
    job = job_from_dict(data, str(tmp_path / "a.toml"))
    path = tmp_path / "b.toml"
    path.write_text(dumps_toml(job_to_dict(job)))
    again = load_config(str(path))
    assert again.replace(path=job.path) == job
    assert again.fixed == {"lambert.rho_d": (0.5, 0.5, 0.5)}


@pytest.mark.parametrize("camera", [
    {"type": "perspective", "origin": [1.0, 2.0, 5.0], "fov": 20.0},
    {"type": "orthographic", "origin": [0.0, 0.0, 3.0], "half_width": 1.5},
])
def test_scene_to_dict_is_the_inverse_of_scene_from_dict(tmp_path, camera):
    scene_tbl = _with(("scene", "camera"), camera)["scene"]
    scene_tbl["environment"] = {"type": "constant", "radiance": [0.1, 0.2, 0.3]}
    scene = scene_from_dict(scene_tbl, str(tmp_path / "x.toml"))
    assert scene_from_dict(scene_to_dict(scene), str(tmp_path / "x.toml")) == scene
    assert tomllib.loads(dumps_toml({"scene": scene_to_dict(scene)}))["scene"] == scene_to_dict(scene)


def test_envmap_path_is_resolved_and_must_exist(tmp_path):
    (tmp_path / "sky.exr").write_bytes(b"")
    env = {"type": "envmap", "file": "sky.exr", "scale": 2.0}
    job = job_from_dict(_with(("scene", "environment"), env), str(tmp_path / "j.toml"))
    assert job.scene.environment == fitter.Environment(type="envmap", file=str(tmp_path / "sky.exr"),
                                                       scale=2.0)
    env["file"] = "nope.exr"
    with pytest.raises(ConfigError, match="nope.exr"):
        job_from_dict(_with(("scene", "environment"), env), str(tmp_path / "j.toml"))


# (where in BASE, bad value, words the message must contain)
ERRORS = [
    (("surprise",), 1, ["surprise", "unknown key"]),
    (("scene", "widht"), 3, ["scene.widht", "unknown key", "width"]),
    (("scene", "width"), 0, ["scene.width", ">= 1"]),
    (("scene", "height"), 12.5, ["scene.height", "integer"]),
    (("scene", "supersampling"), True, ["scene.supersampling", "integer"]),
    (("scene", "camera", "type"), "fisheye", ["scene.camera.type", "'perspective'",
                                              "'orthographic'"]),
    (("scene", "camera", "half_width"), 1.0, ["scene.camera.half_width", "unknown key"]),
    (("scene", "camera", "fov"), 180.0, ["scene.camera.fov", "range"]),
    (("scene", "camera", "origin"), [0.0, 4.0], ["scene.camera.origin", "3 numbers"]),
    (("scene", "camera", "origin"), [0.0, 0.0, 0.5], ["scene.camera.origin", "inside the sphere"]),
    (("scene", "camera", "up"), [0.0, 0.0, 1.0], ["scene.camera.up", "parallel"]),
    (("scene", "camera", "target"), [0.0, 0.0, 4.0], ["scene.camera.target", "differ"]),
    (("scene", "sphere", "radius"), -1.0, ["scene.sphere.radius", "range"]),
    (("scene", "sphere", "radius"), "big", ["scene.sphere.radius", "number"]),
    (("scene", "lights"), {"type": "point"}, ["scene.lights", "array of tables"]),
    (("scene", "lights", 0, "type"), "spot", ["scene.lights[0].type", "'point'", "'directional'"]),
    (("scene", "lights", 0, "type"), ..., ["scene.lights[0].type", "missing"]),
    (("scene", "lights", 0, "intensity"), [1.0, -1.0, 1.0], ["scene.lights[0].intensity", "range"]),
    (("scene", "lights", 0, "intensity"), ..., ["scene.lights[0].intensity", "missing"]),
    (("scene", "lights", 0, "irradiance"), [1.0, 1.0, 1.0], ["scene.lights[0].irradiance",
                                                            "unknown key"]),
    (("scene", "lights", 0, "position"), [0.0, 0.5, 0.0], ["scene.lights[0].position", "inside"]),
    (("scene", "lights", 1, "direction"), [0.0, 0.0, 0.0], ["scene.lights[1].direction", "zero"]),
    (("scene", "lights", 1, "direction"), [0.0, float("nan"), 1.0], ["scene.lights[1].direction",
                                                                     "finite"]),
    (("scene", "environment", "type"), "sky", ["scene.environment.type", "'black'", "'constant'",
                                               "'envmap'"]),
    (("scene", "environment", "radiance"), [1.0, 1.0, 1.0], ["scene.environment.radiance",
                                                             "unknown key"]),
    (("scene", "environment"), {"type": "constant"}, ["scene.environment.radiance", "missing"]),
    (("scene", "environment"), {"type": "envmap"}, ["scene.environment.file", "missing"]),
    (("scene",), ..., ["[scene]", "missing"]),
    (("material",), ..., ["[material]", "missing"]),
    (("material", "lobes"), ..., ["material.lobes", "missing", "lambert"]),
    (("material", "lobes"), ["lambert", "ward"], ["material.lobes", "ward", "torrance_sparrow"]),
    (("material", "lobes"), ["lambert", "lambert"], ["material", "twice"]),
    (("material", "lobes"), 3, ["material.lobes", "list"]),
    (("material", "shiny"), 1.0, ["material.shiny", "unknown key"]),
    (("material", "truth", "lambert.rho_d"), [0.6, 0.4, 1.2], ["material.truth.lambert.rho_d",
                                                               "[0, 1]"]),
    (("material", "truth", "lambert.rho_d"), [0.6, 0.4], ["material.truth.lambert.rho_d",
                                                          "3 value"]),
    (("material", "truth", "torrance_sparrow.m"), 0.0, ["material.truth.torrance_sparrow.m",
                                                        "[0.001, 1]"]),
    (("material", "truth", "torrance_sparrow.m"), "rough", ["material.truth.torrance_sparrow.m",
                                                            "number"]),
    (("material", "truth", "phong.e"), 10.0, ["material.truth.phong.e", "unknown parameter",
                                              "torrance_sparrow.eta"]),
    (("material", "truth", "torrance_sparrow.geometry"), "v_groove",
     ["material.truth.torrance_sparrow.geometry", "differs", "smith"]),
    (("material", "init", "torrance_sparrow.eta"), 0.5, ["material.init.torrance_sparrow.eta",
                                                         "range"]),
    (("material", "init", "torrance_sparrow.geometry"), "smith",
     ["material.init.torrance_sparrow.geometry", "option"]),
    (("material", "fixed", "torrance_sparrow.m"), 0.2, ["material.init.torrance_sparrow.m",
                                                        "material.fixed"]),
    (("material", "fixed", "torrance_sparrow.geometry"), "ggx",
     ["torrance_sparrow.geometry", "'v_groove'", "'smith'"]),
    (("material", "fixed", "torrance_sparrow.geometry"), True,
     ["torrance_sparrow.geometry", "'v_groove'"]),
    (("material", "init"), 0.3, ["material.init", "table"]),
    (("fit", "solver"), "newton", ["fit.solver", "'levenberg_marquardt'", "'dogleg'"]),
    (("fit", "loss"), "l1", ["fit.loss", "'huber'", "'cauchy'"]),
    (("fit", "n_starts"), 0, ["fit.n_starts", ">= 1"]),
    (("fit", "max_steps"), 2.5, ["fit.max_steps", "integer"]),
    (("fit", "rtol"), 0.0, ["fit.rtol", "range"]),
    (("fit", "noise_sigma"), -0.1, ["fit.noise_sigma", "range"]),
    (("fit", "validate"), "yes", ["fit.validate", "true or false"]),
    (("fit", "validate_spp"), 0, ["fit.validate_spp", ">= 1"]),
    (("fit", "saturation"), 0, ["fit.saturation", "range"]),
    (("fit", "target"), 7, ["fit.target", "string"]),
    (("fit", "dtype"), "float16", ["fit.dtype", "'float64'", "'float32'"]),
    (("fit", "mask"), "edges", ["fit.mask", "'interior'", "'active'"]),
    (("fit", "solve"), "lm", ["fit.solve", "unknown key", "solver"]),
]


@pytest.mark.parametrize("where,value,words", ERRORS, ids=[
    ".".join(map(str, w)) + f"={v!r}"[:20] for w, v, _ in ERRORS])
def test_each_mistake_is_one_sentence_naming_file_and_key(tmp_path, where, value, words):
    path = str(tmp_path / "bad.toml")
    with pytest.raises(ConfigError) as info:
        job_from_dict(_with(where, value), path)
    msg = str(info.value)
    assert msg.startswith(path + ": ")
    assert "\n" not in msg
    for word in words:
        assert word in msg, (word, msg)


def test_unknown_solver_lists_exactly_the_engines_solvers(tmp_path):
    with pytest.raises(ConfigError) as info:
        job_from_dict(_with(("fit", "solver"), "newton"), str(tmp_path / "x.toml"))
    for name in solvers():
        assert repr(name) in str(info.value)


def test_option_values_stand_in_fixed_like_numbers(tmp_path):
    data = copy.deepcopy(BASE)
    data["material"] = {"lobes": ["lambert", "phong", "dielectric"],
                        "fixed": {"phong.normalized": True, "dielectric.bounces": 4,
                                  "phong.e": 50.0}}
    job = job_from_dict(data, str(tmp_path / "x.toml"))
    assert job.material.options_of("phong") == {"normalized": True}
    assert job.material.options_of("dielectric") == {"bounces": 4}
    assert job.fixed == {"phong.e": 50.0}
    data["material"]["fixed"]["dielectric.bounces"] = -1
    with pytest.raises(ConfigError, match="dielectric.bounces"):
        job_from_dict(data, str(tmp_path / "x.toml"))


@pytest.mark.parametrize("text,words", [
    ("[scene\nwidth = 3", ["not valid TOML"]),
    (b"\xff\xfe[scene]", ["not valid TOML"]),
])
def test_unreadable_toml_names_the_file(tmp_path, text, words):
    path = tmp_path / "broken.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ConfigError) as info:
        load_config(str(path))
    assert str(info.value).startswith(str(path))
    for word in words:
        assert word in str(info.value)


def test_missing_config_file_is_named(tmp_path):
    path = str(tmp_path / "absent.toml")
    with pytest.raises(ConfigError, match="absent.toml: config file not found"):
        load_config(path)


ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir)


def _case_names():
    from fitter.cases import CASES

    return sorted(CASES)


@pytest.mark.parametrize("name", _case_names())
def test_case_config_matches_the_case_table_and_its_case_json(name):
    """configs/<case>.toml describes exactly the shipped case (cases.py and case.json)."""
    import json

    import numpy as np

    from fitter.cases import CASES

    job = load_config(os.path.join(ROOT, "configs", f"{name}.toml"))
    case_dir = os.path.join(ROOT, "data_synthetic", name)
    ref = job_from_dict(CASES[name], f"<case {name}>", base_dir=case_dir)
    assert job.scene == ref.scene
    assert job.material == ref.material
    assert (job.truth, job.fixed, job.synth) == (ref.truth, ref.fixed, ref.synth)
    assert os.path.normpath(job.fit.target) == os.path.normpath(
        os.path.join(case_dir, "target.exr"))
    with open(os.path.join(case_dir, "case.json")) as fh:
        case = json.load(fh)
    assert scene_from_dict(case["scene"], base_dir=case_dir) == job.scene
    full = job.material.full_params({**job.fixed, **job.truth})
    assert set(full) == set(case["truth"])
    for key, value in full.items():
        np.testing.assert_array_equal(value, case["truth"][key], err_msg=key)


def test_shipped_configs_load():
    folder = os.path.join(os.path.dirname(__file__), os.pardir, "configs")
    names = sorted(f for f in os.listdir(folder) if f.endswith(".toml")) if os.path.isdir(
        folder) else []
    assert "quickstart.toml" in names
    for name in names:
        job = load_config(os.path.join(folder, name))
        assert job.fit.target is not None, name
        assert job.truth, name


def test_pixel_rule_is_read_written_and_checked(tmp_path):
    path = str(tmp_path / "x.toml")
    assert job_from_dict(BASE, path).scene.pixel_rule == "gauss"
    scene = job_from_dict(_with(("scene", "pixel_rule"), "midpoint"), path).scene
    assert scene.pixel_rule == "midpoint"
    assert scene_from_dict(scene_to_dict(scene), path) == scene
    with pytest.raises(ConfigError, match="scene.pixel_rule"):
        job_from_dict(_with(("scene", "pixel_rule"), "simpson"), path)

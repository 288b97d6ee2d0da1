"""The stated discretisation error's finer geometry, made on a thread while the
solver runs (``fit._discretisation.prefetch``), is the one made where it is
used: the fit states the same errors either way."""

from __future__ import annotations

import threading

import numpy as np

import fitter
from fitter.fit import _discretisation, _renders

LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),)
SCENE = fitter.Scene(width=48, height=48, supersampling=2, lights=LIGHTS)
GLOSSY = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
          "torrance_sparrow.eta": 1.5}


def test_the_finer_geometry_made_ahead_gives_the_same_stated_errors(finer_builds, monkeypatch):
    # Target with 16 x 16 samples, fitted with 2 x 2: a discretisation error to state.
    target = np.asarray(fitter.render(GLOSSY, SCENE.replace(supersampling=16)))
    made_on = finer_builds
    monkeypatch.setattr(_discretisation, "_GEOMETRIES", {})  # none kept from other fits
    ahead = fitter.fit(target, SCENE, "lambert+torrance_sparrow")
    assert made_on == [(4, "fitter-finer-geometry")]
    assert not _discretisation._AHEAD  # used, not kept

    made_on.clear()
    _discretisation._GEOMETRIES.clear()  # a refit would reuse the kept one
    monkeypatch.setattr(_discretisation, "prefetch", lambda problem: None)
    here = fitter.fit(target, SCENE, "lambert+torrance_sparrow")
    assert made_on == [(4, threading.main_thread().name)]

    assert ahead.status == here.status == "converged"
    for key in GLOSSY:
        for part in ("params", "stderr", "stderr_disc", "stderr_sys"):
            np.testing.assert_array_equal(getattr(ahead, part)[key], getattr(here, part)[key])
    assert np.all(np.asarray(ahead.stderr_disc["lambert.rho_d"]) > 0)


def test_shift_of_several_changes_is_each_ones_least_squares_shift():
    """Reference: NumPy's least-squares solve of J itself (SVD), per column."""
    rng = np.random.default_rng(4)
    J, d = rng.normal(size=(500, 5)) * [1.0, 0.1, 3.0, 1.0, 0.01], rng.normal(size=(500, 2))
    both = _discretisation.shift(J, d)
    assert both.shape == (5, 2)
    for k in range(2):
        np.testing.assert_allclose(both[:, k], np.linalg.lstsq(J, d[:, k], rcond=None)[0],
                                   rtol=1e-9)
        np.testing.assert_allclose(_discretisation.shift(J, d[:, k]), both[:, k], rtol=1e-12)


def test_the_finer_models_pixels_stand_for_their_strata_within_its_sample_budget(monkeypatch):
    """Every highlight and rim pixel, every BODY_STRIDE-th body pixel; beyond
    MAX_FINER_SAMPLES every s-th of each. Reference: the strata's own sizes
    (each pick's weight is its stratum's pixels per pick, a Horvitz-Thompson
    sum) and the budget."""
    rng = np.random.default_rng(0)
    labels = rng.choice([0, 0, 0, 1, 2], size=20000)
    scene = fitter.Scene(width=256, height=256, supersampling=4)
    per_pixel = _discretisation.finer_supersampling(scene) ** 2
    for budget in (2**30, 20000 * per_pixel // 10):
        monkeypatch.setattr(_discretisation, "MAX_FINER_SAMPLES", budget)
        rows, weight = _discretisation.sample_rows(labels, scene)
        assert np.all(np.diff(rows) > 0)
        for sharp in (False, True):
            mine = (labels[rows] != 0) == sharp
            np.testing.assert_allclose(weight[mine].sum(), np.sum((labels != 0) == sharp))
        if budget == 2**30:
            assert np.array_equal(rows[labels[rows] != 0], np.nonzero(labels != 0)[0])
            stride = _discretisation.BODY_STRIDE
            assert np.sum(labels[rows] == 0) == np.ceil(np.sum(labels == 0) / stride)
        else:
            assert rows.size * per_pixel <= 1.01 * budget


def test_under_a_sky_the_renders_made_ahead_are_the_ones_used(tmp_path, monkeypatch):
    """Under a sky the thread also compiles the renders of its three geometries
    (finer samples, finer sun, half the rings) and of the fitted geometry's sky
    terms; the fit uses those executables: the main thread compiles none."""
    from fitter.imageio import write_image

    img = np.full((16, 32, 3), 0.3)
    img[5, 9] = [3000.0, 2900.0, 2500.0]  # a sun: all three geometries are made
    write_image(str(tmp_path / "sun.exr"), img)
    scene = SCENE.replace(lights=(), environment=fitter.Environment(
        type="envmap", file=str(tmp_path / "sun.exr")))
    target = np.asarray(fitter.render(GLOSSY, scene.replace(supersampling=4)))
    compiled_on = []
    compile_render = _renders.compile_render

    def recorded(args, material, env_type, key, single=False):
        compiled_on.append(threading.current_thread().name)
        return compile_render(args, material, env_type, key, single)

    monkeypatch.setattr(_renders, "compile_render", recorded)
    monkeypatch.setattr(_discretisation, "_GEOMETRIES", {})
    monkeypatch.setattr(_renders, "EXECUTABLES", {})
    res = fitter.fit(target, scene, "lambert+torrance_sparrow")
    assert res.status == "converged"
    assert compiled_on == ["fitter-finer-geometry"] * 4


def test_finer_model_in_float32_states_the_float64_errors(monkeypatch):
    """The finer model rendered in float32 (``_discretisation.SINGLE``, its
    geometry kept in float32) gives stated errors within 1e-3 of float64's
    (its rounding, ~1e-7 of the values and ~3e-8 of the parameters, against a
    discretisation error ~1e-4 of them), the same values and verdict; a
    material with Phong (no ``single_precision``) renders it in float64."""
    target = np.asarray(fitter.render(GLOSSY, SCENE.replace(supersampling=16)))
    target = target + np.random.default_rng(0).normal(0.0, 1e-3, target.shape)
    out = {}
    for single in (False, True):
        monkeypatch.setattr(_discretisation, "SINGLE", single)
        monkeypatch.setattr(_discretisation, "_GEOMETRIES", {})
        out[single] = fitter.fit(target, SCENE, "lambert+torrance_sparrow")
    a, b = out[False], out[True]
    assert a.status == b.status == "converged" and a.warnings == b.warnings
    for key in GLOSSY:
        np.testing.assert_array_equal(a.params[key], b.params[key])
        np.testing.assert_allclose(b.stderr[key], a.stderr[key], rtol=1e-3, err_msg=key)
        assert np.all(np.asarray(b.stderr_disc[key]) > 0)
    phong = fitter.Material.make("lambert+phong")
    assert _discretisation.single(fitter.Material.make("lambert+torrance_sparrow"), False)
    assert not _discretisation.single(phong, False)
    assert not _discretisation.single(fitter.Material.make("lambert+torrance_sparrow"), True)

"""A best fit on the edge of its box (``fitter.fit._edge``): Oren-Nayar's sigma
at 0, where the model's slope in sigma vanishes, so the solver's coordinate
approaches the edge without reaching it and runs out of steps.

Reference: the shipped Mitsuba target ``extreme_sigma0`` (sigma = 0, i.e.
Lambert; 128^2), the model's own render of it, and fits of them with sigma
fixed (``fixed=``), which refit rho_d exactly (nonlinearly), independent of
the edge code's linearised profile.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

import fitter
from fitter import serialize
from fitter.cases import CASES
from fitter.fit import _edge
from fitter.imageio import read_image

pytestmark = pytest.mark.mitsuba

KEY = "oren_nayar.sigma"
#: The linearised profile (rho_d refit to first order) against exact refits:
#: chi^2 at the stated one-sided limit rises by 1 within this (measured +1.000).
PROFILE_RTOL = 0.05


@pytest.fixture(scope="module")
def case():
    name = "extreme_sigma0"
    base = os.path.join(os.path.dirname(__file__), os.pardir, "data_synthetic", name)
    scene = serialize.scene_from_dict(CASES[name]["scene"], name, base_dir=base)
    mat, truth, _, _ = serialize.material_from_dict(CASES[name]["material"], name)
    return read_image(os.path.join(base, "target.exr")), scene, mat, truth, base


def _chi2(res, s2):
    return 2.0 * res.cost / s2


def _model_target():
    """(scene, target): the model's own render of extreme_sigma0's material at
    sigma = 0 (128^2, two lights) plus white noise of 0.002."""
    lights = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
              fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0)))
    scene = fitter.Scene(width=128, height=128, supersampling=4, lights=lights)
    clean = np.asarray(fitter.render({"oren_nayar.rho_d": [0.5, 0.45, 0.4], KEY: 0.0},
                                     scene, "oren_nayar"))
    return scene, clean + np.random.default_rng(0).normal(0.0, 0.002, clean.shape)


def test_a_best_fit_on_the_edge_is_refit_there_and_stated_one_sided(case):
    target, scene, mat, truth, base = case
    res = fitter.fit(target, scene, mat, base_dir=base)
    assert res.status == "converged", res.message
    assert res.params[KEY] == 0.0 and KEY in res.free
    err = np.abs(res.params["oren_nayar.rho_d"] - np.asarray(truth["oren_nayar.rho_d"]))
    assert np.all(err <= 3 * res.stderr["oren_nayar.rho_d"]), (err, res.stderr)
    (why,) = [w for w in res.warnings if w.startswith(f"{KEY} is on the edge of its box, 0")]
    # The one-sided statistical error: half of [0, x1], where chi^2 with rho_d
    # refit rises by 1. Exact refits at sigma = 0 and sigma = x1 agree.
    x1 = 2.0 * res.stderr_stat[KEY]
    at0 = fitter.fit(target, scene, mat, fixed={KEY: 0.0}, base_dir=base)
    at1 = fitter.fit(target, scene, mat, fixed={KEY: x1}, base_dir=base)
    s2 = 2.0 * at0.cost / (3 * at0.n_pixels - 3)
    assert _chi2(at1, s2) - _chi2(at0, s2) == pytest.approx(1.0, rel=PROFILE_RTOL)
    assert res.cost == pytest.approx(at0.cost, rel=1e-9)
    # Its systematic part in the proportion of rho_d's (the largest ratio).
    ratio = np.max(res.stderr_sys["oren_nayar.rho_d"] / res.stderr_stat["oren_nayar.rho_d"])
    assert res.stderr_sys[KEY] == pytest.approx(ratio * res.stderr_stat[KEY])
    assert res.stderr[KEY] == pytest.approx(np.hypot(res.stderr_stat[KEY], res.stderr_sys[KEY]))
    assert ratio > 1 and "one-sided" in why


def test_on_a_target_the_model_made_the_edge_is_stated_from_the_profile():
    """The model's own render at sigma = 0 plus white noise (128^2): the fit runs
    out of steps short of the edge too. The error stated where it stopped was
    0.60 for sigma (its systematic part read the stopping point's misfit as
    structure); on the edge the residual is white, and sigma's stated error is
    the profile's (exact refits: chi^2 +1 at twice its statistical part)."""
    scene, target = _model_target()
    res = fitter.fit(target, scene, "oren_nayar")
    assert res.status == "converged" and res.params[KEY] == 0.0, res.message
    assert res.stderr[KEY] < 2.0 * res.stderr_stat[KEY], (res.stderr, res.stderr_stat)
    at0 = fitter.fit(target, scene, "oren_nayar", fixed={KEY: 0.0})
    at1 = fitter.fit(target, scene, "oren_nayar", fixed={KEY: 2.0 * res.stderr_stat[KEY]})
    s2 = 2.0 * at0.cost / (3 * at0.n_pixels - 3)
    assert _chi2(at1, s2) - _chi2(at0, s2) == pytest.approx(1.0, rel=PROFILE_RTOL)


def test_without_the_edge_refit_the_fit_stops_short_of_the_edge_and_fits_worse(case, monkeypatch):
    """The pinned refit is kept only if it fits at least as well (``EDGE_SLACK``);
    made impossible here, the fit out of steps is returned as it was, with the
    message naming the edge. It stopped inside the box at a higher cost."""
    target, scene, mat, _, base = case
    monkeypatch.setattr(_edge, "EDGE_SLACK", -np.inf)
    stopped = fitter.fit(target, scene, mat, base_dir=base)
    assert stopped.status == "max_steps"
    assert f"{KEY} = " in stopped.message and "of its bound 0" in stopped.message
    assert 0.0 < stopped.params[KEY] < stopped.stderr[KEY]
    monkeypatch.undo()
    pinned = fitter.fit(target, scene, mat, base_dir=base)
    assert pinned.cost < stopped.cost


def test_a_batch_target_out_of_steps_short_of_the_edge_is_refit_alone():
    """``fit_batch`` does not refit inside its shared solve; a target out of
    steps with a value near an edge is fitted alone, as ``fit`` does it."""
    scene, target = _model_target()
    (res,) = fitter.fit_batch(target[None], scene, "oren_nayar")
    alone = fitter.fit(target, scene, "oren_nayar")
    assert res.status == alone.status == "converged" and res.params[KEY] == 0.0
    assert res.stderr[KEY] == pytest.approx(alone.stderr[KEY])

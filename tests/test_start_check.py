"""The start check (parameters whose Jacobian column is zero at the start are
held, ``_drivers._hold_dead_columns``) after a Levenberg-Marquardt solve, made
only where the solution shows a zero column (``_drivers._checked_after``);
before the solve for the undamped solvers. The reference is the same fit with
the check made first (``CHECK_AFTER = ()``), as every fit did before."""

from __future__ import annotations

import numpy as np
import pytest

import fitter
from fitter.fit import _drivers

LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),)
SCENE = fitter.Scene(width=32, height=32, supersampling=2, lights=LIGHTS)
NOISE = 1e-3


def _target(truth, scene=SCENE):
    clean = np.asarray(fitter.render(truth, scene))
    return clean + np.random.default_rng(0).normal(0.0, NOISE, clean.shape)


def _same(a, b):
    assert a.unidentifiable == b.unidentifiable and a.warnings == b.warnings
    for key, value in a.params.items():
        np.testing.assert_array_equal(b.params[key], value)
    for key, value in a.stderr.items():
        np.testing.assert_array_equal(b.stderr[key], value)


ALIVE = {"lambert.rho_d": [0.5, 0.4, 0.3], "phong.rho_s": 0.3, "phong.e": 40.0}


def _without(monkeypatch, name: str, scene=SCENE):
    """Fit ``ALIVE``'s target with ``_drivers.<name>`` raising (it must not run),
    then as every fit did before (the check first); both results."""
    target = _target(ALIVE, scene)

    def forbidden(*args, **kwargs):
        raise AssertionError(f"_drivers.{name} ran")

    with monkeypatch.context() as m:
        m.setattr(_drivers, name, forbidden)
        after = fitter.fit(target, scene, "lambert+phong")
    monkeypatch.setattr(_drivers, "CHECK_AFTER", ())
    return after, fitter.fit(target, scene, "lambert+phong")


def test_a_fit_without_dead_parameters_makes_no_start_jacobian(monkeypatch):
    after, first = _without(monkeypatch, "jac_res")
    assert after.status == "converged" and not after.unidentifiable
    _same(after, first)


def test_a_coarse_start_without_dead_parameters_makes_no_check(monkeypatch):
    """A coarse start (``fit._coarse``) would read the start check's Jacobian
    from a full-size linearisation at the start; with every parameter alive
    at the solution none is made, and the fit is the one checked first."""
    from fitter.fit import _coarse

    scene = SCENE.replace(width=64, height=64)  # 32^2 fell back from its coarse start
    monkeypatch.setattr(_coarse, "MIN_PIXELS", 64 * 64)
    finished = []
    solve = _coarse.solve
    monkeypatch.setattr(_coarse, "solve", lambda *a, **k: finished.append(solve(*a, **k))
                        or finished[-1])
    after, first = _without(monkeypatch, "_hold_dead_columns", scene)
    assert len(finished) == 2 and all(f is not None for f in finished)  # both started coarse
    assert after.status == "converged" and not after.unidentifiable
    _same(after, first)


def test_a_parameter_dead_at_the_start_is_held_as_the_check_first_holds_it(monkeypatch):
    # A mirror in a black environment shows nothing: rho_m's column is zero everywhere.
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3], "mirror.rho_m": 0.8}
    target = _target(truth)
    init = {"lambert.rho_d": 0.3, "mirror.rho_m": 0.5}
    after = fitter.fit(target, SCENE, "lambert+mirror", init=init)
    monkeypatch.setattr(_drivers, "CHECK_AFTER", ())
    first = fitter.fit(target, SCENE, "lambert+mirror", init=init)
    assert after.unidentifiable == ["mirror.rho_m"]
    assert np.all(after.params["mirror.rho_m"] == 0.5)  # held at its start
    assert any("mirror.rho_m" in w and "at the start" in w for w in after.warnings)
    _same(after, first)


def test_every_parameter_dead_fails_without_a_second_solve(monkeypatch):
    # The only light is behind the sphere: no visible pixel depends on the lobe.
    scene = SCENE.replace(lights=(fitter.PointLight((0.0, 0.0, -6.0), (50.0, 50.0, 50.0)),))
    solves = []
    solve_starts = _drivers.solve_starts
    monkeypatch.setattr(_drivers, "solve_starts",
                        lambda *a, **k: solves.append(1) or solve_starts(*a, **k))
    r = fitter.fit(np.zeros((32, 32, 3)), scene, "phong")
    assert len(solves) == 1  # the damped solve, then the check holds everything
    assert r.status == "failed" and set(r.unidentifiable) == {"phong.rho_s", "phong.e"}
    assert all(np.all(np.isfinite(v)) for v in r.params.values())


@pytest.mark.parametrize("solver", ["gauss_newton", "dogleg"])
def test_undamped_solvers_are_checked_before_the_solve(solver, monkeypatch):
    """An undamped step would factor a singular J^T J: the dead parameter is
    held before the solve, which then sees only live ones."""
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3], "mirror.rho_m": 0.8}
    target = _target(truth)
    solved_with = []
    solve_starts = _drivers.solve_starts

    def recorded(problem, *args, **kwargs):
        solved_with.append([b.key for b in problem.blocks])
        return solve_starts(problem, *args, **kwargs)

    monkeypatch.setattr(_drivers, "solve_starts", recorded)
    r = fitter.fit(target, SCENE, "lambert+mirror", solver=solver,
                   init={"lambert.rho_d": 0.3, "mirror.rho_m": 0.5})
    assert solved_with[0] == ["lambert.rho_d"]
    assert r.status == "converged" and r.unidentifiable == ["mirror.rho_m"]
    np.testing.assert_allclose(r.params["lambert.rho_d"], truth["lambert.rho_d"], atol=5 * NOISE)

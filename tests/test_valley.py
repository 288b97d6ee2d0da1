"""The solver's coordinates along a conductor's circles of equal F0
(``fitter.fit._valley``): references from the Fresnel equations at normal
incidence, F0 = ((eta - 1)^2 + k^2) / ((eta + 1)^2 + k^2)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import fitter
from fitter import transforms
from fitter.bsdf.registry import LOBES
from fitter.fit import _setup, _valley

ETA_BOX, K_BOX = (1e-2, 10.0), (1e-3, 20.0)
CHART = _valley.Chart(slice(0, 3), slice(3, 6), ETA_BOX, K_BOX)
#: A point moved off an interval's edge (``_valley.EDGE``) moves k near its least
#: value by up to this, relative (the interval of the angle is wide there).
EDGE_MOVE = 0.05


def _f0(n, k):
    return ((n - 1) ** 2 + k**2) / ((n + 1) ** 2 + k**2)


def _z(n, k):
    return jnp.asarray(np.concatenate([transforms.to_unconstrained("log", n, *ETA_BOX),
                                       transforms.to_unconstrained("log", k, *K_BOX)]))


def _user(z):
    z = np.asarray(z)
    return (transforms.to_user("log", z[:3], *ETA_BOX), transforms.to_user("log", z[3:], *K_BOX))


def test_a_conductor_fit_has_one_chart_and_a_dielectric_none():
    scene = fitter.Scene(width=8, height=8, supersampling=1,
                         lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),))
    target = np.full((1, 8, 8, 3), 0.1)
    conductor = _setup.Problem.make(target, scene, "torrance_sparrow",
                                    fixed={"torrance_sparrow.fresnel": "conductor"})
    (c,) = _valley.charts(conductor.spec)
    assert (c.real_box, c.imag_box) == (ETA_BOX, K_BOX)
    assert _valley.charts(_setup.Problem.make(target, scene, "torrance_sparrow").spec) == ()
    held_k = _setup.Problem.make(target, scene, "torrance_sparrow", fixed={
        "torrance_sparrow.fresnel": "conductor", "torrance_sparrow.k": 3.0})
    assert _valley.charts(held_k.spec) == ()  # eta alone: no valley
    assert LOBES["torrance_sparrow"].complex_index({"fresnel": "conductor"}) == ("eta", "k")


@settings(max_examples=60, deadline=None)
@given(n=st.lists(st.floats(np.log(ETA_BOX[0]), np.log(ETA_BOX[1])), min_size=3, max_size=3),
       k=st.lists(st.floats(np.log(K_BOX[0]), np.log(K_BOX[1])), min_size=3, max_size=3))
def test_the_coordinates_go_back_to_the_same_eta_and_k(n, k):
    n, k = np.exp(n), np.exp(k)
    # (F0 below 1e-4, eta ~ 1 and k ~ 0, nothing reflected: there F0's own interval
    # edge, EDGE of F0's range, is a large relative move)
    assume(np.all(_f0(n, k) > 1e-4))
    back_n, back_k = _user(_valley.to_z(_valley.to_w(_z(n, k), (CHART,)), (CHART,)))
    tol = 1e-6 + EDGE_MOVE * (k < 2 * K_BOX[0])
    assert np.all(np.abs(back_n / n - 1) <= tol) and np.all(np.abs(back_k / k - 1) <= tol), (
        n, k, back_n, back_k)


def test_gold_goes_back_exactly_and_the_angle_keeps_f0():
    n, k = np.array([0.143, 0.3753, 1.442]), np.array([3.983, 2.3856, 1.6034])
    w = _valley.to_w(_z(n, k), (CHART,))
    back = _user(_valley.to_z(w, (CHART,)))
    np.testing.assert_allclose(back[0], n, rtol=1e-9)
    np.testing.assert_allclose(back[1], k, rtol=1e-9)
    for shift in (-3.0, -0.5, 0.7, 4.0):  # along the angle: another (eta, k) of the same F0
        n2, k2 = _user(_valley.to_z(w.at[3:].add(shift), (CHART,)))
        np.testing.assert_allclose(_f0(n2, k2), _f0(n, k), rtol=1e-9)
        assert np.all(np.abs(n2 - n) > 1e-4)
        assert np.all((n2 >= ETA_BOX[0]) & (n2 <= ETA_BOX[1]))
        assert np.all((k2 >= K_BOX[0]) & (k2 <= K_BOX[1]))


@settings(max_examples=40, deadline=None)
@given(w=st.lists(st.floats(-40.0, 40.0), min_size=6, max_size=6))
def test_every_solver_point_is_inside_the_boxes_with_a_finite_jacobian(w):
    w = jnp.asarray(w)
    z = _valley.to_z(w, (CHART,))
    n, k = _user(z)
    assert np.all(np.isfinite(np.asarray(z)))
    assert np.all((n >= ETA_BOX[0] * (1 - 1e-9)) & (n <= ETA_BOX[1] * (1 + 1e-9)))
    assert np.all((k >= K_BOX[0] * (1 - 1e-9)) & (k <= K_BOX[1] * (1 + 1e-9)))
    assert np.all(np.isfinite(np.asarray(jax.jacfwd(lambda v: _valley.to_z(v, (CHART,)))(w))))


def test_narrowed_boxes_whose_arcs_split_keep_the_fits_coordinates():
    # With k <= 1 and eta in [0.05, 5] the arc of one F0 leaves the boxes in its
    # middle (k over 1) and comes back: two pieces, of which the solver's angle
    # would reach one (42 % of random points there did not come back). Such
    # bounds keep the fit's own coordinates; bounds whose arcs stay whole use the
    # angle, and their points come back.
    scene = fitter.Scene(width=8, height=8, supersampling=1,
                         lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),))
    target = np.full((1, 8, 8, 3), 0.1)
    fixed = {"torrance_sparrow.fresnel": "conductor"}

    def charts(eta, k):
        return _valley.charts(_setup.Problem.make(
            target, scene, "torrance_sparrow", fixed=fixed,
            init={"torrance_sparrow.eta": np.sqrt(eta[0] * eta[1]),
                  "torrance_sparrow.k": np.sqrt(k[0] * k[1])},
            bounds={"torrance_sparrow.eta": eta, "torrance_sparrow.k": k}).spec)

    assert charts((0.05, 5.0), (0.01, 1.0)) == ()
    (c,) = charts((0.1, 0.9), (1.0, 4.0))
    assert (c.real_box, c.imag_box) == ((0.1, 0.9), (1.0, 4.0))
    c = c._replace(real=slice(0, 3), imag=slice(3, 6))  # (m is the spec's first coordinate)
    rng = np.random.default_rng(0)
    for _ in range(50):
        n, k = (np.exp(rng.uniform(np.log(lo) + 0.01, np.log(hi) - 0.01, 3))
                for lo, hi in (c.real_box, c.imag_box))
        z = jnp.asarray(np.concatenate([transforms.to_unconstrained("log", n, *c.real_box),
                                        transforms.to_unconstrained("log", k, *c.imag_box)]))
        back = np.asarray(_valley.to_z(_valley.to_w(z, (c,)), (c,)))
        np.testing.assert_allclose(back, np.asarray(z), rtol=1e-6, atol=1e-9)


def test_a_float32_conductor_fit_converges_in_the_fits_own_coordinates():
    # The circle's centre and radius cancel to a small eta (gold's red: 34.7 - 34.5),
    # which float32 does not resolve: its Jacobian went NaN and the glint check raised
    # (a traceback). float32 fits keep the fit's coordinates; F0 from the Fresnel
    # equations at normal incidence.
    scene = fitter.Scene(width=24, height=24, supersampling=2,
                         lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
                                 fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0))))
    fixed = {"torrance_sparrow.fresnel": "conductor", "torrance_sparrow.geometry": "smith"}
    n, k = np.array([0.143, 0.3753, 1.442]), np.array([3.983, 2.3856, 1.6034])
    clean = np.asarray(fitter.render({"torrance_sparrow.m": 0.25, "torrance_sparrow.eta": n,
                                      "torrance_sparrow.k": k, **fixed}, scene))
    target = clean + np.random.default_rng(0).normal(0.0, 1e-3, clean.shape)
    r = fitter.fit(target, scene, "torrance_sparrow", fixed=fixed, dtype="float32")
    assert r.status == "converged", r.message
    f0 = _f0(np.asarray(r.params["torrance_sparrow.eta"]),
             np.asarray(r.params["torrance_sparrow.k"]))
    np.testing.assert_allclose(f0, _f0(n, k), atol=0.005)


def test_the_fits_coordinates_of_jax_values_are_numpys():
    # ``transforms.to_unconstrained`` serves the solver's map in JAX (traced,
    # differentiable) and the fit's set-up in NumPy: the same coordinates.
    for kind, box, x in (("log", ETA_BOX, [0.011, 0.5, 9.9]),
                         ("box", (0.2, 0.9), [0.21, 0.5, 0.89])):
        x = np.array(x)
        z = transforms.to_unconstrained(kind, jnp.asarray(x), *box)
        np.testing.assert_allclose(np.asarray(z), transforms.to_unconstrained(kind, x, *box),
                                   rtol=1e-12)
        np.testing.assert_allclose(np.asarray(transforms.to_user(kind, z, *box)), x, rtol=1e-12)
        g = jax.grad(lambda v: jnp.sum(transforms.to_unconstrained(kind, v, *box)))(jnp.asarray(x))
        assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g) > 0)

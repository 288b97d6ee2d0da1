"""The dielectric fit's shortcuts: the start search, the bounce count, the
derivatives by hand (issue 16, item 4).

* eta near 1 (1.001, 1.02) is recovered from the lobe's default start (eta
  1.5, attenuation 1). Targets are rendered by the JAX model itself (an
  inverse crime: this checks the search and the solver, not the physics) in
  the shipped envmap, 48^2 with 2x2 samples.
* The bounce count a fit chooses leaves out less than its tolerance in every
  pixel. Reference: the closed-form remainder of the geometric series of
  Fresnel reflectances, (1 - F)^2 T (F T)^(K+1) / (1 - F T), with F from the
  Fresnel equations written out here and T = c^(2 R cos theta_t); and the
  renderer's own image at 64 bounces.
* The hand-written derivatives equal autodiff's, and stay finite as eta -> 1
  and at the attenuation's box edges.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import fresnel_reference

import fitter
from fitter.bsdf import LOBES
from fitter.bsdf.base import SurfaceHit
from fitter.environment import EnvData, lookup
from fitter.fit._search import TRUNCATION_NOISE_FRACTION, cheapened
from fitter.fit._setup import Problem
from fitter.imageio import read_image

ENVMAP = os.path.join(os.path.dirname(__file__), os.pardir, "data_synthetic", "envmap.exr")
ATT = [0.9, 0.7, 0.5]
SCENE = fitter.Scene(width=48, height=48, supersampling=2,
                     environment=fitter.Environment("envmap", file=ENVMAP))


@pytest.mark.parametrize("eta", [1.001, 1.02])
def test_eta_near_one_is_found_from_the_default_start(eta):
    truth = {"dielectric.eta": eta, "dielectric.attenuation": ATT}
    target = np.asarray(fitter.render(truth, SCENE))
    result = fitter.fit(target, SCENE, "dielectric")  # start: eta 1.5, attenuation 1
    assert result.status == "converged", result.message
    # Noise-free target: the solver's tolerance, not the 0.005 of the Mitsuba cases.
    assert abs(result.params["dielectric.eta"] - eta) < 1e-6
    np.testing.assert_allclose(result.params["dielectric.attenuation"], ATT, atol=1e-5)


def _remainder(cos_i, eta, att, radius, k):
    """Weight of the paths after exit k, sum_{j > k} (1 - F)^2 F^j T^(j+1)."""
    cos_i = np.clip(cos_i, 1e-12, 1.0)
    f = fresnel_reference(cos_i, eta)  # textbook form, from outside (eta >= 1)
    cos_t = np.sqrt(1.0 - (1.0 - cos_i ** 2) / eta ** 2)
    t = np.asarray(att)[None, :] ** (2.0 * radius * cos_t)[:, None]
    f = f[:, None]
    return (1.0 - f) ** 2 * t * (f * t) ** (k + 1) / (1.0 - f * t)


@pytest.mark.parametrize("att", [[0.5, 0.3, 0.2], [0.3, 0.2, 0.1]])
def test_chosen_bounces_leave_out_less_than_the_tolerance(att):
    eta, sigma = 1.5, 2e-3
    truth = {"dielectric.eta": eta, "dielectric.attenuation": att}
    target = np.asarray(fitter.render(truth, SCENE))
    problem = Problem.make(target[None], SCENE, "dielectric", init=truth, noise_sigma=sigma)
    chosen = cheapened(problem).material.options_of("dielectric")["bounces"]
    tol = TRUNCATION_NOISE_FRACTION * sigma
    env_max = read_image(ENVMAP).reshape(-1, 3).max(axis=0)

    # The bound, from the closed form, over the fitted pixels' samples.
    geo = problem.geometry
    d, n = np.asarray(geo.ray_dir), np.asarray(geo.normal)
    hit, w = np.asarray(geo.hit), np.asarray(geo.sample_weight)
    cos_i = np.clip(-np.sum(d * n, axis=-1), 0.0, 1.0)

    def worst(k, eta, att):
        rem = _remainder(cos_i.reshape(-1), eta, att, 1.0, k).reshape(cos_i.shape + (3,))
        return (np.einsum("pkc,pk->pc", rem, hit * w) * env_max).max(axis=0)

    assert 0 < chosen < 8, chosen  # a real saving over the default 8
    # At the start point, and with the margins the fit adds (eta - 1 larger by
    # 1.2, half the absorption), where the count is the least that suffices.
    assert np.all(worst(chosen, eta, att) <= tol)
    margined = (1.0 + 1.2 * (eta - 1.0), np.sqrt(att))
    assert np.all(worst(chosen, *margined) <= tol)
    assert np.any(worst(chosen - 1, *margined) > tol)

    # The renderer's image: what the chosen count drops is within the bound.
    full = np.asarray(fitter.render({**truth, "dielectric.bounces": 64}, SCENE))
    cut = np.asarray(fitter.render({**truth, "dielectric.bounces": chosen}, SCENE))
    inside = np.zeros(SCENE.width * SCENE.height, bool)
    inside[problem.renderer.pixel_index[problem.rows]] = True
    dropped = (full - cut).reshape(-1, 3)[inside]
    assert np.all(dropped >= -1e-15) and np.all(dropped.max(axis=0) <= tol)


def test_bounces_stay_at_the_cap_for_a_noise_free_target():
    """An inverse-crime target has (almost) no noise: nothing may be cut."""
    truth = {"dielectric.eta": 1.5, "dielectric.attenuation": ATT}
    target = np.asarray(fitter.render(truth, SCENE))
    problem = Problem.make(target[None], SCENE, "dielectric", init=truth, noise_sigma=1e-9)
    assert cheapened(problem).material.options_of("dielectric")["bounces"] == 8


def _hit_and_env(seed=0, n=60):
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    d = -normal + 0.7 * rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    keep = np.sum(d * normal, -1) < 0
    hit = SurfaceHit(jnp.asarray(normal[keep]), jnp.asarray(normal[keep]),
                     jnp.asarray(d[keep]), jnp.zeros(3), jnp.asarray(1.0))
    data = EnvData(jnp.asarray(read_image(ENVMAP), dtype=jnp.float64), jnp.zeros(3))
    return hit, (lambda v: lookup("envmap", data, v))


@pytest.mark.parametrize("eta", [1.0, 1.0 + 1e-9, 1.001, 1.5, 4.0])
def test_radiance_grad_matches_autodiff(eta):
    lobe = LOBES["dielectric"]
    hit, env = _hit_and_env()
    p = {"eta": jnp.asarray(eta), "attenuation": jnp.asarray([0.95, 0.4, 0.05])}
    opts = {"bounces": 8}
    value, grads = jax.jit(lambda p: lobe.radiance_grad(p, opts, hit, env))(p)
    jac = jax.jit(jax.jacfwd(lambda p: lobe.radiance(p, opts, hit, env)))(p)
    # jit against eager: rounding only
    np.testing.assert_allclose(value, lobe.radiance(p, opts, hit, env), rtol=1e-12)
    scale = float(np.abs(jac["eta"]).max()) or 1.0
    np.testing.assert_allclose(grads["eta"], jac["eta"], rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(grads["attenuation"],
                               np.diagonal(jac["attenuation"], axis1=-2, axis2=-1),
                               rtol=1e-10, atol=1e-14)


def test_envmap_lookup_derivative_matches_differences():
    """The lookup's hand-written direction derivative against central differences."""
    hit, env = _hit_and_env(seed=3)
    v = hit.ray_dir
    dv = jnp.asarray(np.random.default_rng(4).normal(size=v.shape))
    _, tangent = jax.jvp(env, (v,), (dv,))
    h = 1e-6
    fd = (env(v + h * dv) - env(v - h * dv)) / (2 * h)
    # Bilinear: a difference straddling a texel edge differs; those are few.
    close = np.isclose(np.asarray(tangent), np.asarray(fd), rtol=1e-5, atol=1e-6)
    assert close.mean() > 0.95


@pytest.mark.parametrize("eta", [1.0, 1.0 + 1e-12, 1.0 + 1e-8, 1.0 + 1e-4, 1.001, 1.02])
@pytest.mark.parametrize("att", [0.0, 1e-6, 0.5, 1.0])
def test_fit_jacobian_finite_near_eta_one(eta, att):
    """The renderer's Jacobian (the fitter's forward mode) is finite on a grid
    reaching eta = 1 and the attenuation's box edges."""
    scene = SCENE.replace(width=16, height=16)
    rend = fitter.Renderer(scene, fitter.Material.make(["dielectric"]))
    p = {"dielectric.eta": jnp.asarray(eta), "dielectric.attenuation": jnp.full(3, att)}
    jac = jax.jacfwd(lambda q: rend.active(q))(p)
    for key, j in jac.items():
        assert np.all(np.isfinite(np.asarray(j))), key


def test_fewer_bounces_keep_a_free_exposure():
    # The cheaper material must still scale by the exposure: without it the
    # "exposure" parameter stays free with a zero Jacobian column.
    truth = {"dielectric.eta": 1.5, "dielectric.attenuation": [0.3, 0.2, 0.1]}
    target = np.asarray(fitter.render(truth, SCENE))
    problem = Problem.make(target[None], SCENE, "dielectric", init={**truth, "exposure": 1.0},
                           noise_sigma=2e-3)
    assert problem.material.exposure
    cheaper = cheapened(problem).material
    assert cheaper.options_of("dielectric")["bounces"] < 8
    assert cheaper.exposure


def _searched_problem(scene, truth):
    from fitter.fit._search import searched

    target = np.asarray(fitter.render(truth, scene))
    return searched(Problem.make(target[None], scene, "dielectric")), target


def test_the_start_search_spares_the_start_check_for_what_it_saw_change(monkeypatch):
    """Under the envmap every parameter changes the search's cost: the start
    check (a Jacobian at the start) is not made, and the fit is the one the
    check would have given."""
    from fitter.fit import _drivers, _search

    truth = {"dielectric.eta": 1.5, "dielectric.attenuation": ATT}
    problem, target = _searched_problem(SCENE, truth)
    assert problem.alive == {"dielectric.eta", "dielectric.attenuation"}

    def no_jacobian(*args, **kwargs):
        raise AssertionError("the start check made a Jacobian")

    with monkeypatch.context() as m:
        m.setattr(_drivers, "jac_res", no_jacobian)
        assert _drivers._hold_dead_columns(problem) == (problem, 0.0)
        skipped = fitter.fit(target, SCENE, "dielectric")
    monkeypatch.setattr(_search, "SEEN_CHANGE", np.inf)  # nothing seen: the check runs
    checked = fitter.fit(target, SCENE, "dielectric")
    for key, value in checked.params.items():
        np.testing.assert_array_equal(skipped.params[key], value)
        np.testing.assert_array_equal(skipped.stderr[key], checked.stderr[key])


def test_a_channel_the_pixels_do_not_see_is_still_checked_and_held():
    """A constant environment without blue: the blue attenuation changes no
    pixel, so the search's spread for it is 0, the start check runs and holds
    the attenuation (a block is held whole), as it did before the search
    spared anything."""
    from fitter.fit import _drivers

    scene = fitter.Scene(width=48, height=48, supersampling=2,
                         environment=fitter.Environment("constant", radiance=(1.0, 0.5, 0.0)))
    truth = {"dielectric.eta": 1.5, "dielectric.attenuation": ATT}
    problem, _ = _searched_problem(scene, truth)
    assert problem.alive == {"dielectric.eta"}
    held, _ = _drivers._hold_dead_columns(problem)
    assert [b.key for b in held.blocks] == ["dielectric.eta"]
    assert held.unidentifiable == ("dielectric.attenuation",)

"""Reverse-mode gradients of a rendered image against central finite differences.

For every parameter (every RGB component) of every lobe, at an interior
point of its box: d/dp of S = sum(w * image) by ``jax.grad`` against
(S(p + h) - S(p - h)) / 2h in float64. The central difference has truncation
error O(h^2 S''') and rounding error ~ eps S / h; with h = 1e-6 (relative)
both are < 1e-8 of the derivative's scale, far inside ``RTOL``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitter

#: Relative agreement of jax.grad and the central difference.
RTOL = 1e-6
#: Relative finite-difference step.
STEP = 1e-6

SCENE = fitter.Scene(
    width=16, height=14, supersampling=2,
    lights=(fitter.PointLight((2.0, 3.0, 4.0), (30.0, 25.0, 20.0)),
            fitter.DirectionalLight((0.3, -0.5, -1.0), (1.0, 1.5, 2.0))),
    environment=fitter.Environment(type="constant", radiance=(1.0, 0.8, 0.6)))

CASES = {
    "lambert": ({}, {"lambert.rho_d": [0.6, 0.4, 0.2]}),
    "oren_nayar": ({}, {"oren_nayar.rho_d": [0.5, 0.6, 0.7], "oren_nayar.sigma": 0.4}),
    "phong-lecture": ({"phong.normalized": False}, {"phong.rho_s": [0.3, 0.4, 0.5],
                                                    "phong.e": 25.0}),
    "phong-normalized": ({"phong.normalized": True}, {"phong.rho_s": [0.3, 0.4, 0.5],
                                                      "phong.e": 25.0}),
    "torrance_sparrow-v_groove": ({"torrance_sparrow.geometry": "v_groove"},
                                  {"torrance_sparrow.m": 0.25, "torrance_sparrow.eta": 1.6,
                                   "torrance_sparrow.rho_s": 0.8}),
    "torrance_sparrow-smith": ({"torrance_sparrow.geometry": "smith"},
                               {"torrance_sparrow.m": 0.25, "torrance_sparrow.eta": 1.6,
                                "torrance_sparrow.rho_s": 0.8}),
    "mirror": ({}, {"mirror.rho_m": [0.9, 0.5, 0.7]}),
    "dielectric": ({}, {"dielectric.eta": 1.45, "dielectric.attenuation": [0.6, 0.7, 0.8]}),
}


@functools.lru_cache(maxsize=None)
def _functions(case):
    opts, params = CASES[case]
    lobes = sorted({k.split(".")[0] for k in params})
    renderer = fitter.Renderer(SCENE, fitter.Material.make(lobes, opts))
    w = jnp.asarray(np.random.default_rng(7).uniform(0.2, 1.0, (renderer.n_active, 3)))
    scalar = jax.jit(lambda p: jnp.sum(renderer.active(p) * w))
    return scalar, jax.jit(jax.grad(scalar)), jax.jit(jax.jacfwd(scalar))


@pytest.mark.parametrize("case", CASES)
def test_gradient_matches_central_differences(case):
    scalar, grad, jac_fwd = _functions(case)
    p0 = {k: np.asarray(v, dtype=np.float64) for k, v in CASES[case][1].items()}
    g = grad({k: jnp.asarray(v) for k, v in p0.items()})
    g_fwd = jac_fwd({k: jnp.asarray(v) for k, v in p0.items()})  # the fitter's mode
    worst = 0.0
    for key, value in p0.items():
        got = np.atleast_1d(np.asarray(g[key]))
        np.testing.assert_allclose(np.atleast_1d(np.asarray(g_fwd[key])), got, rtol=1e-12)
        flat = np.atleast_1d(value)
        assert np.all(got != 0.0), key  # every parameter moves this image
        for i in range(flat.size):
            h = STEP * max(abs(flat[i]), 1e-3)
            up, down = flat.copy(), flat.copy()
            up[i] += h
            down[i] -= h
            shape = np.shape(value)
            f_up = float(scalar({**p0, key: jnp.asarray(up.reshape(shape))}))
            f_dn = float(scalar({**p0, key: jnp.asarray(down.reshape(shape))}))
            fd = (f_up - f_dn) / (2 * h)
            assert abs(got[i] - fd) <= RTOL * abs(fd), (key, i, got[i], fd)
            worst = max(worst, abs(got[i] - fd) / abs(fd))
    print(f"{case}: max |grad - fd| / |fd| = {worst:.1e}")

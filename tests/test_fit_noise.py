"""Statistical efficiency and honest uncertainties under Gaussian pixel noise.

Reference: the Cramer-Rao bound sigma^2 (J^T J)^-1 at the truth, with J the
Jacobian of the interior pixels w.r.t. the user parameters computed here
directly from ``fitter.render`` (independent of the fitter's transforms and
covariance code). Least squares is the ML estimator for Gaussian noise, so its
RMSE should reach the bound, and +-1 sigma intervals should cover the truth
in ~68 % of draws.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitter

#: Number of independent noise draws (the issue asks for >= 50; 300 makes the
#: coverage band below about 3 binomial standard deviations wide).
N_DRAWS = 300
#: Pixel noise standard deviation (image values are ~0.05-0.6).
SIGMA = 0.01
#: Empirical RMSE / CRLB must not exceed this (project target 1.25).
MAX_EFFICIENCY_RATIO = 1.25
#: Coverage of +-1 sigma intervals, required band (nominal 68.3 %).
COVERAGE = (0.60, 0.76)

#: 4 x 4 samples (the product's default): the stated error includes the model's
#: discretisation (k vs 2k, ``fitter.fit._discretisation``), which the fitter
#: cannot tell is absent from a target the model made; at 2 x 2 on 32^2 it is
#: 0.65 of the noise's error for rho_d (mean stated error 1.19x the bound,
#: measured), at 4 x 4 1.01-1.03x.
SCENE = fitter.Scene(width=32, height=32, supersampling=4, lights=(
    fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
    fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0))))
LOBES = "lambert+torrance_sparrow"
TRUTH = {"lambert.rho_d": np.array([0.6, 0.4, 0.2]), "torrance_sparrow.m": 0.15,
         "torrance_sparrow.eta": 1.5}
KEYS = ["lambert.rho_d[0]", "lambert.rho_d[1]", "lambert.rho_d[2]",
        "torrance_sparrow.m", "torrance_sparrow.eta"]


def flat(params):
    return np.concatenate([np.atleast_1d(np.asarray(params[k], dtype=float)) for k in TRUTH])


def crlb(interior):
    """sqrt(diag(sigma^2 (J^T J)^-1)) at the truth, user units, in KEYS order."""

    def image(x):
        p = {"lambert.rho_d": x[:3], "torrance_sparrow.m": x[3], "torrance_sparrow.eta": x[4]}
        return fitter.render(p, SCENE).reshape(-1, 3)[interior].reshape(-1)

    J = np.asarray(jax.jacfwd(image)(jnp.asarray(flat(TRUTH))))
    return SIGMA * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))


@pytest.mark.slow
def test_noisy_recovery_reaches_cramer_rao_with_honest_errors(capsys):
    clean = np.asarray(fitter.render(TRUTH, SCENE))
    renderer = fitter.Renderer(SCENE, fitter.Material.make(LOBES))
    interior = renderer.pixel_index[np.asarray(renderer.geometry.hit).all(axis=1)]
    bound = crlb(interior)
    init = {k: np.asarray(v) * 1.3 for k, v in TRUTH.items()}
    rng = np.random.default_rng(20261123)
    errors, stderrs = [], []
    for _ in range(N_DRAWS):
        target = clean + rng.normal(0.0, SIGMA, clean.shape)
        r = fitter.fit(target, SCENE, LOBES, init=init, noise_sigma=SIGMA)
        assert r.status == "converged", r.message
        errors.append(flat(r.params) - flat(TRUTH))
        stderrs.append(flat(r.stderr))
    errors, stderrs = np.array(errors), np.array(stderrs)
    rmse = np.sqrt(np.mean(errors**2, axis=0))
    ratio = rmse / bound
    coverage = np.mean(np.abs(errors) <= stderrs, axis=0)
    with capsys.disabled():
        print(f"\nnoisy recovery, {N_DRAWS} draws, sigma = {SIGMA}")
        for k, b, e, c, s in zip(KEYS, bound, ratio, coverage, stderrs.mean(0)):
            print(f"  {k:24s} CRLB {b:.3e}  RMSE/CRLB {e:.3f}  mean stderr/CRLB {s / b:.3f}"
                  f"  1-sigma coverage {c:.1%}")
    assert np.all(ratio <= MAX_EFFICIENCY_RATIO), dict(zip(KEYS, ratio))
    assert np.all((coverage >= COVERAGE[0]) & (coverage <= COVERAGE[1])), dict(zip(KEYS, coverage))
    # The reported errors are the bound itself evaluated at the estimate.
    np.testing.assert_allclose(stderrs.mean(0), bound, rtol=0.05)

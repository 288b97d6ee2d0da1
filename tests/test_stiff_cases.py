"""Stiff and extreme cases (the fast subset of ``benchmarks/stiff.py``, 24 x 24 images).

Every case must give finite parameters, loss gradients (at the truth, the
start and the solution) and covariance, and must never be a confident wrong
answer (status converged, |error| > 5 reported stderr and > tolerance; see
``stiff.classify``). Beyond that, the physics says which outcome to expect:

* recovered: every parameter changes the image by much more than the noise
  (sigma = 1e-3 on values 0.05-1), the truth is inside the box;
* reported (not converged / unidentifiable / error within its stated
  uncertainty): the image does not determine a parameter -- eta = 1 or
  1.001 makes the Fresnel factor (and the whole specular lobe) vanish
  (F(0) = ((eta-1)/(eta+1))^2 = 2.5e-7 at 1.001), so m is not determined;
  lights behind the sphere leave the highlight unseen; a target clipped at
  its 90 % quantile that the fit is not told about cannot be explained by
  the model (chi^2/dof check);
* either: the truth sits on the edge of the box (eta = 4, e = 1e4), where
  the fitted coordinate runs to infinity.

The whole table (and float32) is swept by ``fitter bench``.
"""

from __future__ import annotations

import os
import sys

import jax.numpy as jnp
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(__file__)), "benchmarks"))
import stiff  # noqa: E402

SIZE = 24
RECOVERED = {"m=0.01", "m=0.05", "e=1", "e=1000", "eta=1.02", "eta=2.5", "rho_d=0", "rho_d=1",
             "light at 89.9 deg", "10% saturated, masked", "SNR 5", "far start m x10",
             "far start e /10"}
REPORTED = {"eta=1.0", "eta=1.001", "lights behind", "10% saturated, unmasked"}
FAST = [c for c in stiff.cases() if c.fast]


@pytest.fixture(scope="module")
def outcomes():
    return {c.name: stiff.run_case(c, SIZE) for c in FAST}


def test_table_covers_expectations():
    names = {c.name for c in FAST}
    assert RECOVERED <= names and REPORTED <= names
    assert not RECOVERED & REPORTED


@pytest.mark.parametrize("name", [c.name for c in FAST])
def test_finite_and_never_confidently_wrong(outcomes, name):
    row = outcomes[name]
    assert all(row["gradients_finite"]), row
    assert row["outcome"] in ("recovered", "reported"), row


@pytest.mark.parametrize("name", sorted(RECOVERED))
def test_identifiable_cases_are_recovered(outcomes, name):
    row = outcomes[name]
    assert row["outcome"] == "recovered", row


@pytest.mark.parametrize("name", sorted(REPORTED))
def test_unidentifiable_cases_are_reported(outcomes, name):
    row = outcomes[name]
    assert row["outcome"] == "reported", row


def test_float32_reflectance_at_its_bound_is_reported_not_raised():
    case = next(c for c in FAST if c.name == "rho_d=1")
    row = stiff.run_case(case, SIZE, jnp.float32)
    assert row["outcome"] in ("recovered", "reported"), row

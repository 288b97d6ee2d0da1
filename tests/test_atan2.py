"""``fitter._math.atan2`` (the envmap's and the sky table's direction angles)
against libm's ``atan2`` through NumPy, evaluated in float64 (the reference,
independent of the rational approximation), in float64 and float32."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra import numpy as hnp

from fitter._math import atan2

#: Largest error in units in the last place of the result's dtype (libm's own
#: float32 atan2 was measured at 1.44 ulp against the float64 reference).
MAX_ULP = 2.0

_atan2 = jax.jit(atan2)


def ulp_error(y, x, dtype):
    got = np.asarray(_atan2(jnp.asarray(y, dtype), jnp.asarray(x, dtype)), np.float64)
    ref = np.arctan2(np.asarray(y, dtype).astype(np.float64), np.asarray(x, dtype).astype(np.float64))
    return np.abs(got - ref) / np.spacing(np.abs(ref).astype(dtype)).astype(np.float64)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_within_two_ulp_on_every_octant(dtype):
    rng = np.random.default_rng(3)
    y, x = rng.normal(size=(2, 200_000)) * rng.choice([1e-6, 1.0, 1e6], size=(2, 200_000))
    # the octant edges: |y| = |x|, t = 0.66 (the reduction's switch), the axes
    edges = np.concatenate([np.ones(4), np.full(4, 0.66), np.full(4, 1 / 0.66), np.zeros(4)])
    sign = np.tile([1.0, -1.0, 1.0, -1.0], 4)
    y = np.concatenate([y, edges * sign, sign])
    x = np.concatenate([x, np.roll(sign, 1), edges * np.roll(sign, 1)])
    assert ulp_error(y, x, dtype).max() <= MAX_ULP


@settings(max_examples=50, deadline=None)
@given(hnp.arrays(np.float64, 64, elements=st.floats(-1e6, 1e6, allow_subnormal=False)),
       hnp.arrays(np.float64, 64, elements=st.floats(-1e6, 1e6, allow_subnormal=False)))
def test_within_two_ulp_anywhere(y, x):
    # XLA's CPU flushes subnormal numbers to zero: results below the normal
    # range (and zeros, checked below) are left out.
    normal = np.abs(np.arctan2(y, x)) >= np.finfo(np.float64).tiny * 2.0**53
    assert ulp_error(y[normal], x[normal], np.float64).max(initial=0.0) <= MAX_ULP


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_signed_zeros_and_axes_as_libm(dtype):
    z = 0.0
    y = np.array([z, -z, z, -z, 1.0, -1.0, z, -z, 1e-30, -1e-30], dtype)
    x = np.array([z, z, -z, -z, z, -z, -2.0, -2.0, -1.0, -1.0], dtype)
    got = np.asarray(_atan2(jnp.asarray(y), jnp.asarray(x)))
    ref = np.arctan2(y, x)
    np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(np.signbit(got), np.signbit(ref))

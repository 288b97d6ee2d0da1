"""Maps between user parameters and the solver's unconstrained coordinates.

Every parameter is fitted in a coordinate z in R that is O(1) over its range,
so Levenberg-Marquardt's damping lambda*I (not scale invariant) treats all
parameters alike and no step can leave the valid box:

* ``logit`` / ``box`` / ``eta``: x = lo + (hi - lo) sigmoid(z), for bounded
  parameters (reflectances, sigma, eta in [1, 4]; eta = 1 is the limit
  z -> -inf, approached without NaN);
* ``log``: log x = log lo + (log hi - log lo) sigmoid(z), for positive scales
  spanning decades (Beckmann m, Phong e).

The box edges themselves are limits, so ``to_unconstrained`` nudges values
on an edge inside by ``EDGE`` of the range.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

#: Fraction of the range by which a start on the box edge is moved inside.
EDGE = 1e-6

TRANSFORMS = ("logit", "box", "eta", "log")


def _is_log(kind: str) -> bool:
    if kind not in TRANSFORMS:
        raise ValueError(f"unknown transform {kind!r}; known: {TRANSFORMS}")
    return kind == "log"


def _sigmoid(z):
    if isinstance(z, np.ndarray):  # NumPy in, NumPy out: no JAX dispatch for diagnostics
        # scipy.special.expit's stable form, without importing scipy (0.1 s)
        e = np.exp(-np.abs(z))
        return np.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e)), np
    return jax.nn.sigmoid(z), jnp


def to_user(kind: str, z, lo: float, hi: float):
    """User value x(z) (JAX and differentiable for JAX input; NumPy for NumPy input)."""
    s, xp = _sigmoid(z)
    lo, hi = float(lo), float(hi)  # Python floats stay weakly typed: float32 z stays float32
    if _is_log(kind):
        a, b = float(np.log(lo)), float(np.log(hi))
        return xp.exp(a + (b - a) * s)
    return lo + (hi - lo) * s


def _array(x):
    """(``x``, jax.numpy) for a JAX array or tracer (differentiable in a solve's
    trace); (float64 NumPy ``x``, NumPy) for anything else."""
    if isinstance(x, (jax.Array, jax.core.Tracer)):
        return x, jnp
    return np.asarray(x, dtype=np.float64), np


def box_fraction(kind: str, x, lo: float, hi: float):
    """Where x lies in [lo, hi], 0..1 (NumPy, or JAX for JAX input): linear, or in
    log for the log box.

    This is sigmoid(z), the fraction the transforms are built on."""
    x, xp = _array(x)
    if _is_log(kind):
        return xp.log(xp.maximum(x, lo) / lo) / np.log(hi / lo)
    return (x - lo) / (hi - lo)


def logit(u):
    """z with sigmoid(z) = u, for u in (0, 1) (NumPy, or JAX for JAX input): the
    inverse of the box fraction."""
    u, xp = _array(u)
    return xp.log(u) - xp.log1p(-u)


def to_unconstrained(kind: str, x, lo: float, hi: float, margin: float = EDGE):
    """Coordinate z(x) (NumPy, or JAX for JAX input); x is moved ``margin`` of the
    range inside [lo, hi]."""
    xp = _array(x)[1]
    return logit(xp.clip(box_fraction(kind, x, lo, hi), margin, 1.0 - margin))


def derivative(kind: str, z, lo: float, hi: float):
    """dx/dz, for mapping standard errors by the delta method."""
    s, xp = _sigmoid(z)
    ds = s * (1.0 - s)
    if _is_log(kind):
        a, b = np.log(lo), np.log(hi)
        return xp.exp(a + (b - a) * s) * (b - a) * ds
    return (hi - lo) * ds


def natural_scale(kind: str, x, lo: float, hi: float):
    """How far a parameter can move across its box, in user units, at ``x``.

    (hi - lo) for the linear boxes, x * log(hi / lo) for the log box (whose
    natural steps are relative). Multiplying a Jacobian column in user units
    by it says how much the image can change through that parameter,
    whatever the current coordinate.
    """
    x = np.asarray(x, dtype=np.float64)
    if _is_log(kind):
        return x * np.log(hi / lo)
    return np.full_like(x, hi - lo)

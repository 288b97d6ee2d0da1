"""A vectorised atan2 to float32 accuracy, for NumPy and JAX arrays alike."""

from __future__ import annotations

import numpy as np


#: tan(pi / 8): ``atan2`` reduces its argument below it.
_TAN_PI_8 = 0.41421356237309503


def atan2(xp, y, x):
    """atan2(y, x) of arrays of module ``xp`` (NumPy or jax.numpy) in float32
    accuracy (|error| <= 3e-7 rad; XLA's own is 2.5e-7), vectorised: XLA's CPU
    atan2 took ~35 ns an element, a third of the sky table's time
    (``fitter.skystencil.sky_table``).
    Octant reduction to a = min / max in [0, 1], then a -> (a - 1) / (a + 1) above
    tan(pi / 8) (+ pi / 4), and Cephes' ``atanf`` polynomial (S. L. Moshier, Cephes
    Math Library 2.2, ``atanf.c``). Signed zeros as IEEE's atan2."""
    ax, ay = xp.abs(x), xp.abs(y)
    hi, lo = xp.maximum(ax, ay), xp.minimum(ax, ay)
    a = lo / xp.where(hi > 0, hi, 1)
    big = a > _TAN_PI_8
    a = xp.where(big, (a - 1) / (a + 1), a)
    z = a * a
    p = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z
         - 3.33329491539e-1) * z * a + a
    p = xp.where(big, p + np.pi / 4, p)
    p = xp.where(ay > ax, np.pi / 2 - p, p)
    p = xp.where(xp.signbit(x), np.pi - p, p)
    return xp.where(xp.signbit(y), -p, p)

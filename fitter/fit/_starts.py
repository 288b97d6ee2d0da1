"""Start points for multi-start fits: a Halton sequence over the box.

Start 0 is the user's initial point. Starts 1.. are the first points of the
unscrambled Halton sequence (scipy.stats.qmc.Halton), mapped through the
parameter transforms: each coordinate's unit interval u in [0.02, 0.98]
covers its box uniformly in the transform's scale (log for m and e, linear
for reflectances, sigma and eta). Deterministic, so fits are reproducible.
"""

from __future__ import annotations

import numpy as np

from .. import transforms

#: Margin kept from the box edges by the Halton starts (fraction of the range).
MARGIN = 0.02


def starts(spec, z_init: np.ndarray, n: int) -> np.ndarray:
    """(n, len(z_init)) start coordinates; row 0 is ``z_init``."""
    z_init = np.asarray(z_init, dtype=np.float64)
    if n == 1:
        return z_init[None]
    from scipy.stats import qmc  # 0.4 s to import: only for multi-start fits
    u = qmc.Halton(d=z_init.size, scramble=False).random(n)[1:]  # row 0 of Halton is 0
    u = MARGIN + (1.0 - 2.0 * MARGIN) * u
    return np.concatenate([z_init[None], transforms.logit(u)], axis=0)

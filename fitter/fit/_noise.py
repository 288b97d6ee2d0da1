"""Noise level of a target image, to judge a fit when no noise sigma is given.

Reference: J. Immerkaer (1996), "Fast noise variance estimation", Computer
Vision and Image Understanding 64(2): sigma = sqrt(pi/2) / 6 * mean |I * N|
with N = [1 -2 1]^T [1 -2 1], a mask that cancels the image's linear trends
so what remains is mostly noise (plus the curvature of sharp highlights, which
only makes the estimate conservative).
"""

from __future__ import annotations

import numpy as np

from .._math import finite_rows


def estimate_noise(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-channel noise standard deviation (3,) from pixels whose 3 x 3
    neighbourhood lies inside ``mask`` ((H, W) bool); NaN if there are none."""
    img = np.asarray(image, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    ys, xs = np.nonzero(m.any(axis=1))[0], np.nonzero(m.any(axis=0))[0]
    if ys.size:  # the mask's bounding box holds every pixel that counts
        img = img[ys[0]:ys[-1] + 1, xs[0]:xs[-1] + 1]
        m = m[ys[0]:ys[-1] + 1, xs[0]:xs[-1] + 1]
    h, w, c = img.shape
    if h < 3 or w < 3:
        return np.full(c, np.nan)
    rows = np.ascontiguousarray(img).reshape(h, w * c)  # x neighbours c apart on contiguous rows
    d2x = rows[:, :-2 * c] - 2.0 * rows[:, c:-c] + rows[:, 2 * c:]
    lap = np.abs(d2x[:-2] - 2.0 * d2x[1:-1] + d2x[2:]).reshape(-1, c)  # (H-2)(W-2), centred
    inside = np.ones((m.shape[0] - 2, m.shape[1] - 2), dtype=bool)
    for dy in range(3):
        for dx in range(3):
            inside &= m[dy:dy + m.shape[0] - 2, dx:dx + m.shape[1] - 2]
    # Sums over the 3 channels and the pixels as products: NumPy's reductions over a
    # last axis of 3 and its boolean picks took 2.5 of 4.7 ms at 256^2.
    bad = ~finite_rows(lap)
    lap[bad] = 0.0
    inside = inside.reshape(-1) & ~bad
    n = int(np.count_nonzero(inside))
    if not n:
        return np.full(c, np.nan)
    return np.sqrt(np.pi / 2.0) / 6.0 * (inside.astype(np.float64) @ lap) / n

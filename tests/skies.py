"""Skies with a one-texel sun (128x64 envmaps) for tests of glints under Mitsuba."""

from __future__ import annotations

import numpy as np

import fitter


def one_texel_sun(path, row: int, col: int, base, slope, ground, sun, size: int = 64):
    """A ``size``^2 scene lit by a 128x64 equirectangular sky written to ``path``: above
    the horizon base + slope (1 - v) per channel (v the row's height, 0 at the
    zenith), ``ground`` below it, and one texel (row, col) of ``sun`` radiance (2.8
    degrees, ~2000 times the sky in the tests)."""
    from fitter.imageio import write_image

    h, w = 64, 128
    y = (np.arange(h) + 0.5) / h
    sky = np.empty((h, w, 3))
    sky[:] = (np.asarray(base) + np.asarray(slope) * (1.0 - y)[:, None])[:, None]
    sky[y > 0.5] = ground
    sky[row, col] = sun
    write_image(str(path), sky)
    return fitter.Scene(width=size, height=size, supersampling=4,
                        environment=fitter.Environment(type="envmap", file=str(path)))

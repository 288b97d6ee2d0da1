"""A sky's irradiance per normal, and a lobe kernel's per sample, summed over its map.

E(n) = int L(w) max(n . w, 0) dw is the map convolved with the clamped cosine
(Ramamoorthi & Hanrahan 2001, "An efficient representation for irradiance
environment maps", eq. 1). Here it is summed over the map itself, as
Mitsuba's ``envmap`` reads it: bilinear between texel centres (columns at
u = (i + 0.5) / W, rows at v' = j / (H - 1), the poles). Resampled to finer
nodes of the same bilinear surface, each node weighs its tent's solid angle,
so the sum is exact but for the cosine's variation across a tent. On a
lat-long grid of normals with the map's columns the sum over azimuth is a
circular convolution per pair of rows (one FFT per row pair), and a normal
between grid nodes takes the bilinear value of its four.

Against a brute-force quadrature of the bilinear map (2048 x 4096
directions) on the shipped probe's sky, 400 random normals: relative rms
4.9e-5, at most 2.8e-4 (the sky stencil's own irradiance, which Lambert's sky
term took before: rms 2.4-4.1e-3 per channel, at most 1.4e-2 on the pixels of a
64^2 sphere); ``tests/test_irradiance.py``.

A lobe's parameter-free kernel k (``Lobe.kernel``: Oren-Nayar's angular term)
depends on the view too: ``kernel_sums`` sums L k cos_i over the directions of
the map's level at most ``KERNEL_COLUMNS`` wide per env sample (compiled, in
chunks of samples). Oren-Nayar's against a brute-force integral over the
probe's sky, 300 random (n, wo): rms 6.3e-4, at most 4.5e-3 of the term (the
sky stencil's: rms 1.6e-2, at most 5.2e-2; from the 32 x 64 level 2.3e-3,
2.2e-2), a 24^2 sphere's interior pixels 1.7e-3, 9.0e-3; the whole lobe there
within 7e-5. 25 k samples (a 128^2 sphere's) 0.45 s, its compile included.
"""

from __future__ import annotations

import functools

import numpy as np

from ._keep import derived
from ._math import to_device
from .envlight import bilinear, dir_to_uv, uv_to_dir

#: The map is summed at its finest pyramid level at most this wide, its columns
#: resampled to at least this many: the cosine then varies by at most 0.025 rad
#: across a tent (its error ~ that squared / 12; 128 columns: rms 2.9e-4).
COLUMNS = 256
#: ... and its rows to at least this many (the poles included).
ROWS = 127


def _tent_weights(rows: int) -> np.ndarray:
    """(rows,) int tent_j(theta) sin(theta) dtheta of rows at theta_j = j pi / (rows - 1)."""
    d = np.pi / (rows - 1)
    w = np.sin(d * np.arange(rows)) * 2.0 * (1.0 - np.cos(d)) / d
    w[0] = w[-1] = 1.0 - np.sin(d) / d  # (a pole's tent is one-sided)
    return w


def _source(levels, rows: int = ROWS, columns: int = COLUMNS) -> np.ndarray:
    """The finest level at most ``columns`` wide, resampled on its own bilinear surface
    to at least ``rows`` x ``columns`` nodes: (rows', columns', 3)."""
    img = next(lv for lv in levels if lv.shape[1] <= columns)
    h, w = img.shape[:2]
    rows = (h - 1) * int(np.ceil((rows - 1) / (h - 1))) + 1
    cols = w * int(np.ceil(columns / w))
    u = (np.arange(cols) + 0.5) / cols
    v = np.arange(rows) / (rows - 1)
    return bilinear(np.asarray(img, np.float64), u[None, :], v[:, None])


def irradiance_grid(levels) -> np.ndarray:
    """E (rows, columns, 3) of a sky (``levels``: its pyramid, ``envlight.Pyramid.levels``)
    at the normals of a lat-long grid in Mitsuba's layout (rows at the poles,
    columns at (i + 0.5) / columns); ``irradiance`` reads it. A uniform sky's is
    pi L exactly (a ``constant`` environment's)."""
    top = np.asarray(levels[0], np.float64)
    if np.all(top == top[:1, :1]):
        return np.broadcast_to(np.pi * top[:1, :1], (2, 2, top.shape[-1])).copy()
    src = _source(levels)
    rows, cols = src.shape[:2]
    theta = np.pi * np.arange(rows) / (rows - 1)
    c, s = np.cos(theta), np.sin(theta)
    dphi = 2.0 * np.pi * np.arange(cols) / cols
    weighted = src * (_tent_weights(rows) * 2.0 * np.pi / cols)[:, None, None]
    # K[a, b, m]: the clamped cosine between row a's normal and row b's direction m
    # columns apart; E[a] = sum_b K[a, b] (*) L[b] (circular in azimuth).
    k = np.maximum(c[:, None, None] * c[None, :, None]
                   + (s[:, None, None] * s[None, :, None]) * np.cos(dphi), 0.0)
    spectrum = np.einsum("abf,bfc->afc", np.fft.rfft(k, axis=-1),
                         np.fft.rfft(weighted, axis=1))
    return np.fft.irfft(spectrum, n=cols, axis=1)


def irradiance(grid: np.ndarray, normals) -> np.ndarray:
    """E (..., 3) at unit ``normals`` (..., 3), bilinear in the grid of
    ``irradiance_grid``."""
    u, v = dir_to_uv(np.asarray(normals, np.float64))
    return bilinear(grid, u, v)


def _per_pixel(rows, values, n: int) -> np.ndarray:
    """(n, 3): the env samples' ``values`` (R, 3) summed per pixel ``rows`` (R,)."""
    return np.stack([np.bincount(rows, values[:, c], minlength=n) for c in range(3)], -1)


def pixel_irradiance(levels, rows, normal, weight, n: int) -> np.ndarray:
    """(n, 3) per active pixel: E at each env sample (``rows`` (R,) its pixel, unit
    ``normal`` (R, 3)) times its weight (R,), summed per pixel; ``levels``: the sky's
    pyramid, whose grid of E (``irradiance_grid``) is kept with its top level."""
    grid = derived(levels[0], "irradiance", lambda: irradiance_grid(levels))
    return _per_pixel(rows, weight[:, None] * irradiance(grid, normal), n)


#: ``kernel_sums`` sums the map's finest level at most this wide, at its texel nodes
#: (a smaller map resampled to ``KERNEL_ROWS`` x this: a constant sky's 2 x 4 texels
#: as nodes had left Oren-Nayar's B term 7 % off).
KERNEL_COLUMNS = 128
KERNEL_ROWS = 64
#: Env samples per chunk of ``kernel_sums`` (x the level's directions: 4 M pairs).
KERNEL_CHUNK = 512


def _nodes(levels):
    """(directions (T, 3), radiance x tent solid angle (T, 3)) of the finest level at
    most ``KERNEL_COLUMNS`` wide, at its own nodes (``_source``: at least
    ``KERNEL_ROWS`` x ``KERNEL_COLUMNS`` of them)."""
    img = _source(levels, KERNEL_ROWS, KERNEL_COLUMNS)
    h, w = img.shape[:2]
    u, v = np.meshgrid((np.arange(w) + 0.5) / w, np.arange(h) / (h - 1))
    weighted = img * (_tent_weights(h) * 2.0 * np.pi / w)[:, None, None]
    return uv_to_dir(u, v).reshape(-1, 3), weighted.reshape(-1, 3)


@functools.lru_cache(maxsize=8)
def _summer(kernel):
    import jax
    import jax.numpy as jnp

    from .bsdf.base import Cosines

    def one(args, dirs, radiance):  # a chunk of samples: (B, 3) x 3 -> (B, 3)
        n, wo, w = args
        # (the three dot products only, two as matrix products: with every field of
        # ``cosines`` the sums took 3.3 s for 25 k samples instead of 0.3 s)
        c = Cosines(n @ dirs.T, jnp.sum(n * wo, -1)[:, None], wo @ dirs.T,
                    *(None,) * (len(Cosines._fields) - 3))
        k = jnp.where((c.cos_i > 0) & (c.cos_o > 0), kernel(c) * c.cos_i, 0.0)
        return w[:, None] * (k @ radiance)

    @jax.jit
    def run(n, wo, w, dirs, radiance):
        chunks = [a.reshape((-1, KERNEL_CHUNK) + a.shape[1:]) for a in (n, wo, w)]
        return jax.lax.map(lambda a: one(a, dirs, radiance), chunks).reshape(-1, 3)

    return run


def kernel_sums(levels, kernel, rows, normal, view, weight, n: int) -> np.ndarray:
    """(n, 3) per active pixel: int L k(c) cos_i dw of ``kernel`` k (on ``Cosines``,
    of which it may read cos_i, cos_o and cos_io only, the rest None) at
    each env sample (``rows`` (R,) its pixel, unit ``normal`` and ``view`` (R, 3)),
    times its weight (R,), summed per pixel; ``levels``: the sky's pyramid."""
    dirs, radiance = _nodes(levels)
    pad = (-len(rows)) % KERNEL_CHUNK
    # (zero padding: cos_i = 0 there, which the kernel's mask takes to 0, and weight 0)
    args = [np.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1)) for a in (normal, view, weight)]
    # (to_device: jnp.asarray compiled a copy kernel per shape on a first run)
    e = np.asarray(_summer(kernel)(*map(to_device, args), to_device(dirs),
                                   to_device(radiance)))[:len(rows)]
    return _per_pixel(rows, e, n)

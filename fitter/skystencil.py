"""The sky stencil: the environment's smooth part as a fixed set of cells per env sample.

Material-independent, built once per scene (``sky_table``): per env sample
(``geometry.env_samples``) and cell of a stencil about the sample's mirror
direction r -- rings (``RING_EDGES``: 0.006 rad first ring, up to ``MAX_PHI``
sectors a ring, one sector centred on the plane of incidence; 690 cells) --
c = Q x the radiance prefiltered to the cell's size at its cos-weighted
centroid, Q = int_cell max(cos_i, 0) dw tabulated against theta_o. Per step
the renderer evaluates a lobe only at ``Detail.nodes`` theta_o nodes (dense
towards grazing) x cells x ``Detail.sub`` points per cell (``node_geometry``:
the lobe is averaged over the cell, the radiance is not -- it is prefiltered),
interpolates cos_o x lobe linearly in theta_o per sample and sums against c
as one batched matrix product (``blocks``, ``sky_sum``). Against a
brute-force hemisphere quadrature (``tests/test_envlight_reference.py``):
Beckmann m = 0.1 within 0.33 % and m = 0.25 within 0.3 % for theta_o up to
89.5 degrees; the error against Mitsuba per discretisation is measured by
``benchmarks/envlight.py``.
"""

from __future__ import annotations

import functools
import itertools
from typing import NamedTuple

import numpy as np

from ._math import to_device
from .atan2 import atan2

#: Ring edges (radians from the mirror direction) of the sky stencil.
#: Below 0.3 rad twice as many rings as the first version (midpoints added): a midpoint
#: rule in angle over a Gaussian-like lobe is -0.3 % (Phong e = 300) to +0.4 % (Beckmann
#: m = 0.1) biased on the coarser rings, measured against a brute-force quadrature
#: (``tests/test_envlight_reference.py``).
RING_EDGES = np.array([0.0, 0.006, 0.012, 0.0195, 0.027, 0.036, 0.045, 0.055, 0.065, 0.0775, 0.09,
                       0.105, 0.12, 0.1375, 0.155, 0.175, 0.195, 0.2175, 0.24, 0.265, 0.29, 0.35,
                       0.42, 0.5, 0.6, 0.72, 0.86, 1.03, 1.25, 1.5, 1.8, 2.2, 2.65, np.pi])
#: Azimuthal cells per ring: about square cells, between these bounds. A microfacet lobe at
#: grazing view is a stripe in the plane of incidence only ~2 m cos(theta_o) wide across
#: it: 16 sectors left Beckmann m = 0.1 -2 % / -4 % / -6 % low at theta_o = 70 / 80 / 84
#: degrees (the "limb" error against Mitsuba); 24 sectors -0.2 / -0.6 / -0.5 %.
MIN_PHI, MAX_PHI = 6, 24

class Detail(NamedTuple):
    """The discretisation of the sky term (the public knob of its quadrature error).

    Attributes:
        nodes: theta_o nodes at which the lobe is evaluated (``LOBE_NODES``).
        sub: (alpha, phi) lobe points per stencil cell (``LOBE_SUB``; each divides 8).
        rings: every ``rings``-th ring edge of ``RING_EDGES`` is kept (and the
            last): 2 is a stencil of half the rings, which the stated errors
            compare the default with (``fitter.fit._discretisation.ring_error``).

    ``Detail.finer()`` (193 nodes, 4 x 8 points) is about 4x the per-step lobe
    cost; the difference of a render with it estimates the default's error.
    """

    nodes: int = 97
    sub: tuple = (2, 4)
    rings: int = 1

    @classmethod
    def finer(cls) -> Detail:
        return cls(nodes=193, sub=(4, 8))


# ---------------------------------------------------------------------- the sky stencil
#: Cosine tables: angles between n and r (0 .. pi/2) at which Q and the centroids are tabulated.
N_THETA = 129
_FINE = 8  # sub-cells per cell side when tabulating


def ring_edges(rings: int = 1) -> np.ndarray:
    """Every ``rings``-th edge of ``RING_EDGES``, and the last (``Detail.rings``)."""
    return RING_EDGES if rings == 1 else np.concatenate([RING_EDGES[:-1:rings],
                                                         RING_EDGES[-1:]])


def _cells(sub, sub_phi=None, rings: int = 1):
    """Sub-cells (``sub`` in alpha x ``sub_phi`` in phi per cell, consecutive) of the stencil
    about +z in (cos alpha, phi, d cos, d phi, cell id) and the number of cells: rings in
    alpha (``ring_edges``), each cut into azimuthal sectors, one centred on phi = 0."""
    sub_phi = sub if sub_phi is None else sub_phi
    out, n = [], 0
    sa, sp = np.arange(sub), np.arange(sub_phi)
    for a0, a1 in itertools.pairwise(ring_edges(rings)):
        mid = 0.5 * (a0 + a1)
        nphi = 1 if a0 == 0 else int(np.clip(round(2 * np.pi * np.sin(mid) / (a1 - a0)),
                                             MIN_PHI, MAX_PHI))
        ca = np.cos(np.linspace(a0, a1, sub + 1))
        # (sector j, alpha row, phi column), phi fastest: the sub-cells of a cell consecutive
        j, a, f = (x.reshape(-1) for x in np.meshgrid(np.arange(nphi), sa, sp, indexing="ij"))
        out.append((0.5 * (ca[a] + ca[a + 1]),  # equal-area midpoint in cos
                    2 * np.pi * (j + (f + 0.5) / sub_phi - 0.5) / nphi,
                    ca[a] - ca[a + 1], np.full(j.size, 2 * np.pi / nphi / sub_phi), n + j))
        n += nphi
    return tuple(np.concatenate(a) for a in zip(*out)) + (n,)


def _sub_directions(ct, ph):
    """Unit directions (M, 3) of sub-cells at (cos alpha, phi) about +z."""
    st = np.sqrt(np.maximum(1.0 - ct * ct, 0.0))
    return np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1)


def _cos_weights(d, dw, th):
    """max(n . d, 0) dw (T, M) of sub-cells ``d`` (M, 3) of solid angle ``dw`` (M,)
    for normals n = (sin t, 0, cos t) at the angles ``th`` (T,), an angle a row:
    each row's temporaries stay in cache (whole (T, M) products took 3x as long).
    The callers sum them per cell by reshaping (a cell's sub-cells are consecutive
    in ``_cells``), not by ``np.bincount`` per angle: ``_tables`` 0.13 -> 0.05 CPU-s,
    ``_node_geometry`` 0.17 -> 0.10."""
    out = np.empty((th.size, d.shape[0]))
    for t, row in zip(th, out):
        np.maximum(d[:, 0] * np.sin(t) + d[:, 2] * np.cos(t), 0.0, out=row)
        row *= dw
    return out


def _tables(rings: int = 1):
    """Per cell and angle theta_o between n and r: Q = int_cell max(n.w, 0) dw, the unit
    direction of the cos-weighted centroid (local frame: r = +z, n in the xz plane) and
    the cell's angular size sqrt(solid angle)."""
    ct, ph, dct, dph, cell, n = _cells(_FINE, rings=rings)
    assert np.array_equal(cell, np.repeat(np.arange(n), _FINE * _FINE))  # consecutive
    d, dw = _sub_directions(ct, ph), dct * dph
    th = np.linspace(0.0, np.pi / 2, N_THETA)
    w = _cos_weights(d, dw, th).reshape(N_THETA, n, _FINE * _FINE)  # a cell's sub-cells
    q = w.sum(-1)
    cen = np.matmul(w.transpose(1, 0, 2), d.reshape(n, -1, 3)).transpose(1, 0, 2)
    size = np.broadcast_to(np.sqrt(dw.reshape(n, -1).sum(-1)), (N_THETA, n)).copy()
    nl = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)
    norm = np.linalg.norm(cen, axis=-1, keepdims=True)
    cen = np.where(norm > 0, cen / np.where(norm > 0, norm, 1.0), nl[:, None])
    return q, cen, size


@functools.cache
def _cached_tables(rings: int = 1):
    """``_tables``, built on first use (~0.05 s), not at import; kept on disk beside
    the compilation cache when that is on (``compilation_cache.cached_arrays``)."""
    from .compilation_cache import cached_arrays

    return cached_arrays("sky-tables", repr((N_THETA, _FINE, rings)), lambda: _tables(rings))


#: Nodes in theta_o (0 .. pi/2, uniform) at which a lobe is evaluated on the stencil.
#: The renderer evaluates the lobe once per node and cell (T x N values per step, not
#: one per env sample and cell) and interpolates cos_o x lobe linearly in theta_o per
#: sample; ``benchmarks/envlight.py`` measures the error against exact per-sample
#: evaluation and against Mitsuba per node count (``lobe_nodes`` there).
LOBE_NODES = Detail().nodes


#: Points per cell (alpha x phi) at which the lobe is averaged: the sky's radiance is
#: prefiltered to the cell's size, the lobe is not, and a microfacet lobe at grazing view
#: is a stripe narrower than a sector (2 m cos(theta_o) across it). One point (the
#: cell's centroid) was -/+17 % off at theta_o = 89 degrees for Beckmann m = 0.1 (sector
#: edge / centre on the stripe); ``benchmarks/envlight.py`` measures the choices.
LOBE_SUB = Detail().sub


def node_angles(nodes: int = LOBE_NODES):
    """The theta_o nodes (T,): 0 .. pi/2, spaced ~(1 - x) dense towards grazing, where
    cos_o x lobe bends fastest (the last spacing pi/2 / (T - 1)^2)."""
    x = np.linspace(0.0, 1.0, nodes)
    return np.pi / 2 * (1.0 - (1.0 - x) ** 2)


def _node_of(theta, nodes):
    """The lower node (int32) of angles theta and the linear fraction towards the next."""
    x = (1.0 - np.sqrt(np.clip(1.0 - theta / (np.pi / 2), 0.0, 1.0))) * (nodes - 1)
    node = np.clip(np.floor(x).astype(np.int32), 0, nodes - 2)
    th = node_angles(nodes)
    return node, (theta - th[node]) / (th[node + 1] - th[node])


@functools.cache
def node_geometry(nodes: int = LOBE_NODES, sub: tuple = LOBE_SUB, rings: int = 1):
    """``_node_geometry``, kept on disk beside the compilation cache when that is
    on (``compilation_cache.cached_arrays``): ~0.1 s of NumPy a process."""
    from .bsdf.base import Cosines
    from .compilation_cache import cached_arrays

    def make():
        cos, w = _node_geometry(nodes, tuple(sub), rings)
        return (*cos, w)

    *cos, w = cached_arrays("sky-nodes", repr((nodes, tuple(sub), _FINE, rings)), make)
    return Cosines(*cos), w


def warm() -> None:
    """Make the default stencil's constant tables now (``_cached_tables``,
    ``node_geometry``), as ``geometry.build_geometry`` asks for them: a fit's
    set-up starts this on a thread (``fit._ahead.import_ahead``)."""
    det = Detail()
    _cached_tables(det.rings)
    node_geometry(det.nodes, tuple(det.sub), det.rings)


def _node_geometry(nodes: int, sub: tuple, rings: int = 1):
    """``Cosines`` (T, N, M) of M points per stencil cell at the theta_o nodes (cos_o
    (T, 1, 1): one per node) and the weights (T, N, M) by which the renderer sums
    a lobe there: cos_o x the point's share of the cell's Q = int max(cos_i, 0) dw.
    The points are the cos-weighted centroids of ``sub`` = (alpha, phi) groups of
    the ``_FINE`` sub-cells that tabulate Q, so the shares sum to exactly 1 where
    Q > 0 (Lambert stays exact).
    Local frame: r = +z, n = (sin t, 0, cos t), wo = (sin 2t, 0, cos 2t). Points
    that receive nothing get the normal as a harmless stand-in direction (weight 0).
    """
    from .bsdf.base import cosines

    sa, sp = sub
    if _FINE % sa or _FINE % sp:
        raise ValueError(f"sub = {sub}: each must divide _FINE = {_FINE}")
    ct, ph, dct, dph, cell, n_cells = _cells(_FINE, rings=rings)
    assert np.array_equal(cell, np.repeat(np.arange(n_cells), _FINE * _FINE))
    # A cell's _FINE x _FINE sub-cells (alpha rows, phi columns) in sa x sp groups,
    # reordered so that each group's are consecutive.
    group = np.arange(ct.size).reshape(n_cells, sa, _FINE // sa, sp, _FINE // sp)
    group = group.transpose(0, 1, 3, 2, 4).reshape(-1)
    d = _sub_directions(ct[group], ph[group])
    th = node_angles(nodes)
    wf = _cos_weights(d, (dct * dph)[group], th).reshape(nodes, n_cells * sa * sp, -1)
    w = wf.sum(-1)
    cen = np.matmul(wf.transpose(1, 0, 2), d.reshape(w.shape[1], -1, 3)).transpose(1, 0, 2)
    n = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)[:, None]
    wo = np.stack([np.sin(2 * th), np.zeros_like(th), np.cos(2 * th)], -1)[:, None]
    norm = np.linalg.norm(cen, axis=-1, keepdims=True)
    lit = w > 0
    cen = np.where(lit[..., None], cen / np.where(norm > 0, norm, 1.0), n)
    w = w.reshape(nodes, n_cells, -1)
    tot = w.sum(-1, keepdims=True)
    w = np.where(tot > 0, w / np.where(tot > 0, tot, 1.0), 0.0) * np.cos(th)[:, None, None]
    cos = cosines(np.broadcast_to(n, cen.shape), cen, np.broadcast_to(wo, cen.shape))
    cos = _reshaped(cos, (nodes, n_cells, sa * sp))
    # cos_o = n . wo is one value per node: kept (T, 1, 1) here (and in the table kept
    # on disk); ``geometry.build_geometry`` repeats it over the points for the renderer,
    # which evaluates the lobe's derivative columns on them flat (``render._env_unit``).
    return cos._replace(cos_o=np.ascontiguousarray(cos.cos_o[:, :1, :1]),
                        cot_o=np.ascontiguousarray(cos.cot_o[:, :1, :1])), w


def _reshaped(cos, shape):
    return type(cos)(*(np.reshape(a, shape) for a in cos))


#: Env samples per block of the sky sum and theta_o nodes per block's window: a block
#: holds B consecutive node-sorted samples whose nodes and next nodes lie in a window of
#: S consecutive nodes, so the sum is one batched matrix product (blocks x (B x 3, N) @
#: (N, S x columns)) with the lobe's values at the S window nodes, then each sample's
#: two neighbouring nodes picked by hat weights; not a per-sample gather (~20x slower
#: here). XLA's CPU batched dot is slow for many small blocks: at 128^2 (26 k samples,
#: both cores free) B = 256, S = 4 (3.7 % padding rows) took the sky sum from ~42 to
#: ~21 ms (render, one column) and ~72 to ~38 ms (3 columns) against B = 16 of one
#: node, which runs on one thread; S = 3 pads 8 % and S = 5 or B = 512 were slower
#: (``benchmarks/skyblocks.py``, ``benchmarks/README.md``).
BLOCK = 256
WINDOW = 4


def blocks(node, frac, nodes: int, block: int = BLOCK, window: int = WINDOW):
    """Blocked order of env samples by theta_o node, for ``sky_sum``.

    node (R0,) int, each sample's lower node (0 .. ``nodes`` - 2), frac (R0,) its
    linear fraction towards the next. Returns (order (R,): sample index or -1 for
    padding, R a multiple of ``block``; window (nb, S) int32: each block's S =
    min(``window``, ``nodes``) consecutive nodes; pos (R,): the sample's position
    in its block's window, node - window[0] + frac in [0, S - 1], 0 for padding).
    Greedy: a block is closed when full or when the next sample's next node would
    leave its window (starting at its first sample's node, clipped to the last S).
    """
    node = np.asarray(node)
    frac = np.asarray(frac, np.float64)
    s = max(min(window, nodes), 2)
    srt = np.argsort(node, kind="stable")
    ns = node[srt]
    order, start = [], []
    i = 0
    while i < ns.size:
        j0 = max(min(int(ns[i]), nodes - s), 0)
        end = min(i + block, int(np.searchsorted(ns, j0 + s - 2, "right")))
        order.append(np.concatenate([srt[i:end], np.full(block - (end - i), -1)]))
        start.append(j0)
        i = end
    if not order:
        return np.zeros(0, np.int64), np.zeros((0, s), np.int32), np.zeros(0)
    order = np.concatenate(order)
    start = np.asarray(start, np.int32)
    pick = np.maximum(order, 0)
    # frac on the grid of pos's spacing below S - 1: pos is then exact and ``sky_sum``'s
    # hat weights are exactly 1 - frac and frac, whichever window a sample lands in (a
    # pixel subset's blocks give the whole's values bit for bit); <= 2^-52 relative.
    q = np.spacing(float(s - 1))
    frac = np.round(frac / q) * q
    pos = np.where(order < 0, 0.0, node[pick] - np.repeat(start, block) + frac[pick])
    return order, start[:, None] + np.arange(s, dtype=np.int32), pos


def sky_sum(h, window, pos, c, xp=None):
    """Per env sample sum over cells of the node-interpolated h times c.

    h: (..., T, N) or (..., T, N, 3) lobe x ``node_geometry`` weight (an RGB
    last axis for coloured lobes); window (nb, S) each block's nodes and pos
    (R,) the sample's position in them (``blocks``); c (nb, B x 3, N): samples
    x RGB rows (``sky_table``). Returns (..., R, 3): per sample sum_n c (h at
    its node + pos's fraction towards the next, linearly), as hat weights
    max(0, 1 - |pos - s|) over the window's S products c h[window[s]].
    ``xp``: the array module (default jax.numpy; NumPy for a host table).
    """
    if xp is None:
        import jax.numpy as xp

    rgb = h.shape[-1] == 3 and h.shape[-2] == c.shape[-1]
    nd = 3 if rgb else 2
    lead = h.shape[:h.ndim - nd]
    nb, rows, n = c.shape
    b, s = rows // 3, window.shape[-1]
    # (T, N, [3,] K): the lobe's columns (lead axes) last, for a plain batched matmul.
    ht = xp.moveaxis(h.reshape((-1,) + h.shape[-nd:]), 0, -1)
    k = ht.shape[-1]
    hw = xp.moveaxis(xp.take(ht, window, axis=0), 1, -2)  # (nb, N, [3,] S, K)
    hw = hw.reshape(hw.shape[:-2] + (s * k,))
    if rgb:  # per channel: (nb, B, 3, N) x (nb, N, 3, S K)
        out = xp.einsum("bscn,bnck->bsck", c.reshape(nb, b, 3, n).astype(h.dtype), hw)
    else:
        out = xp.einsum("brn,bnk->brk", c.astype(h.dtype), hw)
    out = out.reshape(nb, b, 3, s, k)
    at = pos.reshape(nb, b, 1).astype(h.dtype) - xp.arange(s, dtype=h.dtype)
    w = xp.maximum(1.0 - xp.abs(at), 0.0)  # (nb, B, S)
    # an elementwise sum, not a dot: XLA makes (1, S) x (S, 3 K) matrices per sample of it
    val = xp.sum(out * w[:, :, None, :, None], axis=3)  # (nb, B, 3, K)
    return xp.moveaxis(val.reshape(nb * b, 3, k), -1, 0).reshape(lead + (nb * b, 3))


def _flat_levels(sky):
    """The pyramid's levels as one (sum h w, 4, 3) array of each texel's 2 x 2
    neighbourhood ((y, x), (y, x + 1), (y + 1, x), (y + 1, x + 1); x wraps, y + 1
    stops at the last row, which a lookup never starts from) with per-level (h,
    w, offset): a bilinear lookup is one gather of 12 values, not four of 3
    (the tabulation ~12 % faster, the same values)."""
    quads, shp = [], np.array([lv.shape[:2] for lv in sky.levels])
    off = np.concatenate([[0], np.cumsum(shp[:, 0] * shp[:, 1])[:-1]])
    for lv in sky.levels:
        h, w = lv.shape[:2]
        y1, x1 = np.minimum(np.arange(h) + 1, h - 1), (np.arange(w) + 1) % w
        quads.append(np.stack([lv, lv[:, x1], lv[y1], lv[y1][:, x1]], 2).reshape(-1, 4, 3))
    return np.concatenate(quads), shp[:, 0], shp[:, 1], off


def _bilinear(xp, quads, h, w, off, u, v):
    """Mitsuba's bilinear lookup (``envlight.bilinear``) of the level (h, w) at
    ``off`` of ``_flat_levels``' ``quads``, at u in [0, 1), v in [0, 1] (``xp``:
    NumPy or jax.numpy)."""
    hf, wf = h.astype(u.dtype), w.astype(u.dtype)
    fx, fy = u * wf - 0.5, v * (hf - 1)
    x0 = xp.floor(fx)
    y0 = xp.clip(xp.floor(fy), 0.0, hf - 2)
    wx, wy = (fx - x0)[..., None], xp.clip(fy - y0, 0.0, 1.0)[..., None]
    x0i = x0.astype(xp.int32)
    x0i = xp.where(x0i < 0, x0i + w, x0i)  # u in [0, 1): x0 >= -1 (not an integer mod)
    g = xp.take(quads, y0.astype(xp.int32) * w + off + x0i, axis=0)  # (..., 4, 3)
    top = g[..., 0, :] * (1 - wx) + g[..., 1, :] * wx
    bot = g[..., 2, :] * (1 - wx) + g[..., 3, :] * wx
    return top * (1 - wy) + bot * wy


def _table_fn(xp):
    """The tabulation of ``sky_table`` for env samples (C,): c (C, 3, N), computed
    in the inputs' dtype and returned as float64; ``xp``: jax.numpy (one chunk,
    under ``_table_all_fn``'s jit) or NumPy (a small table, on the host)."""

    def fn(nrm, wo, wt, q_tab, cen_tab, quads, lh, lw, loff, lo, fl):
        co = xp.clip(xp.sum(nrm * wo, -1), 0.0, 1.0)
        r = 2.0 * co[:, None] * nrm - wo
        t = nrm - co[:, None] * r
        tn = xp.linalg.norm(t, axis=-1, keepdims=True)
        a = xp.where(xp.abs(r[:, :1]) < 0.9, xp.array([1.0, 0, 0], dtype=r.dtype),
                     xp.array([0, 1.0, 0], dtype=r.dtype))
        t0 = xp.cross(a, r)
        t0 = t0 / xp.linalg.norm(t0, axis=-1, keepdims=True)
        t = xp.where(tn > 1e-9, t / xp.where(tn > 0, tn, 1.0), t0)
        b = xp.cross(r, t)
        th = xp.arccos(co)
        x = th / (xp.pi / 2) * (q_tab.shape[0] - 1)
        i0 = xp.clip(xp.floor(x).astype(xp.int32), 0, q_tab.shape[0] - 2)
        f = (x - i0.astype(x.dtype))[:, None]
        q = q_tab[i0] * (1 - f) + q_tab[i0 + 1] * f  # (C, N)
        cl = cen_tab[i0] * (1 - f[..., None]) + cen_tab[i0 + 1] * f[..., None]
        # Not normalised: (u, v) and the sign test below are scale-free (|d| ~ 1, so
        # no hypot either; the division was ~10 % of the tabulation).
        d = cl[..., :1] * t[:, None] + cl[..., 1:2] * b[:, None] + cl[..., 2:] * r[:, None]
        u = atan2(xp, d[..., 0], -d[..., 2]) / (2.0 * xp.pi)
        u = u - xp.floor(u)
        v = atan2(xp, xp.sqrt(d[..., 0] ** 2 + d[..., 2] ** 2), d[..., 1]) / xp.pi
        rad = (_bilinear(xp, quads, lh[lo], lw[lo], loff[lo], u, v) * (1 - fl)[:, None]
               + _bilinear(xp, quads, lh[lo + 1], lw[lo + 1], loff[lo + 1], u, v) * fl[:, None])
        lit = (q > 0) & (xp.sum(d * nrm[:, None], -1) > 0)
        c = xp.where(lit[..., None], rad * (q * wt[:, None] / co[:, None])[..., None], 0.0)
        return xp.swapaxes(c, 1, 2).astype(xp.float64)  # (C, 3, N), float64 sums

    return fn


#: A sky table of at most this many env samples x cells is tabulated with NumPy on
#: the host: the stated errors' half-ring table (~2 k samples x 263 cells at
#: 128^2) took ~0.9 CPU-s of a first env fit to trace and compile for its own
#: shapes, and ~0.15 s on the host.
HOST_TABLE_CELLS = 2**20


@functools.cache
def _table_all_fn():
    """Jitted ``_table_fn`` over chunks (n, step, ...) -> (n x step / B, rows, N) float64."""
    import jax
    import jax.numpy as jnp

    from .compilation_cache import NO_LIBRARY_FUSIONS

    def run(nrm, wo, wt, *consts, rows):
        out = jax.lax.map(lambda x: _table_fn(jnp)(*x, *consts), (nrm, wo, wt))
        return out.reshape((-1, rows, out.shape[-1]))

    return jax.jit(run, static_argnames="rows", compiler_options=NO_LIBRARY_FUSIONS)


def sky_table(sky, normal, view, weight=None, nodes: int = LOBE_NODES,
              chunk: int = 2048, dtype=np.float32, rings: int = 1):
    """Env samples in blocks (``blocks``) and their sky-stencil weights.

    ``normal``, ``view`` (S, 3): unit normal and unit direction to the camera
    (n . view > 0); ``weight`` (S,) the sample's quadrature weight (default 1).
    Returns (order (R,): sample index, -1 for padding; window (nb, S) and pos
    (R,) as ``blocks`` gives them; c (nb, B x 3, N)) with c = weight x
    Q(theta_o) x the prefiltered radiance at the cell's cos-weighted centroid
    / cos_o, per sample, RGB channel and cell; Q = int_cell max(cos_i, 0) dw
    is tabulated per cell
    (exact for a constant sky), and the 1/cos_o undoes the cos_o that
    ``node_geometry`` folds into the lobe (smooth up to the horizon). c is a
    device array, or a NumPy one where the table has at most
    ``HOST_TABLE_CELLS`` samples x cells (made on the host, nothing compiled).

    ``rings``: the stencil's ring density (``Detail.rings``).
    ``dtype``: the tabulation runs in float32 by default (c is returned as
    float64 for the float64 sums): c only carries the sky's radiance and
    geometric weights, smooth in the sample's directions, so rounding them
    changes a render by at most 1.5e-6 relative (env_plastic, measured),
    1000x below the stencil's quadrature error, for ~25 % less tabulation time.
    """
    q_tab, cen_tab, size_tab = _cached_tables(rings)
    quads, lh, lw, loff = _flat_levels(sky)
    lev = np.clip(np.log2(size_tab[0] / sky.texel), 0, len(sky.levels) - 1)  # theta-free
    lo = np.minimum(np.floor(lev).astype(np.int32), max(len(sky.levels) - 2, 0))
    fl = lev - lo
    if len(sky.levels) == 1:  # a single level: look it up twice
        lh, lw, loff = (np.concatenate([a, a]) for a in (lh, lw, loff))
    lh, lw, loff = (np.asarray(a, np.int32) for a in (lh, lw, loff))
    weight = np.ones(normal.shape[0]) if weight is None else np.asarray(weight, np.float64)
    node, fr = _node_of(np.arccos(np.clip(np.sum(normal * view, -1), 0.0, 1.0)), nodes)
    order, window, pos = blocks(node, fr, nodes)
    n = size_tab.shape[1]
    if not order.size:
        return order, window, pos, np.zeros((0, 3 * BLOCK, n))
    nb = window.shape[0]
    real = order >= 0

    def cast(a):  # the tabulation's inputs: floats in its dtype, integers as they are
        return np.asarray(a, dtype if np.asarray(a).dtype.kind == "f" else None)

    consts = [cast(a) for a in (q_tab, cen_tab, quads, lh, lw, loff, lo, fl)]
    if np.count_nonzero(real) * n <= HOST_TABLE_CELLS:
        pick = order[real]
        c = np.zeros((order.size, 3, n))
        with np.errstate(all="ignore"):  # (NumPy warns where JAX computes and discards)
            c[real] = _table_fn(np)(*(cast(x) for x in (normal[pick], view[pick],
                                                        weight[pick])), *consts)
        return order, window, pos, c.reshape(nb, 3 * BLOCK, n)
    n_chunks = -(-order.size // max(chunk, BLOCK))
    per = -(-nb // n_chunks)  # blocks per chunk
    extra = (-nb) % per  # whole padding blocks: every chunk the same shape
    order = np.concatenate([order, np.full(extra * BLOCK, -1)])
    window = np.concatenate([window, np.broadcast_to(window[:1], (extra, window.shape[1]))])
    pos = np.concatenate([pos, np.zeros(extra * BLOCK)])
    step = per * BLOCK
    pad = order < 0
    pick = np.where(pad, 0, order)
    nrm = np.where(pad[:, None], [0.0, 0.0, 1.0], normal[pick])
    wo = np.where(pad[:, None], [0.0, 0.0, 1.0], view[pick])
    wt = np.where(pad, 0.0, weight[pick])
    # One jitted map over the chunks writing straight into the (nb, B x 3, N) float64
    # table: no host copy of it (a fresh 0.5 GB costs seconds of page faults here).
    # (to_device: no copy kernel compiled per shape, as jnp.asarray of a host array does)
    c = _table_all_fn()(*(to_device(cast(x.reshape((-1, step) + x.shape[1:])))
                          for x in (nrm, wo, wt)), *(to_device(a) for a in consts),
                        rows=3 * BLOCK)
    return order, window, pos, c

"""The environment as light on opaque lobes: a fixed set of directions per sample.

Mitsuba's ``envmap``/``constant`` emitter lights an opaque sphere with
L_o(wo) = int f(wi, wo) L(wi) cos_i dwi over the hemisphere (direct light is
the whole answer: a convex sphere sees no other part of itself). The
radiance L is the bilinearly interpolated latitude-longitude map
(``fitter.environment``). It is split in two, both tabulated once per scene
(material-independent, float64 NumPy):

* **Sun lights.** Texels brighter than ``SUN_RATIO`` x the map's median
  luminance (at most ``SUN_MAX_TEXELS``) carry their excess over the
  surrounding sky. The bilinear image of that excess is integrated on
  half-texel cells (``SUN_SUB`` x ``SUN_SUB`` sub-samples per texel) into
  directional lights -- irradiance = int L dw over the cell, direction its
  radiance-weighted centroid -- which the renderer treats exactly like the
  scene's directional lights (every sub-pixel sample, every lobe).
* **Sky stencil.** The rest (the map with the sun texels filled in) is
  integrated per *env sample* over a fixed stencil of ``N`` cells: rings
  about the sample's mirror direction r = reflect(wo, n), narrow near r
  (``RING_EDGES``: 0.006 rad first ring, up to ``MAX_PHI`` sectors a ring;
  ~690 cells), wide far away where only broad lobes reach. Against a
  brute-force hemisphere quadrature (``tests/test_envlight_reference.py``):
  Beckmann m = 0.1 within 0.7 % and m = 0.25 within 0.4 % for theta_o <= 84
  degrees (m = 0.1: -3 % at 87, -17 % at 89), normalised Phong e = 300 0.2 %.
  Per cell, ``STENCIL_SUB`` x ``STENCIL_SUB`` sub-cells look up a
  solid-angle-prefiltered pyramid of the map at their own size, giving
  c = int_cell L max(cos_i, 0) dw (RGB) and the direction of the cell's
  cos-weighted luminance centroid (above the horizon by construction). A
  lobe then contributes scale * sum_cells shape(w_cell, wo) * c: Lambert's is
  exactly rho/pi x irradiance, every other lobe a quadrature whose error is
  measured in ``benchmarks/envlight.py``.

Env samples are the pixel centres of pixels wholly on the sphere and every
hitting sub-pixel sample of silhouette pixels and of limb pixels
(``geometry.ENV_LIMB_COS``), weighted by its quadrature weight: the sky term
is smooth across the sphere but for the limb, while the sun's highlight
(sharp) gets the scene's full supersampling through the sun lights.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

#: A texel is part of the sun when its luminance exceeds this x the median.
SUN_RATIO = 20.0
#: At most this many sun texels (the brightest); the rest stays in the sky.
SUN_MAX_TEXELS = 64
#: Sun lights: cells of 1 / SUN_CELL texel, integrated with SUN_SUB sub-samples per texel.
#: A light at a whole texel's centroid (0.049 rad on the 128-wide probe) sharpens a
#: highlight as narrow as Phong e = 300's (0.058 rad): env_phong's e came out 3.2 % low;
#: half-texel cells: 0.6 % (quarter-texel: 0.3 %, at 1.5x the fit time and memory).
SUN_CELL = 2
SUN_SUB = 8
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
_LUM = np.array([0.2126, 0.7152, 0.0722])


class EnvLights(NamedTuple):
    """The environment split for the renderer (see the module docstring).

    Attributes:
        sun_dir: (Ls, 3) unit directions towards the sun cells.
        sun_irradiance: (Ls, 3) int L dw of each cell (a directional light's irradiance).
        sky: ``Pyramid`` of the remaining radiance.
    """

    sun_dir: np.ndarray
    sun_irradiance: np.ndarray
    sky: "Pyramid"


# ----------------------------------------------------------------- lat-long maps (NumPy)
def dir_to_uv(v):
    """Mitsuba's (u, v') of unit directions (..., 3); see ``fitter.environment``."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    u = np.arctan2(x, -z) / (2.0 * np.pi)
    return u - np.floor(u), np.arctan2(np.hypot(x, z), y) / np.pi


def uv_to_dir(u, v):
    """Inverse of ``dir_to_uv``: u in [0, 1), v' in [0, 1] -> unit directions (..., 3)."""
    phi, theta = 2.0 * np.pi * u, np.pi * v
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), -s * np.cos(phi)], -1)


def bilinear(img, u, v):
    """Mitsuba's bilinear lookup of a (H, W, 3) lat-long image at (u, v')."""
    h, w = img.shape[:2]
    fx = u * w - 0.5
    fy = v * (h - 1)
    x0 = np.floor(fx)
    y0 = np.clip(np.floor(fy), 0, h - 2)
    wx, wy = (fx - x0)[..., None], np.clip(fy - y0, 0.0, 1.0)[..., None]
    x0i = x0.astype(np.int64) % w
    x1i = (x0i + 1) % w
    y0i = y0.astype(np.int64) * w
    flat = img.reshape(-1, img.shape[-1])
    take = lambda i: np.take(flat, i, axis=0)  # noqa: E731  (faster than 2-D fancy indexing)
    top = take(y0i + x0i) * (1 - wx) + take(y0i + x1i) * wx
    bot = take(y0i + w + x0i) * (1 - wx) + take(y0i + w + x1i) * wx
    return top * (1 - wy) + bot * wy


class Pyramid:
    """Solid-angle-prefiltered levels of a lat-long map, each in Mitsuba's layout.

    Level l (W / 2^l columns, rows at the poles) holds the sin-theta-weighted
    average of the level-0 bilinear radiance over its texel's footprint, so a
    lookup at angular size s averages the map over about s.
    """

    def __init__(self, img: np.ndarray):
        img = np.asarray(img, dtype=np.float64)
        self.levels = [img]
        h, w = img.shape[:2]
        self.texel = 2.0 * np.pi / w  # level-0 angular texel size
        while w >= 8 and h >= 5:
            w, h = w // 2, (h - 1) // 2 + 1
            self.levels.append(self._average(img, h, w))

    @staticmethod
    def _average(img, h, w, sub=8):
        off = (np.arange(sub) + 0.5) / sub - 0.5
        u = ((np.arange(w)[:, None] + 0.5 + off[None]) / w).reshape(-1)  # (w*sub,)
        v = ((np.arange(h)[:, None] + off[None]) / (h - 1)).reshape(-1)  # (h*sub,)
        inside = (v >= 0) & (v <= 1)
        v = np.clip(v, 0.0, 1.0)
        uu, vv = np.meshgrid(u, v)
        rad = bilinear(img, uu, vv)
        wt = (np.sin(np.pi * vv) + 1e-9) * inside[:, None]
        num = (rad * wt[..., None]).reshape(h, sub, w, sub, 3).sum((1, 3))
        den = wt.reshape(h, sub, w, sub).sum((1, 3))
        return num / den[..., None]

    def lookup(self, dirs, size):
        """Radiance (..., 3) along ``dirs`` averaged over an angular size ``size`` (...)."""
        u, v = dir_to_uv(dirs)
        lev = np.clip(np.log2(np.maximum(size, 1e-12) / self.texel), 0, len(self.levels) - 1)
        lo = np.floor(lev).astype(np.int64)
        out = np.zeros(dirs.shape)
        for i, img in enumerate(self.levels):
            wgt = np.where(lo == i, 1.0 - (lev - lo), 0.0) + np.where(lo + 1 == i, lev - lo, 0.0)
            sel = wgt > 0
            if sel.any():
                out[sel] += wgt[sel][:, None] * bilinear(img, u[sel], v[sel])
        return out


# ----------------------------------------------------------------------------- the sun
def split_sun(img: np.ndarray):
    """(sun_dir (Ls, 3), sun_irradiance (Ls, 3), sky image): the map = sky + sun excess."""
    img = np.asarray(img, dtype=np.float64)
    h, w = img.shape[:2]
    lum = img @ _LUM
    thresh = SUN_RATIO * max(float(np.median(lum)), 1e-12)
    order = np.argsort(lum, axis=None)[::-1][:SUN_MAX_TEXELS]
    order = order[lum.reshape(-1)[order] > thresh]
    if order.size == 0 or h < 2:
        return np.zeros((0, 3)), np.zeros((0, 3)), img
    mask = np.zeros(h * w, bool)
    mask[order] = True
    mask = mask.reshape(h, w)
    sky = img.copy()
    for r, c in zip(*np.nonzero(mask)):  # fill with the mean of the non-sun neighbours
        rs = np.clip(np.arange(r - 1, r + 2), 0, h - 1)
        cs = np.arange(c - 1, c + 2) % w
        nb = [(i, j) for i in rs for j in cs if not mask[i, j]]
        sky[r, c] = np.mean([img[i, j] for i, j in nb], axis=0) if nb else 0.0
    excess = img - sky
    # Fine lattice (SUN_SUB per texel) over each sun texel's bilinear support.
    rows, cols = np.nonzero(mask)
    k = SUN_SUB
    fine = set()
    for r, c in zip(rows, cols):
        for fr in range((r - 1) * k, (r + 1) * k):
            if 0 <= fr < (h - 1) * k:
                for fc in range(int((c - 0.5) * k), int((c + 1.5) * k)):
                    fine.add((fr, fc % (w * k)))
    fr, fc = np.array(sorted(fine)).T
    u = (fc + 0.5) / (w * k)
    v = (fr + 0.5) / ((h - 1) * k)
    rad = np.maximum(bilinear(excess, u, v), 0.0)
    d_omega = np.sin(np.pi * v) * (np.pi / ((h - 1) * k)) * (2 * np.pi / (w * k))
    dirs = uv_to_dir(u, v)
    e = rad * d_omega[:, None]
    wl = e @ _LUM
    cell = (fr // (k // SUN_CELL)) * (w * SUN_CELL) + fc // (k // SUN_CELL)
    ids, inv = np.unique(cell, return_inverse=True)
    irr = np.zeros((ids.size, 3))
    np.add.at(irr, inv, e)
    cen = np.zeros((ids.size, 3))
    np.add.at(cen, inv, dirs * wl[:, None])
    keep = irr @ _LUM > 1e-6 * max(float((irr @ _LUM).sum()), 1e-300)
    cen = cen[keep]
    return cen / np.linalg.norm(cen, axis=-1, keepdims=True), irr[keep], sky


def env_lights(env_type: str, image: np.ndarray, constant: np.ndarray) -> EnvLights | None:
    """The split environment, or None for a black one."""
    if env_type == "envmap":
        sun_dir, sun_irr, sky = split_sun(image)
        return EnvLights(sun_dir, sun_irr, Pyramid(sky))
    rad = np.asarray(constant, dtype=np.float64)
    if env_type != "constant" or not np.any(rad > 0):
        return None
    return EnvLights(np.zeros((0, 3)), np.zeros((0, 3)), Pyramid(np.broadcast_to(rad, (2, 4, 3))))


# ---------------------------------------------------------------------- the sky stencil
#: Cosine tables: angles between n and r (0 .. pi/2) at which Q and the centroids are tabulated.
N_THETA = 129
_FINE = 8  # sub-cells per cell side when tabulating


def _cells(sub, sub_phi=None):
    """Sub-cells (``sub`` in alpha x ``sub_phi`` in phi per cell, consecutive) of the stencil
    about +z in (cos alpha, phi, d cos, d phi, cell id) and the number of cells: rings in
    alpha (``RING_EDGES``), each cut into azimuthal sectors, one centred on phi = 0."""
    sub_phi = sub if sub_phi is None else sub_phi
    ct, ph, dct, dph, cell = [], [], [], [], []
    n = 0
    for a0, a1 in zip(RING_EDGES[:-1], RING_EDGES[1:]):
        mid = 0.5 * (a0 + a1)
        nphi = 1 if a0 == 0 else int(np.clip(round(2 * np.pi * np.sin(mid) / (a1 - a0)),
                                             MIN_PHI, MAX_PHI))
        ca = np.cos(np.linspace(a0, a1, sub + 1))
        for j in range(nphi):
            for sa in range(sub):
                for sp in range(sub_phi):
                    ct.append(0.5 * (ca[sa] + ca[sa + 1]))  # equal-area midpoint in cos
                    ph.append(2 * np.pi * (j + (sp + 0.5) / sub_phi - 0.5) / nphi)
                    dct.append(ca[sa] - ca[sa + 1])
                    dph.append(2 * np.pi / nphi / sub_phi)
                    cell.append(n)
            n += 1
    return tuple(np.array(a) for a in (ct, ph, dct, dph, cell)) + (n,)


def _tables():
    """Per cell and angle theta_o between n and r: Q = int_cell max(n.w, 0) dw, the unit
    direction of the cos-weighted centroid (local frame: r = +z, n in the xz plane) and
    the cell's angular size sqrt(solid angle)."""
    ct, ph, dct, dph, cell, n = _cells(_FINE)
    st = np.sqrt(np.maximum(1.0 - ct * ct, 0.0))
    dw = dct * dph
    th = np.linspace(0.0, np.pi / 2, N_THETA)
    q = np.zeros((N_THETA, n))
    cen = np.zeros((N_THETA, n, 3))
    size = np.zeros((N_THETA, n))
    d = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1)
    for t in range(N_THETA):
        w = np.maximum(d @ np.array([np.sin(th[t]), 0.0, np.cos(th[t])]), 0.0) * dw
        q[t] = np.bincount(cell, w, n)
        size[t] = np.sqrt(np.bincount(cell, dw, n))
        for i in range(3):
            cen[t, :, i] = np.bincount(cell, w * d[:, i], n)
    nl = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)
    norm = np.linalg.norm(cen, axis=-1, keepdims=True)
    cen = np.where(norm > 0, cen / np.where(norm > 0, norm, 1.0), nl[:, None])
    return q, cen, size


_tables = functools.cache(_tables)  # built on first use (~0.1 s), not at import


def lit_by_environment(scene, material) -> bool:
    """Whether the scene's environment lights some opaque (brdf) lobe of ``material``."""
    return scene.environment.type != "black" and any(
        lb.kind == "brdf" for lb in material.lobe_objects)


def unlit(scene, material) -> str | None:
    """Why the material's opaque lobes get no light in ``scene`` (naming the keys), or None."""
    opaque = [lb.name for lb in material.lobe_objects if lb.kind == "brdf"]
    if not opaque:
        return None
    power = [getattr(lt, "intensity", None) or getattr(lt, "irradiance", None)
             for lt in scene.lights]
    if any(max(p) > 0 for p in power):
        return None
    env = scene.environment
    if env.type == "envmap" and env.scale > 0:
        return None  # an all-black map is caught when it is read
    if env.type == "constant" and env.scale > 0 and max(env.radiance) > 0:
        return None
    lights = ("scene.lights is empty" if not scene.lights else
              "every scene.lights[i].intensity/irradiance is zero")
    env_text = {"black": 'scene.environment.type = "black"',
                "constant": "scene.environment.radiance (x scale) is zero",
                "envmap": "scene.environment.scale is zero"}[env.type]
    return (f"the opaque lobe(s) {opaque} get no light: {lights} and {env_text}; "
            "add a light or an environment")


#: Nodes in theta_o (0 .. pi/2, uniform) at which a lobe is evaluated on the stencil.
#: The renderer evaluates the lobe once per node and cell (T x N values per step, not
#: one per env sample and cell) and interpolates cos_o x lobe linearly in theta_o per
#: sample; ``benchmarks/envlight.py`` measures the error against exact per-sample
#: evaluation and against Mitsuba per node count (``lobe_nodes`` there).
LOBE_NODES = 97


#: Points per cell (alpha x phi) at which the lobe is averaged: the sky's radiance is
#: prefiltered to the cell's size, the lobe is not, and a microfacet lobe at grazing view
#: is a stripe narrower than a sector (2 m cos(theta_o) across it). One point (the
#: cell's centroid) was -/+17 % off at theta_o = 89 degrees for Beckmann m = 0.1 (sector
#: edge / centre on the stripe); ``benchmarks/envlight.py`` measures the choices.
LOBE_SUB = (2, 4)


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
def node_geometry(nodes: int = LOBE_NODES, sub: tuple = LOBE_SUB):
    """``Cosines`` (T, N, M) of M points per stencil cell at the theta_o nodes and the
    weights (T, N, M) by which the renderer sums a lobe there: cos_o x the point's
    share of the cell's Q = int max(cos_i, 0) dw. The points are the cos-weighted
    centroids of ``sub`` = (alpha, phi) groups of the ``_FINE`` sub-cells that
    tabulate Q, so the shares sum to exactly 1 where Q > 0 (Lambert stays exact).
    Local frame: r = +z, n = (sin t, 0, cos t), wo = (sin 2t, 0, cos 2t). Points
    that receive nothing get the normal as a harmless stand-in direction (weight 0).
    """
    from .bsdf.base import cosines

    sa, sp = sub
    if _FINE % sa or _FINE % sp:
        raise ValueError(f"sub = {sub}: each must divide _FINE = {_FINE}")
    ct, ph, dct, dph, cell, n_cells = _cells(_FINE)
    st = np.sqrt(np.maximum(1.0 - ct * ct, 0.0))
    d = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1)
    dw = dct * dph
    k = np.arange(ct.size) % (_FINE * _FINE)
    gid = cell * (sa * sp) + (k // _FINE) // (_FINE // sa) * sp + (k % _FINE) // (_FINE // sp)
    ng = n_cells * sa * sp
    th = node_angles(nodes)
    w = np.zeros((nodes, ng))
    cen = np.zeros((nodes, ng, 3))
    for t in range(nodes):
        wf = np.maximum(d @ np.array([np.sin(th[t]), 0.0, np.cos(th[t])]), 0.0) * dw
        w[t] = np.bincount(gid, wf, ng)
        for i in range(3):
            cen[t, :, i] = np.bincount(gid, wf * d[:, i], ng)
    n = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)[:, None]
    wo = np.stack([np.sin(2 * th), np.zeros_like(th), np.cos(2 * th)], -1)[:, None]
    norm = np.linalg.norm(cen, axis=-1, keepdims=True)
    lit = w > 0
    cen = np.where(lit[..., None], cen / np.where(norm > 0, norm, 1.0), n)
    w = w.reshape(nodes, n_cells, -1)
    tot = w.sum(-1, keepdims=True)
    w = np.where(tot > 0, w / np.where(tot > 0, tot, 1.0), 0.0) * np.cos(th)[:, None, None]
    cos = cosines(np.broadcast_to(n, cen.shape), cen, np.broadcast_to(wo, cen.shape))
    return _reshaped(cos, (nodes, n_cells, sa * sp)), w


def _reshaped(cos, shape):
    return type(cos)(*(np.reshape(a, shape) for a in cos))


#: Env samples per block of the sky sum: a block holds samples of one theta_o node only,
#: so the sum is one batched matrix product (blocks x (B x 3, N) @ (N, columns)) with
#: the lobe's values at two nodes per block, not a per-sample gather (~20x slower here).
BLOCK = 16


def blocks(node, block: int = BLOCK):
    """Blocked order of env samples by node: (order (R,) sample index or -1 for padding,
    block_node (R / block,)); each block's samples share one node."""
    node = np.asarray(node)
    order, bnode = [], []
    srt = np.argsort(node, kind="stable")
    bounds = np.searchsorted(node[srt], np.arange(int(node.max(initial=-1)) + 2))
    for j in range(bounds.size - 1):
        idx = srt[bounds[j]:bounds[j + 1]]
        if idx.size:
            nb = -(-idx.size // block)
            order.append(np.concatenate([idx, np.full(nb * block - idx.size, -1)]))
            bnode += [j] * nb
    if not order:
        return np.zeros(0, np.int64), np.zeros(0, np.int32)
    return np.concatenate(order), np.asarray(bnode, np.int32)


def sky_sum(h, block_node, frac, c):
    """Per env sample sum over cells of the node-interpolated h times c (JAX).

    h: (..., T, N) or (..., T, N, 3) lobe x ``node_geometry`` weight (an RGB
    last axis for coloured lobes); block_node (nb,); frac (R,) the sample's
    position between its block's node and the next; c (nb, B x 3, N): samples
    x RGB rows (``sky_table``, blocked by ``blocks``). Returns (..., R, 3).
    """
    import jax.numpy as jnp

    rgb = h.shape[-1] == 3 and h.shape[-2] == c.shape[-1]
    nd = 3 if rgb else 2
    lead = h.shape[:h.ndim - nd]
    nb, rows, n = c.shape
    b = rows // 3
    # (T, N, [3,] K): the lobe's columns (lead axes) last, for a plain batched matmul.
    ht = jnp.moveaxis(h.reshape((-1,) + h.shape[-nd:]), 0, -1)
    h0 = jnp.take(ht, block_node, axis=0)
    h1 = jnp.take(ht, block_node + 1, axis=0)
    k = ht.shape[-1]
    if rgb:  # per channel: (nb, B, 3, N) x (nb, N, 3, K)
        c4 = c.reshape(nb, b, 3, n).astype(h.dtype)
        out = jnp.einsum("bscn,bnck->bsck", c4, jnp.concatenate([h0, h1], -1))
    else:
        out = jnp.einsum("brn,bnk->brk", c.astype(h.dtype), jnp.concatenate([h0, h1], -1))
        out = out.reshape(nb, b, 3, 2 * k)
    f = frac.reshape(nb, b, 1, 1).astype(h.dtype)
    val = out[..., :k] + (out[..., k:] - out[..., :k]) * f  # (nb, B, 3, K)
    val = jnp.moveaxis(val.reshape(nb * b, 3, k), -1, 0)  # (K, R, 3)
    return val.reshape(lead + (nb * b, 3))


def _flat_levels(sky: Pyramid):
    """The pyramid's levels in one flat (sum h w, 3) array with per-level (h, w, offset)."""
    flat = np.concatenate([lv.reshape(-1, 3) for lv in sky.levels])
    shp = np.array([lv.shape[:2] for lv in sky.levels])
    off = np.concatenate([[0], np.cumsum(shp[:, 0] * shp[:, 1])[:-1]])
    return flat, shp[:, 0], shp[:, 1], off


@functools.cache
def _table_fn():
    """The jitted per-chunk tabulation of ``sky_table`` (JAX, float64)."""
    import jax
    import jax.numpy as jnp

    def bil(flat, h, w, off, u, v):  # Mitsuba's bilinear lookup, per cell's level
        hf, wf = h.astype(u.dtype), w.astype(u.dtype)
        fx, fy = u * wf - 0.5, v * (hf - 1)
        x0 = jnp.floor(fx)
        y0 = jnp.clip(jnp.floor(fy), 0.0, hf - 2)
        wx, wy = (fx - x0)[..., None], jnp.clip(fy - y0, 0.0, 1.0)[..., None]
        x0i = jnp.mod(x0.astype(jnp.int32), w)
        x1i = jnp.mod(x0i + 1, w)
        y0i = y0.astype(jnp.int32) * w + off
        t = lambda i: jnp.take(flat, i, axis=0)  # noqa: E731
        top = t(y0i + x0i) * (1 - wx) + t(y0i + x1i) * wx
        bot = t(y0i + w + x0i) * (1 - wx) + t(y0i + w + x1i) * wx
        return top * (1 - wy) + bot * wy

    def fn(nrm, wo, wt, q_tab, cen_tab, flat, lh, lw, loff, lo, fl):
        co = jnp.clip(jnp.sum(nrm * wo, -1), 0.0, 1.0)
        r = 2.0 * co[:, None] * nrm - wo
        t = nrm - co[:, None] * r
        tn = jnp.linalg.norm(t, axis=-1, keepdims=True)
        a = jnp.where(jnp.abs(r[:, :1]) < 0.9, jnp.array([1.0, 0, 0]), jnp.array([0, 1.0, 0]))
        t0 = jnp.cross(a, r)
        t0 = t0 / jnp.linalg.norm(t0, axis=-1, keepdims=True)
        t = jnp.where(tn > 1e-9, t / jnp.where(tn > 0, tn, 1.0), t0)
        b = jnp.cross(r, t)
        th = jnp.arccos(co)
        x = th / (jnp.pi / 2) * (q_tab.shape[0] - 1)
        i0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, q_tab.shape[0] - 2)
        f = (x - i0.astype(x.dtype))[:, None]
        q = q_tab[i0] * (1 - f) + q_tab[i0 + 1] * f  # (C, N)
        cl = cen_tab[i0] * (1 - f[..., None]) + cen_tab[i0 + 1] * f[..., None]
        d = cl[..., :1] * t[:, None] + cl[..., 1:2] * b[:, None] + cl[..., 2:] * r[:, None]
        d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        u = jnp.arctan2(d[..., 0], -d[..., 2]) / (2.0 * jnp.pi)
        u = u - jnp.floor(u)
        v = jnp.arctan2(jnp.hypot(d[..., 0], d[..., 2]), d[..., 1]) / jnp.pi
        rad = (bil(flat, lh[lo], lw[lo], loff[lo], u, v) * (1 - fl)[:, None]
               + bil(flat, lh[lo + 1], lw[lo + 1], loff[lo + 1], u, v) * fl[:, None])
        lit = (q > 0) & (jnp.sum(d * nrm[:, None], -1) > 0)
        c = jnp.where(lit[..., None], rad * (q * wt[:, None] / co[:, None])[..., None], 0.0)
        return jnp.swapaxes(c, 1, 2)  # (C, 3, N)

    return jax.jit(fn)


def sky_table(sky: Pyramid, normal, view, weight=None, nodes: int = LOBE_NODES,
              chunk: int = 2048):
    """Env samples in blocks (``blocks``) and their sky-stencil weights.

    ``normal``, ``view`` (S, 3): unit normal and unit direction to the camera
    (n . view > 0); ``weight`` (S,) the sample's quadrature weight (default 1).
    Returns (order (R,): sample index, -1 for padding; block_node (nb,); frac
    (R,); c (nb, B x 3, N)) with c = weight x Q(theta_o) x the prefiltered
    radiance at the cell's cos-weighted centroid / cos_o, per sample, RGB
    channel and cell; Q = int_cell max(cos_i, 0) dw is tabulated per cell
    (exact for a constant sky), and the 1/cos_o undoes the cos_o that
    ``node_geometry`` folds into the lobe (smooth up to the horizon).
    """
    import jax.numpy as jnp

    q_tab, cen_tab, size_tab = _tables()
    flat, lh, lw, loff = _flat_levels(sky)
    lev = np.clip(np.log2(size_tab[0] / sky.texel), 0, len(sky.levels) - 1)  # theta-free
    lo = np.minimum(np.floor(lev).astype(np.int32), max(len(sky.levels) - 2, 0))
    fl = lev - lo
    if len(sky.levels) == 1:  # a single level: look it up twice
        lh, lw, loff = (np.concatenate([a, a]) for a in (lh, lw, loff))
    lh, lw, loff = (np.asarray(a, np.int32) for a in (lh, lw, loff))
    weight = np.ones(normal.shape[0]) if weight is None else np.asarray(weight, np.float64)
    node, fr = _node_of(np.arccos(np.clip(np.sum(normal * view, -1), 0.0, 1.0)), nodes)
    order, bnode = blocks(node)
    pad = order < 0
    pick = np.where(pad, 0, order)
    nrm = np.where(pad[:, None], [0.0, 0.0, 1.0], normal[pick] if pick.size else np.zeros((0, 3)))
    wo = np.where(pad[:, None], [0.0, 0.0, 1.0], view[pick] if pick.size else np.zeros((0, 3)))
    wt = np.where(pad, 0.0, weight[pick] if pick.size else 0.0)
    frac = np.where(pad, 0.0, fr[pick] if pick.size else 0.0)
    fn = _table_fn()
    consts = [jnp.asarray(a) for a in (q_tab, cen_tab, flat, lh, lw, loff, lo, fl)]
    r = order.size
    c = np.zeros((r, 3, size_tab.shape[1]))
    step = min(chunk, r) if r else 1
    extra = (-r) % step  # every chunk the same shape: one compilation
    nrm = np.concatenate([nrm, np.tile([[0.0, 0.0, 1.0]], (extra, 1))])
    wo = np.concatenate([wo, np.tile([[0.0, 0.0, 1.0]], (extra, 1))])
    wt = np.concatenate([wt, np.zeros(extra)])
    for i in range(0, r, step):
        k = min(step, r - i)
        c[i:i + k] = np.asarray(fn(*(jnp.asarray(x[i:i + step]) for x in (nrm, wo, wt)),
                                   *consts))[:k]
    return order, bnode, frac, c.reshape(bnode.size, -1, c.shape[-1])

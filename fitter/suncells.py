"""An environment's sun as directional lights on their own samples.

The sun cells (``fitter.envlight``: texels far brighter than the sky, integrated
into directional lights) light every opaque lobe. Near the highlight and the
sun's horizon every sub-pixel sample sees every cell; elsewhere an env sample
sees one merged light (``sun_samples``). The (light, sample) pairs of all
groups are stored flat (``SunCells``), so a renderer evaluates a lobe once for
all of them.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import numpy as np

from .bsdf.base import UNLIT, Cosines, cosines
from .envlight import LUMINANCE


def _rows(index) -> np.ndarray:
    """Active-pixel rows as int32: a float32 fit traces without 64-bit types, where
    an int64 index warned on every trace that it was truncated."""
    return np.asarray(index, dtype=np.int32)


class SunCells(NamedTuple):
    """An environment's sun cells as directional lights on their own samples
    (``sun_samples``): groups i of L_i lights x Q_i samples, stored flat, group
    after group, so that a renderer evaluates a lobe once for all of them
    (``render._sun_unit``: a group each made the lobe's graph again, ~290 of
    env_plastic's ~840 traced operations).

    Attributes:
        index: (sum Q_i,) int32, each sample's active-pixel row.
        cosines: ``Cosines`` (sum L_i Q_i,) of each (light, sample) pair, each
            group's (L_i, Q_i) flattened; with their cotangents or without (a lobe
            then takes them from the cosines; ``sun_samples``).
        weight: per group, (L_i, Q_i) sample weight x cos_i where lit, else 0.
        color: per group, (L_i, 3) each light's irradiance.
    """

    index: Any
    cosines: Cosines
    weight: tuple
    color: tuple

    @classmethod
    def of(cls, groups) -> "SunCells | tuple":
        """The cells of ``groups`` (index (Q,), ``Cosines`` (L, Q), weight (L, Q),
        colour (L, 3)) but those without samples; () if none has any."""
        groups = [g for g in groups if np.shape(g[0])[0]]
        if not groups:
            return ()
        flat = (None if f[0] is None else np.concatenate([np.reshape(a, -1) for a in f])
                for f in zip(*(g[1] for g in groups)))
        return cls(_rows(np.concatenate([np.asarray(g[0]) for g in groups])), Cosines(*flat),
                   tuple(g[2] for g in groups), tuple(g[3] for g in groups))

    def groups(self):
        """(index (Q_i,), ``Cosines`` (L_i, Q_i), weight (L_i, Q_i), colour) of each
        group, as NumPy arrays (views where the cells are on the host; slicing
        device arrays here would compile a kernel per slice)."""
        host = jax.tree_util.tree_map(np.asarray, self)
        q0 = e0 = 0
        for w, col in zip(host.weight, host.color):
            n_l, n_q = np.shape(w)
            cos = host.cosines.map(lambda a: a[e0:e0 + n_l * n_q].reshape(n_l, n_q))  # noqa: B023
            yield host.index[q0:q0 + n_q], cos, w, col
            q0, e0 = q0 + n_q, e0 + n_l * n_q


#: Sun samples: a pixel gets every sub-pixel sample and every sun cell where some sample's
#: normal is within ``SUN_CONE`` rad of the half vector of the sun's centroid direction
#: (the highlight of any lobe: at 0.35 rad off the half vector Phong e = 100 is down to
#: 1e-6 of its peak, Beckmann m = 0.1 to e^-12) or sees the sun within ``SUN_EDGE`` of
#: its horizon; every other pixel sees the cells merged (``clusters``: for a small sun
#: one directional light, their sum at their centroid) from its env samples
#: (``env_samples``: the centre, points across the limb, every sub-sample at the silhouette), where
#: the lobes are smooth on the scale of the sun's 0.05 rad. Against every sample x every
#: cell: at most 1.7e-4 relative (env_phong, env_plastic, interior pixels) with 47 k
#: instead of 138 k sample x 32 cell evaluations for 25 k x 32 + 22 k x 1.
SUN_CONE = 0.35
SUN_EDGE = 0.05
#: Far from the highlight an env sample sees the sun's cells as one light at their
#: centroid, off by ~s^2 / 2 of Lambert's cos-weighted irradiance for cells of
#: luminance-weighted rms angle s about it: within 1.7e-4 of every cell on the probe
#: (its 3 deg sun and the cells' bilinear halo: s = 0.034 rad). A sun spread wider than
#: ``SINGLE_SPREAD`` is merged into lights of at most ``CLUSTER_WIDTH`` rad instead
#: (``clusters``): one light for a 20 deg source (s = 0.127) was 0.8 % off, rho_d 0.0036
#: low at 12.7 stated errors and eta 0.004 at 11.7 (Mitsuba target, the probe's sun made
#: 20 deg wide); with 51 such lights rho_d was within 7e-5 and eta 1.4e-4, each within
#: 1.1 stated errors.
SINGLE_SPREAD = 0.04
CLUSTER_WIDTH = 0.06


#: ``_sun_cells`` works on this many (light, sample) pairs at a time: fresh temporaries
#: of the whole (L, Q) arrays cost page faults here (32 cells x 100 k samples: 3 s
#: whole, 0.2 s in pieces that stay in cache; the same numbers).
SUN_CHUNK = 1 << 16


#: The sun cells' ``Cosines`` fields without their cotangents (``sun_samples``).
_SUN_FIELDS = 6


def _sun_cells(groups, cotangents: bool = False) -> SunCells | tuple:
    """``SunCells`` of ``groups`` (n, v (Q, 3) normals and view directions, w (Q,)
    sample weights, rows (Q,), dirs (L, 3) light directions, irr (L, 3)), those
    with samples, written straight into the flat arrays (no copy of them); with
    the pairs' cotangents where ``cotangents``."""
    groups = [g for g in groups if np.shape(g[0])[0]]
    if not groups:
        return ()
    sizes = [np.shape(g[4])[0] * np.shape(g[0])[0] for g in groups]
    fields = len(Cosines._fields) if cotangents else _SUN_FIELDS
    flat = Cosines(*(np.empty(sum(sizes)) for _ in range(fields)))
    weights = []
    for (n, v, w, _, dirs, _), e0, size in zip(groups, np.cumsum([0] + sizes), sizes):
        n, v, w, dirs = (np.asarray(a, np.float64) for a in (n, v, w, dirs))
        L, Q = dirs.shape[0], n.shape[0]
        cos = flat.map(lambda a: a[e0:e0 + size].reshape(L, Q))  # noqa: B023 (views)
        weight = np.empty((L, Q))
        step = max(1, SUN_CHUNK // max(L, 1))
        for s in range(0, Q, step):
            # cosines' NumPy path broadcast on (L, q): the generic (L, Q, 3) form with
            # np.cross took 6 s of a first env fit's 2k-sample discretisation check.
            part = cosines(n[None, s:s + step], dirs[:, None], v[None, s:s + step])
            lit = (part.cos_i > 0) & (part.cos_o > 0)
            for out, a, b in zip(cos[:fields], part, UNLIT):
                out[:, s:s + step] = np.where(lit, a, b)
            weight[:, s:s + step] = np.where(lit, w[s:s + step] * cos.cos_i[:, s:s + step], 0.0)
        weights.append(weight)
    return SunCells(_rows(np.concatenate([np.asarray(g[3]) for g in groups])), flat,
                    tuple(weights), tuple(np.asarray(g[5], np.float64) for g in groups))


def _centroid(sun_dir, sun_irradiance):
    """(each cell's luminance (L,), the unit luminance-weighted centroid (3,))."""
    lum = sun_irradiance @ LUMINANCE
    lc = (sun_dir * lum[:, None]).sum(0)
    return lum, lc / np.linalg.norm(lc)


def clusters(sun_dir, sun_irradiance, width: float = CLUSTER_WIDTH):
    """The sun's cells (L, 3) as the far samples' lights (C, 3): one at their
    luminance-weighted centroid with every cell's irradiance where their rms angle
    about it is at most ``SINGLE_SPREAD``, else one per square of ``width`` rad in the
    tangent plane at the centroid (each at its cells' centroid, their summed
    irradiance)."""
    lum, lc = _centroid(sun_dir, sun_irradiance)
    spread = np.sqrt(lum @ np.sum((sun_dir - lc) ** 2, -1) / max(float(lum.sum()), 1e-300))
    if spread <= SINGLE_SPREAD:
        return lc[None], sun_irradiance.sum(0, keepdims=True)
    a = np.array([1.0, 0.0, 0.0]) if abs(lc[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = np.cross(a, lc)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(lc, t1)
    key = np.stack([np.rint(sun_dir @ t1 / width), np.rint(sun_dir @ t2 / width),
                    sun_dir @ lc < 0], -1)  # (a cell behind the centroid's plane apart)
    ids, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    cen = np.zeros((ids.shape[0], 3))
    np.add.at(cen, inv, sun_dir * lum[:, None])
    irr = np.zeros((ids.shape[0], 3))
    np.add.at(irr, inv, sun_irradiance)
    return cen / np.linalg.norm(cen, axis=-1, keepdims=True), irr


def sun_samples(lighting, hit, normal, view, weight, e_rows, e_n, e_v, e_w,
                cotangents: bool = False):
    """The sun's cells on their samples (``SunCells``, ``Geometry.sun``; () without a
    sun): a group of every sample x every cell near the highlight and the sun's
    horizon (of its centroid), one of its ``clusters`` on the env samples elsewhere.

    ``cotangents``: the pairs' cot_i and cot_o kept (16 bytes a pair more) for a
    geometry a solver renders at every step: without them a lobe's derivatives
    took them from the cosines per column (Smith's G1 reads both; env_plastic's sun
    Jacobian per step 45 -> 25 ms); a geometry rendered once (the stated errors'
    finer ones, where the pairs are most of their memory) goes without."""
    if not lighting.sun_dir.shape[0]:
        return ()
    far_dir, far_irr = clusters(lighting.sun_dir, lighting.sun_irradiance)
    lc = _centroid(lighting.sun_dir, lighting.sun_irradiance)[1]
    h = lc + view
    h /= np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-300)
    cn = normal @ lc
    near = hit & ((np.sum(normal * h, -1) > np.cos(SUN_CONE)) | (np.abs(cn) < SUN_EDGE))
    near_pix = near.any(1)
    p, k = np.nonzero(hit & near_pix[:, None])
    far = ~near_pix[e_rows]
    return _sun_cells([
        (normal[p, k], view[p, k], weight[k], p, lighting.sun_dir, lighting.sun_irradiance),
        (e_n[far], e_v[far], e_w[far], e_rows[far], far_dir, far_irr)], cotangents)

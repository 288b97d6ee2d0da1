"""The environment as light on opaque lobes: a fixed set of directions per sample.

Mitsuba's ``envmap``/``constant`` emitter lights an opaque sphere with
L_o(wo) = int f(wi, wo) L(wi) cos_i dwi over the hemisphere (direct light is
the whole answer: a convex sphere sees no other part of itself). The
radiance L is the bilinearly interpolated latitude-longitude map
(``fitter.environment``; a map wider than ``LIGHT_WIDTH`` lights them from its
pyramid level at most that wide, ``light_map``). It is split in two, both tabulated once per scene
(material-independent, float64 NumPy):

* **Sun lights.** Texels brighter than ``SUN_RATIO`` x the map's median
  luminance (at most ``SUN_MAX_TEXELS``) carry their excess over the
  surrounding sky. The bilinear image of that excess is integrated on
  half-texel cells (``SUN_SUB`` x ``SUN_SUB`` sub-samples per texel) into
  directional lights -- irradiance = int L dw over the cell, direction its
  radiance-weighted centroid -- which the renderer treats exactly like the
  scene's directional lights (on their own sample sets, every lobe).
* **Sky stencil.** The rest (the map with the sun texels filled in) is
  integrated per *env sample* over a fixed stencil of ~690 cells about the
  sample's mirror direction (``fitter.skystencil``, whose docstring gives the
  scheme and its measured accuracy). Lambert's share is exactly rho/pi x the
  irradiance; every other lobe's is a quadrature whose error against Mitsuba
  ``benchmarks/envlight.py`` measures per discretisation (``Detail``).

Env samples are the pixel centres of pixels wholly on the sphere, k points
of a Gauss rule across the limb in limb pixels (``geometry.ENV_LIMB_COS``,
``fitter.limbrule``) and every hitting sub-pixel sample of silhouette pixels,
weighted by its quadrature weight: the sky term is smooth across the sphere
but for the limb, where it changes across the limb, not along it. The sun lights get every
sub-pixel sample near the highlight and their horizon, one merged light at
the env samples elsewhere (``suncells.sun_samples``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._keep import derived
from .skystencil import (  # noqa: F401
    BLOCK,
    LOBE_NODES,
    LOBE_SUB,
    MAX_PHI,
    MIN_PHI,
    N_THETA,
    RING_EDGES,
    WINDOW,
    Detail,
    blocks,
    node_angles,
    node_geometry,
    sky_sum,
    sky_table,
)

#: A texel is part of the sun when its luminance exceeds this x the median.
SUN_RATIO = 20.0
#: At most this many sun texels (the brightest), counted by solid angle in texels at the
#: equator (``_row_shares``); the rest stays in the sky. A 3 deg sun at the zenith is the
#: whole pole row of the map (128 texels of ~1/40 of one at the equator): counted one a
#: texel, half of it stayed in the sky stencil, and env_plastic's rho_d came out 0.017 low
#: at 4.8 stated errors against Mitsuba (now 0.0005, 0.3), in 300 cells (now 14).
SUN_MAX_TEXELS = 64
#: Sun lights: cells of 1 / SUN_CELL texel, integrated with SUN_SUB sub-samples per texel.
#: A light at a whole texel's centroid (0.049 rad on the 128-wide probe) sharpens a
#: highlight as narrow as Phong e = 300's (0.058 rad): env_phong's e came out 3.2 % low;
#: half-texel cells: 0.6 % (quarter-texel: 0.3 %, at 1.5x the fit time and memory).
SUN_CELL = 2
SUN_SUB = 8
#: On a map wider than this the cells keep their angle (SUN_CELL per texel of this
#: width: ~1.4 deg), a texel at the least, and the sun at most SUN_MAX_TEXELS x
#: SUN_CELL^2 cells (``sun_cells``): on the probe 2048 wide (lit from 512) half-texel
#: cells made ~2 s and 1.2 GB more of a fit than whole ones, Phong e then 302.0 against
#: 301.3 (truth 300).
SUN_CELL_WIDTH = 128
#: The opaque lobes are lit from the map at most this wide: a wider map's pyramid level
#: (``light_map``). The sun split and the stencil were measured on the 128-wide probe,
#: where its ~3 deg sun is a texel; on the same probe 2048 wide the sun's 294 texels
#: exceeded ``SUN_MAX_TEXELS``, the rest of it stayed in the sky stencil, and Phong
#: e = 300 came out 4 % low (7.8 stated errors); a fit took 12 s and 3.9 GB.
LIGHT_WIDTH = 512
#: Relative luminance of linear RGB (ITU-R BT.709 / sRGB primaries): which texel is the sun.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


class EnvLights(NamedTuple):
    """The environment split for the renderer (see the module docstring).

    Attributes:
        sun_dir: (Ls, 3) unit directions towards the sun cells.
        sun_irradiance: (Ls, 3) int L dw of each cell (a directional light's irradiance).
        sky: ``Pyramid`` of the remaining radiance.
    """

    sun_dir: np.ndarray
    sun_irradiance: np.ndarray
    sky: Pyramid
    detail: Detail = Detail()


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


def _column_taps(u, w: int):
    """Mitsuba's bilinear lookup along u of a map ``w`` wide: the columns (x0, x1),
    wrapping, and x1's weight (texel centres at (i + 0.5) / w)."""
    fx = u * w - 0.5
    x0 = np.floor(fx)
    x0i = x0.astype(np.int64) % w
    return x0i, (x0i + 1) % w, fx - x0


def _row_taps(v, h: int):
    """Along v' of a map ``h`` high: the rows (y0, y0 + 1) and the second's weight
    (rows at v' = j / (h - 1), the poles)."""
    fy = v * (h - 1)
    y0 = np.clip(np.floor(fy), 0, h - 2)
    y0i = y0.astype(np.int64)
    return y0i, y0i + 1, np.clip(fy - y0, 0.0, 1.0)


def bilinear(img, u, v):
    """Mitsuba's bilinear lookup of a (H, W, 3) lat-long image at (u, v')."""
    h, w = img.shape[:2]
    x0, x1, wx = _column_taps(u, w)
    y0, y1, wy = _row_taps(v, h)
    wx, wy = wx[..., None], wy[..., None]
    flat = img.reshape(-1, img.shape[-1])
    take = lambda i: np.take(flat, i, axis=0)
    top = take(y0 * w + x0) * (1 - wx) + take(y0 * w + x1) * wx
    bot = take(y1 * w + x0) * (1 - wx) + take(y1 * w + x1) * wx
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
        """Level (h, w, 3): the sin(theta)-weighted mean of ``bilinear(img)`` at sub x sub
        points of each texel's footprint, summed separably (rows, then columns): the
        same sums as one lookup per point, which took 7 s and 4 GB for level 1 of a
        2048-wide map."""
        hi, wi = img.shape[:2]
        off = (np.arange(sub) + 0.5) / sub - 0.5
        v = (np.arange(h)[:, None] + off[None]) / (h - 1)  # (h, sub)
        vc = np.clip(v, 0.0, 1.0)
        wt = (np.sin(np.pi * vc) + 1e-9) * ((v >= 0) & (v <= 1))
        y0, y1, wy = _row_taps(vc, hi)
        rows = np.zeros((h, wi, img.shape[-1]))  # the weighted rows at each level row
        for b in range(sub):
            rows += (wt[:, b] * (1 - wy[:, b]))[:, None, None] * img[y0[:, b]]
            rows += (wt[:, b] * wy[:, b])[:, None, None] * img[y1[:, b]]
        x0, x1, wx = _column_taps((np.arange(w)[:, None] + 0.5 + off[None]) / w, wi)  # (w, sub)
        num = np.zeros((h, w, img.shape[-1]))
        for a in range(sub):
            num += (1 - wx[:, a])[None, :, None] * rows[:, x0[:, a]]
            num += wx[:, a][None, :, None] * rows[:, x1[:, a]]
        return num / (sub * wt.sum(1))[:, None, None]

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


def light_map(image: np.ndarray, width: int | None = None) -> np.ndarray:
    """``image`` (H, W, 3), or where W > ``width`` (default ``LIGHT_WIDTH``) its first
    pyramid level at most ``width`` wide: each texel the sin(theta)-weighted mean of
    the map's bilinear radiance over its footprint (``Pyramid._average``, a point per
    texel of the map at least), so int L dw is kept and a sun no smaller than a texel
    stays whole."""
    width = LIGHT_WIDTH if width is None else width
    h, w = image.shape[:2]
    if w <= width:
        return image
    while w > width and w >= 8 and h >= 5:
        w, h = w // 2, (h - 1) // 2 + 1
    return Pyramid._average(np.asarray(image, dtype=np.float64), h, w,
                            sub=max(8, -(-image.shape[1] // w)))


# ----------------------------------------------------------------------------- the sun
def sun_cells(width: int, cell: int = SUN_CELL) -> tuple:
    """(cells per texel, most sun texels) of a map ``width`` wide for ``split_sun``'s
    ``cell`` at SUN_CELL_WIDTH (``FINER_SUN``'s doubles the default's cells per texel,
    over the same texels)."""
    per = max(1, SUN_CELL * SUN_CELL_WIDTH // max(width, SUN_CELL_WIDTH))
    return max(1, per * cell // SUN_CELL), SUN_MAX_TEXELS * SUN_CELL ** 2 // per ** 2


def _row_shares(h: int) -> np.ndarray:
    """Each row's texel solid angle over the equator's, (h,): sin(theta) at the row (a
    pole row, at theta = 0 or pi, at half a row from it)."""
    return np.sin(np.pi * np.clip(np.arange(h), 0.5, h - 1.5) / (h - 1))


def split_sun(img: np.ndarray, cell: int = SUN_CELL, sub: int = SUN_SUB,
              most: int = SUN_MAX_TEXELS):
    """(sun_dir (Ls, 3), sun_irradiance (Ls, 3), sky image): the map = sky + sun excess.

    ``cell``: sun cells of 1 / cell texel; ``sub``: sub-samples per texel (a multiple
    of cell); ``most``: sun texels at most (the brightest; by solid angle,
    ``_row_shares``)."""
    img = np.asarray(img, dtype=np.float64)
    h, w = img.shape[:2]
    if h < 2:
        return np.zeros((0, 3)), np.zeros((0, 3)), img
    lum = img @ LUMINANCE
    thresh = SUN_RATIO * max(float(np.median(lum)), 1e-12)
    order = np.argsort(lum, axis=None)[::-1]
    order = order[lum.reshape(-1)[order] > thresh]
    # the brightest, up to ``most`` texels' solid angle at the equator
    order = order[np.cumsum(_row_shares(h)[order // w]) <= most]
    if order.size == 0:
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
    # Fine lattice (``sub`` per texel) over each sun texel's bilinear support.
    rows, cols = np.nonzero(mask)
    k = sub
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
    wl = e @ LUMINANCE
    # Cells of about equal solid angle: towards the poles a cell row's cells are merged
    # in longitude (1 / sin(theta) of them: only within 30 degrees of a pole).
    cr = fr // (k // cell)
    merge = np.clip(np.floor(1.0 / np.maximum(np.sin(np.pi * (cr + 0.5) / ((h - 1) * cell)),
                                              1e-300)), 1, w * cell).astype(np.int64)
    cell_id = cr * (w * cell) + (fc // (k // cell)) // merge
    ids, inv = np.unique(cell_id, return_inverse=True)
    irr = np.zeros((ids.size, 3))
    np.add.at(irr, inv, e)
    cen = np.zeros((ids.size, 3))
    np.add.at(cen, inv, dirs * wl[:, None])
    keep = irr @ LUMINANCE > 1e-6 * max(float((irr @ LUMINANCE).sum()), 1e-300)
    cen = cen[keep]
    return cen / np.linalg.norm(cen, axis=-1, keepdims=True), irr[keep], sky


def _unchanging(image) -> bool:
    """Whether ``image`` cannot change under its identity (a device array, a read-only
    NumPy one): values made from it may be kept with it (``_keep.derived``)."""
    return not (isinstance(image, np.ndarray) and image.flags.writeable)


def _light_map_of(image) -> np.ndarray:
    """``light_map`` of ``image`` as float64, kept with an unchanging image: a fit asks
    for one map's lights four times (its geometry, the stated errors')."""
    def make():
        return np.array(light_map(np.asarray(image, np.float64)), np.float64)

    return derived(image, ("light map", LIGHT_WIDTH), make) if _unchanging(image) else make()


def env_lights(env_type: str, image, constant: np.ndarray,
               detail: Detail | None = None, sun: tuple = (SUN_CELL, SUN_SUB)) -> EnvLights | None:
    """The split environment of ``image`` (H, W, 3), a NumPy or device array (the
    same unchanging object again reuses its light map and pyramid), or None for a black one;
    ``detail``: the sky term's discretisation, which ``geometry.build_geometry``
    uses (default ``Detail()``, made per call: ``benchmarks/envlight.py`` varies its
    defaults); ``sun``: (cell, sub) of ``split_sun`` (the sun's discretisation)."""
    detail = Detail() if detail is None else detail
    if env_type == "envmap":
        lit = _light_map_of(image)
        cell, most = sun_cells(lit.shape[1], sun[0])
        sun_dir, sun_irr, sky = split_sun(lit, cell, sun[1], most)

        def pyramid():  # (of the sky, which the sun's cells do not change; a read-only copy)
            levels = Pyramid(np.array(sky))
            for level in levels.levels:
                level.flags.writeable = False
            return levels

        return EnvLights(sun_dir, sun_irr, derived(lit, "pyramid", pyramid) if _unchanging(lit)
                         else pyramid(), detail)
    rad = np.asarray(constant, dtype=np.float64)
    if env_type != "constant" or not np.any(rad > 0):
        return None
    return EnvLights(np.zeros((0, 3)), np.zeros((0, 3)), Pyramid(np.broadcast_to(rad, (2, 4, 3))),
                     detail)


def _black_map(env, base_dir) -> bool:
    """Whether the envmap of ``env`` is 0 in every texel (False where it cannot be read)."""
    from .environment import load_environment

    try:
        return not np.any(np.asarray(load_environment(env, base_dir).image) > 0)
    except Exception:  # noqa: BLE001 (the fit's own read names the problem)
        return False


def lit_by_environment(scene, material) -> bool:
    """Whether the scene's environment lights some opaque (brdf) lobe of ``material``."""
    return scene.environment.type != "black" and bool(material.opaque)


def unlit(scene, material, base_dir: str | None = None) -> str | None:
    """Why the material's opaque lobes get no light in ``scene`` (naming the keys), or None.
    An envmap is read (``environment.load_environment``, kept for the fit) where no
    light shines: a map black in every texel lights nothing either; one that cannot
    be read is left to the read that names the problem."""
    opaque = material.opaque
    if not opaque:
        return None
    power = [getattr(lt, "intensity", None) or getattr(lt, "irradiance", None)
             for lt in scene.lights]
    if any(max(p) > 0 for p in power):
        return None
    env = scene.environment
    if env.type == "envmap" and env.scale > 0 and not _black_map(env, base_dir):
        return None
    if env.type == "constant" and env.scale > 0 and max(env.radiance) > 0:
        return None
    lights = ("scene.lights is empty" if not scene.lights else
              "every scene.lights[i].intensity/irradiance is zero")
    env_text = {"black": 'scene.environment.type = "black"',
                "constant": "scene.environment.radiance (x scale) is zero",
                "envmap": ("scene.environment.scale is zero" if not env.scale > 0 else
                           f"scene.environment.file {env.file!r} is black (no texel above 0)")
                }[env.type]
    return (f"the opaque lobe(s) {opaque} get no light: {lights} and {env_text}; "
            "add a light or an environment")

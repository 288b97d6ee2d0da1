"""Everything about the image that does not depend on the material.

The camera, sphere and lights are known, so ray-sphere hits, normals, view
and light directions, light fall-off and the background behind the sphere
are computed once, in float64 NumPy, when a scene is prepared. The
differentiable renderer then only evaluates BSDFs on these arrays. Only
*active* pixels (those with at least one sub-pixel sample on the sphere)
carry per-sample arrays; the others are pure background.
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._keep import derived
from ._math import to_device
from .bsdf.base import UNLIT, Cosines, cosines
from .camera import (SceneError, camera_rays, film_coordinates, film_samples, pixel_rule,
                     rays_through)
from .compilation_cache import FAST_COMPILE
from .environment import EnvData, lookup
from .limbrule import across_limb
from .scene import DirectionalLight, PointLight, Scene
from .suncells import SunCells, sun_samples

_LOOKUP = jax.jit(lookup, static_argnums=0, compiler_options=FAST_COMPILE)
#: Directions per call of ``_LOOKUP``: the geometries of one fit (the fitted one,
#: the stated errors' finer ones) share one executable, not one each (~0.1 s of
#: compiling each on a first run).
LOOKUP_CHUNK = 1 << 16


def _miss_radiance(env_type: str, env: EnvData, d) -> np.ndarray:
    """Radiance (..., 3) of an envmap from directions ``d`` (..., 3), float64, in
    ``LOOKUP_CHUNK`` pieces (the last padded)."""
    flat = d.reshape(-1, 3)
    n = flat.shape[0]
    out = np.empty((n + (-n) % LOOKUP_CHUNK, 3))
    for i in range(0, n, LOOKUP_CHUNK):
        part = flat[i:i + LOOKUP_CHUNK]
        if part.shape[0] < LOOKUP_CHUNK:  # any unit direction
            part = np.concatenate([part, np.broadcast_to([0.0, 1.0, 0.0],
                                                         (LOOKUP_CHUNK - part.shape[0], 3))])
        out[i:i + LOOKUP_CHUNK] = np.asarray(_LOOKUP(env_type, env, to_device(part)))
    return out[:n].reshape(d.shape)


@functools.partial(jax.jit, static_argnums=3)
def _slabs(c, src, real, block: int):
    """Rows of the sky table ``c`` (nb, B x 3, N) of the samples ``src`` (R,), zero
    where not ``real``, as (R / B, B x 3, N): gathered where the table is (the
    device), not copied to the host whole."""
    n = c.shape[-1]
    slabs = jnp.take(c.reshape(-1, 3, n), src, axis=0)
    return jnp.where(real[:, None, None], slabs, 0.0).reshape(-1, 3 * block, n)


class Geometry(NamedTuple):
    """Per-sample arrays of the active pixels (P pixels x K = k*k samples).

    Attributes:
        pixel_index: (P,) int, flat index (row * W + col) of each active pixel.
        hit: (P, K) bool, sample hits the sphere.
        sample_weight: (K,) quadrature weights of the sub-pixel samples (sum 1).
        position, normal, ray_dir: (P, K, 3) hit point, unit outward normal,
            unit camera ray direction (towards the surface). Samples that
            miss hold a harmless stand-in (normal = -ray_dir).
        cosines: ``Cosines`` of (light direction, view direction) per light,
            each (L, P, K); a stand-in normal-incidence pair where unlit.
        light_weight: (L, P, K) sample weight * cos_i * light fall-off (1/r^2
            for point lights, 1 for directional), 0 where the sample misses
            or cos_i <= 0 or cos_o <= 0.
        light_color: (L, 3) RGB intensity (W/sr) or irradiance (W/m^2).
        background: (P, 3) weighted sum of what missing samples see.
        background_image: (H*W, 3) the image with no sphere.
        env_index: (R,) int32, active-pixel row of each env sample (pixel
            centres inside the sphere, hitting sub-pixel samples on its
            silhouette and limb; ``fitter.envlight``), -1 for padding, past
            the last row for a pixel a ``subset`` dropped; (0,)
            without environment light. Samples come in blocks of
            ``envlight.BLOCK`` whose theta_o nodes lie in a window of S
            consecutive nodes (``envlight.blocks``).
        env_node: (R / B, S) int, each block's window of theta_o nodes;
            env_frac (R,) the sample's position in it: its lower node - the
            window's first + the fraction towards the next (``envlight.blocks``).
        env_color: (R / B, B x 3, N), per sample and RGB channel and
            sky-stencil cell int L cos_i dw times the sample's weight in its
            pixel / cos_o (0 for unlit cells and padding).
        env_cosines: ``Cosines`` (T, N, M) of M points per cell at the theta_o
            nodes (cos_o, one per node, repeated over its points) and
            env_node_weight (T, N, M) their weights (``envlight.node_geometry``):
            the lobe is evaluated on these only.
        env_irradiance: (P, 3) the sky's irradiance E (int L cos_i dw) of each
            pixel, summed over the map (``fitter.irradiance``), not the stencil:
            a lobe's uniform part u (``Lobe.uniform``: Lambert's 1/pi) reflects
            u x E, no per-step sum; None without a sky (``sky_lit``).

        sun: the environment's sun cells as directional lights on their own
            sample sets (``SunCells``, ``sun_samples``); () without.
        env_kernels: {lobe name: (P, 3)} the sky's sum of that lobe's kernel per
            pixel (``Lobe.kernel``, ``irradiance.kernel_sums``: per material,
            ``with_kernels``); None: none.
        env_samples: the env samples with a lit sky (rows, normals, views,
            weights) and the sky's pyramid levels, which ``with_kernels`` sums
            over; None once a renderer has prepared the geometry.
    """

    pixel_index: np.ndarray
    hit: np.ndarray
    sample_weight: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    ray_dir: np.ndarray
    cosines: Cosines
    light_weight: np.ndarray
    light_color: np.ndarray
    background: np.ndarray
    background_image: np.ndarray
    env_index: np.ndarray
    env_node: np.ndarray
    env_frac: np.ndarray
    env_color: np.ndarray
    env_cosines: Cosines
    env_node_weight: np.ndarray
    env_irradiance: np.ndarray
    sun: SunCells | tuple = ()
    env_kernels: dict | None = None
    env_samples: tuple | None = None

    @property
    def has_env_samples(self) -> bool:
        """Whether env samples or sun cells point at pixel rows (``subset`` remaps them)."""
        return bool(np.shape(self.env_index)[0] or self.sun)

    @property
    def has_sky(self) -> bool:
        """Whether these pixels have a sky table (the stencil's lobes' sky term)."""
        return bool(self.env_color.shape[0] and self.env_color.shape[1])

    @property
    def sky_lit(self) -> bool:
        """Whether the environment's sky lights these pixels (its irradiance, and a
        sky table where a lobe needs the stencil, ``has_sky``)."""
        return self.env_irradiance is not None

    def kept(self, name: str, make):
        """``make()``, a value that depends on this geometry alone, kept with it
        under ``name`` (``fitter._keep.derived``: read-only, and this geometry
        not kept alive by it). A fit asks for some twice and a repeated fit of
        one problem shares its geometry objects (the renderer's and the fitted
        pixels' geometries are cached)."""
        return derived(self.hit, name, make)

    def subset(self, rows: np.ndarray, own_samples: bool = False,
               shared_sun: bool = False) -> "Geometry":
        """The geometry of the active pixels ``rows`` only (NumPy arrays; the sky
        irradiance of a sky table stays on the device when it is there).

        The env samples' blocks are shared, not copied, unless ``own_samples``:
        then the samples of ``rows`` alone are blocked anew with their rows of
        the sky table (``_own_samples``), so a render sums only theirs. The sun
        cells' pairs are those of ``rows``, or with ``shared_sun`` all of them,
        shared as they are (a dropped pixel's point past the last row), for a
        subset of most pixels: no copy of the pairs, most of an env geometry."""
        per_light = lambda a: np.asarray(a)[:, rows]  # noqa: E731
        pick = lambda a: np.asarray(a)[rows]  # noqa: E731
        # One entry past the last row: a subset's samples of dropped pixels point there.
        inv = np.full(np.asarray(self.hit).shape[0] + 1, -1)
        inv[rows] = np.arange(len(rows))
        # The env samples keep their blocks (c is not copied, 0.5 GB at 128^2): a sample
        # of a dropped pixel points past the last row, where the renderer's scatter drops it.
        idx = np.asarray(self.env_index)
        env_rows = np.where(idx >= 0, inv[np.maximum(idx, 0)], -1)
        env_rows = np.where((idx >= 0) & (env_rows < 0), len(rows), env_rows).astype(np.int32)
        if shared_sun and self.sun:
            sun_rows = inv[np.asarray(self.sun.index)]
            sun = self.sun._replace(
                index=np.where(sun_rows >= 0, sun_rows, len(rows)).astype(np.int32))
        elif self.sun:
            sun = SunCells.of(
                (inv[i][inv[i] >= 0], cs.map(lambda a: a[:, inv[i] >= 0]),  # noqa: B023
                 wt[:, inv[i] >= 0], col) for i, cs, wt, col in self.sun.groups())
        else:
            sun = ()
        env = (_own_samples(self, env_rows, len(rows)) if own_samples and self.has_sky
               else {"env_index": env_rows})
        return self._replace(
            sun=sun, **env, sample_weight=np.asarray(self.sample_weight),
            light_color=np.asarray(self.light_color), **self._pixels(pick, per_light))

    def take(self, rows) -> "Geometry":
        """The active pixels ``rows`` only, by plain indexing: NumPy, or JAX
        inside a traced function (the gather then runs in its executable, not
        as a host copy). Only without env samples and sun cells, whose row
        indices ``subset`` remaps."""
        if self.has_env_samples:
            raise ValueError("take: the geometry has env samples or sun cells; use subset")
        return self._replace(**self._pixels(lambda a: a[rows], lambda a: a[:, rows]))

    def _pixels(self, pick, per_light) -> dict:
        """The per-pixel fields, each picked: (P, ...) by ``pick``, (L, P, ...) by
        ``per_light``."""
        return dict(
            env_irradiance=None if self.env_irradiance is None else pick(self.env_irradiance),
            hit=pick(self.hit),
            env_kernels=None if self.env_kernels is None else {
                k: pick(v) for k, v in self.env_kernels.items()},
            pixel_index=None if self.pixel_index is None else pick(self.pixel_index),
            position=pick(self.position), normal=pick(self.normal), ray_dir=pick(self.ray_dir),
            cosines=self.cosines.map(per_light),
            light_weight=per_light(self.light_weight), background=pick(self.background))


#: Samples per block of a subset's own sky table (``Geometry.subset(own_samples=True)``):
#: a subset's few samples spread over every theta_o window, so blocks of the
#: table's 256 were half padding. env_plastic's cost-profile subset (~5 k samples):
#: 39 blocks of 256, 54 of 128 or 91 of 64 (10.0 k, 6.9 k, 5.8 k rows), the same
#: time per pass (51-55 ms for 6 points), the smallest gather at 64.
SUBSET_BLOCK = 64


def _own_samples(geo: Geometry, env_rows, n_rows: int) -> dict:
    """The env fields of the samples of pixel rows 0 .. ``n_rows`` - 1 only
    (``env_rows``: each sample's new row), blocked anew (``envlight.blocks``)
    with their rows of the sky table; padded to 2^(k/8) blocks, so that one
    compile serves subsets of similar size. Values equal the whole's bit for
    bit: ``blocks`` keeps each sample's hat weights exact, and a sample's
    products with its cells are the same whichever block holds it."""
    from .envlight import blocks

    window, pos = np.asarray(geo.env_node), np.asarray(geo.env_frac)
    nb, s = window.shape
    b = pos.size // max(nb, 1)
    lower = np.minimum(np.floor(pos), s - 2).astype(np.int64)
    node = window[np.arange(pos.size) // b, lower]
    keep = np.nonzero((env_rows >= 0) & (env_rows < n_rows))[0]
    if not keep.size:  # none of theirs: the shared table, every sample dropped
        return {"env_index": env_rows}
    block = SUBSET_BLOCK
    order, window, pos = blocks(node[keep], (pos - lower)[keep], geo.env_node_weight.shape[0],
                                block=block, window=s)
    size = int(np.ceil(2.0 ** (np.ceil(8.0 * np.log2(max(window.shape[0], 1))) / 8.0)))
    pad = size - window.shape[0]
    order = np.concatenate([order, np.full(pad * block, -1)])
    src = keep[np.maximum(order, 0)]
    return dict(env_index=np.where(order < 0, -1, env_rows[src]).astype(np.int32),
                env_node=np.concatenate([window, np.broadcast_to(np.arange(s, dtype=window.dtype),
                                                                 (pad, s))]),
                env_frac=np.concatenate([pos, np.zeros(pad * block)]),
                env_color=_slabs(geo.env_color, src, order >= 0, block))


def intersect_sphere(o, d, center, radius):
    """Nearest hit distance of rays o + t d with the sphere; inf where they miss.

    A ray tangent to the sphere (discriminant exactly 0) counts as a hit.
    """
    oc = o - np.asarray(center, dtype=np.float64)
    b = np.einsum("...i,...i->...", d, oc)
    c = np.einsum("...i,...i->...", oc, oc) - radius * radius
    disc = b * b - c
    hit = disc >= 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    return np.where(hit & (t > 0), t, np.inf)


def light_terms(lights, position):
    """Unit directions to each light (L, ..., 3), fall-off (L, ...) and colour (L, 3)."""
    dirs, falloff, color = [], [], []
    for light in lights:
        if isinstance(light, PointLight):
            to = np.asarray(light.position, dtype=np.float64) - position
            r2 = np.einsum("...i,...i->...", to, to)
            dirs.append(to / np.sqrt(r2)[..., None])
            falloff.append(1.0 / r2)
            color.append(light.intensity)
        elif isinstance(light, DirectionalLight):
            v = -np.asarray(light.direction, dtype=np.float64)
            n = np.linalg.norm(v)
            if not n > 0:
                raise SceneError(f"directional light direction {light.direction} is zero")
            dirs.append(np.broadcast_to(v / n, position.shape))
            falloff.append(np.ones(position.shape[:-1]))
            color.append(light.irradiance)
        else:
            raise SceneError(f"unknown light {light!r}")
    if not dirs:
        return (np.zeros((0,) + position.shape), np.zeros((0,) + position.shape[:-1]),
                np.zeros((0, 3)))
    return np.stack(dirs), np.stack(falloff), np.asarray(color, dtype=np.float64)


#: Pixels wholly on the sphere whose centre sees it at cos(theta_o) below this are
#: sampled across the limb (``LIMB_NODES``): near the limb the glossy reflection of the
#: sky rises steeply (Fresnel, the lobe's horizon cut) across one pixel, and its centre
#: value was 5.7 % below Mitsuba's pixel average over the outermost 5 % of the radius
#: (Torrance-Sparrow m = 0.1 under the probe, 128^2); with 4 x 4 sub-samples 2.0 %
#: (2 x 2 midpoints: 3.2 %).
ENV_LIMB_COS = 0.35
#: A limb pixel's env samples: k points of the Gauss rule across the limb
#: (``limbrule``; k the scene's sub-pixel samples per axis, whose k x k grid it
#: replaces resolves k rows across it), or this many; 0: every sub-pixel sample. The
#: grid's limb held 70 % of env_plastic's env samples; against Mitsuba the rule is as
#: accurate (benchmarks/README.md, envlight).
LIMB_NODES: int | None = None


def env_samples(scene: Scene, hit, t, o, d, weight, pixel_index):
    """Env samples: (row, normal, view, weight) of pixel centres wholly inside the
    sphere (away from the limb), of points across the limb of limb pixels
    (``ENV_LIMB_COS``, ``LIMB_NODES``; every sub-pixel sample where one of the
    points misses) and of every hitting sub-pixel sample of silhouette pixels."""
    sph = scene.sphere
    full = hit.all(axis=1)
    oc, dc = _rays_from_centres(scene, pixel_index[full], np.zeros(2))
    tc = intersect_sphere(oc, dc, sph.center, sph.radius)
    tc = np.where(np.isfinite(tc), tc, 0.0)  # a centre ray between Gauss nodes: tangent
    pos_c = oc + tc[:, None] * dc
    nc = (pos_c - np.asarray(sph.center)) / sph.radius
    nc /= np.linalg.norm(nc, axis=-1, keepdims=True)
    limb = -np.sum(nc * dc, -1) < ENV_LIMB_COS
    centre = np.nonzero(full)[0][~limb]
    many = hit & ~full[:, None]
    l_rows, l_pos, l_ray, l_wts, missed = _across_limb(scene, t, o, d, weight, pixel_index,
                                                       np.nonzero(full)[0][limb])
    many[missed] = True
    edge_p, edge_k = np.nonzero(many)
    rows = np.concatenate([centre, l_rows, edge_p])
    pos = np.concatenate([pos_c[~limb], l_pos, o[edge_p, edge_k] + t[edge_p, edge_k, None]
                          * d[edge_p, edge_k]])
    ray = np.concatenate([dc[~limb], l_ray, d[edge_p, edge_k]])
    normal = (pos - np.asarray(sph.center)) / sph.radius
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    wts = np.concatenate([np.ones(centre.size), l_wts, weight[edge_k]])
    return rows, normal, -ray, wts


def _across_limb(scene: Scene, t, o, d, weight, pixel_index, px):
    """(rows, hit points, ray directions, weights) of the points across the limb
    (``LIMB_NODES``) of each of the pixels ``px`` (rows of the traced arrays, every
    sub-sample a hit), and the pixels where a point misses (given every sub-sample)."""
    sph = scene.sphere
    m = scene.supersampling if LIMB_NODES is None else LIMB_NODES
    none = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    if not m or scene.supersampling < 2 or not px.size:  # (one sub-sample: the centre)
        return none + (px,)
    pos = o[px] + t[px, :, None] * d[px]
    cos_o = -np.sum((pos - np.asarray(sph.center)) * d[px], -1) / sph.radius
    sub = pixel_rule(scene.supersampling, scene.pixel_rule)[0]
    off, w = across_limb(cos_o, weight, sub, m)  # (P, m, 2), (P, m)
    o_l, d_l = _rays_from_centres(scene, pixel_index[px][:, None], off)
    t_l = intersect_sphere(o_l, d_l, sph.center, sph.radius)
    ok = np.isfinite(t_l).all(axis=1)
    p_l = o_l[ok] + t_l[ok][..., None] * d_l[ok]
    return (np.repeat(px[ok], m), p_l.reshape(-1, 3), d_l[ok].reshape(-1, 3),
            w[ok].reshape(-1), px[~ok])


def _rays_from_centres(scene: Scene, flat, offset):
    """Ray origins and directions (..., 3) through the points ``offset`` (..., 2:
    column, row, in pixel units) from the centres of the pixels ``flat`` (...,
    flat indices, broadcast against the offsets' leading axes)."""
    row, col = np.divmod(np.asarray(flat), scene.width)
    return rays_through(scene, *film_coordinates(scene, col + 0.5 + offset[..., 0],
                                                 row + 0.5 + offset[..., 1]))


def _beside(fn):
    """``fn()`` started on a thread (``concurrent.futures``; the thread ends with
    it), in this thread's x64 setting: returns its future's ``result``."""
    x64 = jax.config.jax_enable_x64  # (a new thread starts with the global setting)

    def run():
        with jax.enable_x64(x64):
            return fn()

    pool = ThreadPoolExecutor(1, thread_name_prefix="fitter-geometry")
    future = pool.submit(run)
    pool.shutdown(wait=False)
    return future.result


def build_geometry(scene: Scene, env_type: str, env: EnvData, lighting=None,
                   pixels=None, stencil: bool = True, cotangents: bool = True) -> Geometry:
    """Trace the camera rays against the sphere and tabulate the lights.

    ``lighting``: the environment as light (``fitter.envlight.EnvLights``) or
    None (the opaque lobes see the point/directional lights only); with a
    ``sky`` of None the sun cells alone (no sky tabulation). ``pixels``: flat
    indices (row * W + col) of the only pixels to make active (default all
    that the sphere covers); ``stencil``: tabulate the sky stencil (False where
    every lobe the sky lights is ``Lobe.stencil_free``: its sums alone);
    ``cotangents``: the sun cells keep their pairs' cotangents
    (``suncells.sun_samples``; False for a geometry rendered once).
    """
    sph = scene.sphere
    sel = None if pixels is None else np.unique(np.asarray(pixels, dtype=np.int64))
    o, d = camera_rays(scene, sel)  # (H, W, K, 3), or (P, 1, K, 3) of the pixels asked for
    weight = film_samples(scene, np.zeros(1, np.int64))[2]  # (K,): the same for every pixel
    h, w, k2, _ = d.shape
    # An envmap's compiled lookups (op by op it compiled ~50 kernels, 3 s of a first fit),
    # beside the rays' intersection: the compile releases the interpreter.
    looked_up = _beside(lambda: _miss_radiance(env_type, env, d)) if env_type == "envmap" else None
    t = intersect_sphere(o, d, sph.center, sph.radius)
    hit_all = np.isfinite(t)

    active = hit_all.any(axis=2).reshape(-1)
    pixel_index = np.nonzero(active)[0]  # rows of the traced arrays
    hit = hit_all.reshape(h * w, k2)[pixel_index]
    o_a = o.reshape(h * w, k2, 3)[pixel_index]
    d_a = d.reshape(h * w, k2, 3)[pixel_index]
    t_a = np.where(hit, t.reshape(h * w, k2)[pixel_index], 0.0)
    pos = o_a + t_a[..., None] * d_a
    normal = (pos - np.asarray(sph.center)) / sph.radius
    normal = np.where(hit[..., None], normal, -d_a)
    pos = np.where(hit[..., None], pos, np.asarray(sph.center) + sph.radius * normal)
    # (a constant: no device round trip, where each eager op compiles a kernel)
    miss_rad = (looked_up() if looked_up else  # (H, W, K, 3)
                np.broadcast_to(np.asarray(env.constant, dtype=np.float64), d.shape))
    background_image = np.einsum("hwkc,k->hwc", miss_rad, weight).reshape(h * w, 3)
    miss_a = miss_rad.reshape(h * w, k2, 3)[pixel_index]
    background = np.einsum("pkc,k->pc", np.where(hit[..., None], 0.0, miss_a), weight)

    if sel is not None:  # back to the film's flat indices
        full = np.zeros((scene.width * scene.height, 3))
        full[sel] = background_image
        background_image, pixel_index = full, sel[pixel_index]
    light_dir, falloff, color = light_terms(scene.lights, pos)
    cos = Cosines(*(np.asarray(a) for a in cosines(normal, light_dir, -d_a)))
    lit = hit & (cos.cos_i > 0) & (cos.cos_o > 0)
    cos = Cosines(*(np.where(lit, a, s) for a, s in zip(cos, UNLIT)))
    light_weight = np.where(lit, weight * cos.cos_i * falloff, 0.0)
    tabulated = None
    if lighting is not None:
        from .envlight import node_geometry, sky_table
        from .irradiance import pixel_irradiance

        rows, e_n, e_v, e_w = env_samples(scene, hit, t_a, o_a, d_a, weight, pixel_index)
        ok = np.sum(e_n * e_v, -1) > 0
        det = lighting.detail

        def sky():
            r = rows[ok]
            order, node, frac, e_c = sky_table(lighting.sky, e_n[ok], e_v[ok], e_w[ok],
                                               nodes=det.nodes, rings=det.rings)
            r = np.where(order < 0, -1, r[np.maximum(order, 0)] if r.size else -1)
            cos, nw = node_geometry(det.nodes, tuple(det.sub), det.rings)
            # Every field at the points' (T, N, M), cos_o's too (one per node there): the
            # renderer evaluates the lobe on them flat (``render._env_unit``).
            return r, node, frac, e_c, cos.map(
                lambda a: a if a.shape == nw.shape else np.broadcast_to(a, nw.shape).copy()), nw

        # The sky's tabulation compiled beside the sun's cells (XLA's compile releases the
        # interpreter): env_plastic's first fit ~0.05-0.1 s sooner (benchmarks/README.md).
        tabulated = _beside(sky) if lighting.sky is not None and stencil else None
        sun = sun_samples(lighting, hit, normal, -d_a, weight, rows, e_n, e_v, e_w,
                          cotangents)
        if lighting.sky is not None:
            e_irr = pixel_irradiance(lighting.sky.levels, rows[ok], e_n[ok], e_w[ok],
                                     pixel_index.size)
            samples = (rows[ok], e_n[ok], e_v[ok], e_w[ok], tuple(lighting.sky.levels))
        if tabulated is not None:
            rows, node, frac, e_c, e_cos, e_nw = tabulated()
    if tabulated is None:  # no sky table (no sky, the sun alone, or no lobe's stencil)
        rows, node, frac = np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0)
        e_c, e_nw = np.zeros((0, 0, 0)), np.zeros((0, 0))
        e_cos = Cosines(*(np.zeros((0, 0)),) * len(Cosines._fields))
    if lighting is None or lighting.sky is None:
        e_irr, samples = None, None
        sun = sun if lighting is not None else ()
    # (int32 rows: a float32 fit traces without 64-bit types, where int64 warned)
    return Geometry(pixel_index, hit, weight, pos, normal, d_a, cos, light_weight, color,
                    background, background_image, np.asarray(rows, np.int32), node, frac, e_c,
                    e_cos, e_nw, e_irr,
                    sun, env_samples=samples)


def with_kernels(geo: Geometry, material) -> Geometry:
    """``geo`` with the sky's sum of each of ``material``'s opaque lobes' kernels
    (``Lobe.kernel``) per pixel (``env_kernels``), and without its env samples; as
    it is without a lit sky or such a lobe."""
    from .irradiance import kernel_sums

    samples = geo.env_samples
    geo = geo._replace(env_samples=None)
    kernels = [lb for lb in material.lobe_objects if lb.kind == "brdf" and lb.kernel]
    if samples is None or not kernels:
        return geo
    rows, normal, view, weight, levels = samples
    n = np.shape(geo.hit)[0]
    return geo._replace(env_kernels={lb.name: kernel_sums(levels, lb.kernel, rows, normal,
                                                          view, weight, n) for lb in kernels})

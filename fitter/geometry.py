"""Everything about the image that does not depend on the material.

The camera, sphere and lights are known, so ray-sphere hits, normals, view
and light directions, light fall-off and the background behind the sphere
are computed once, in float64 NumPy, when a scene is prepared. The
differentiable renderer then only evaluates BSDFs on these arrays. Only
*active* pixels (those with at least one sub-pixel sample on the sphere)
carry per-sample arrays; the others are pure background.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .bsdf.base import Cosines, cosines
from .camera import SceneError, camera_rays, film_samples
from .compilation_cache import FAST_COMPILE
from .environment import EnvData, lookup
from .scene import DirectionalLight, PointLight, Scene

_LOOKUP = jax.jit(lookup, static_argnums=0, compiler_options=FAST_COMPILE)


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
        env_index: (S,) int, active-pixel row of each env sample (pixel
            centres inside the sphere, hitting sub-pixel samples on its
            silhouette; ``fitter.envlight``); (0,) without environment light.
        env_cosines: ``Cosines`` of (cell direction, view direction), each
            (S, N): the sky-stencil cells of each env sample that receive
            light (N the most any sample has; the others a stand-in).
        env_color: (S, N, 3) int over the cell of L cos_i dw, times the
            sample's weight in its pixel (0 for stand-ins).

    The environment's sun cells are extra directional lights (the last rows
    of the per-light arrays).
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
    env_cosines: Cosines
    env_color: np.ndarray

    def subset(self, rows: np.ndarray) -> "Geometry":
        """The geometry of the active pixels ``rows`` only (NumPy arrays)."""
        per_light = lambda a: np.asarray(a)[:, rows]  # noqa: E731
        pick = lambda a: np.asarray(a)[rows]  # noqa: E731
        inv = np.full(np.asarray(self.hit).shape[0], -1)
        inv[rows] = np.arange(len(rows))
        env_rows = inv[np.asarray(self.env_index)]
        keep = env_rows >= 0
        env = lambda a: np.asarray(a)[keep]  # noqa: E731
        return self._replace(
            env_index=env_rows[keep], env_cosines=Cosines(*(env(a) for a in self.env_cosines)),
            env_color=env(self.env_color),
            pixel_index=pick(self.pixel_index), hit=pick(self.hit),
            position=pick(self.position), normal=pick(self.normal), ray_dir=pick(self.ray_dir),
            cosines=Cosines(*(per_light(a) for a in self.cosines)),
            light_weight=per_light(self.light_weight), background=pick(self.background),
            sample_weight=np.asarray(self.sample_weight), light_color=np.asarray(self.light_color))


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


def light_terms(lights, position, extra_dirs=(), extra_irradiance=()):
    """Unit directions to each light (L, ..., 3), fall-off (L, ...) and colour (L, 3).

    ``extra_dirs`` / ``extra_irradiance``: further directional lights, given
    by the unit direction *towards* them (the environment's sun cells).
    """
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
    for v, irr in zip(extra_dirs, extra_irradiance):
        dirs.append(np.broadcast_to(np.asarray(v, dtype=np.float64), position.shape))
        falloff.append(np.ones(position.shape[:-1]))
        color.append(irr)
    if not dirs:
        return (np.zeros((0,) + position.shape), np.zeros((0,) + position.shape[:-1]),
                np.zeros((0, 3)))
    return np.stack(dirs), np.stack(falloff), np.asarray(color, dtype=np.float64)


#: Pixels wholly on the sphere whose centre sees it at cos(theta_o) below this get every
#: sub-pixel sample as env samples, like silhouette pixels: near the limb the glossy
#: reflection of the sky rises steeply (Fresnel, the lobe's horizon cut) across one
#: pixel, and its centre value was 5.7 % below Mitsuba's pixel average over the
#: outermost 5 % of the radius (Torrance-Sparrow m = 0.1 under the probe, 128^2); with
#: 4 x 4 sub-samples 2.0 % (2 x 2 midpoints: 3.2 %).
ENV_LIMB_COS = 0.35


def env_samples(scene: Scene, hit, t, o, d, weight, pixel_index):
    """Env samples: (row, normal, view, weight) of pixel centres wholly inside the
    sphere (away from the limb) and of every hitting sub-pixel sample of silhouette
    and limb pixels (``ENV_LIMB_COS``)."""
    sph = scene.sphere
    full = hit.all(axis=1)
    oc, dc = camera_rays(scene.replace(supersampling=1, pixel_rule="midpoint"))
    oc = oc.reshape(-1, 3)[pixel_index[full]]
    dc = dc.reshape(-1, 3)[pixel_index[full]]
    tc = intersect_sphere(oc, dc, sph.center, sph.radius)
    tc = np.where(np.isfinite(tc), tc, 0.0)  # a centre ray between Gauss nodes: tangent
    pos_c = oc + tc[:, None] * dc
    nc = (pos_c - np.asarray(sph.center)) / sph.radius
    nc /= np.linalg.norm(nc, axis=-1, keepdims=True)
    limb = -np.sum(nc * dc, -1) < ENV_LIMB_COS
    centre = np.nonzero(full)[0][~limb]
    many = hit & ~full[:, None]
    many[np.nonzero(full)[0][limb]] = True
    edge_p, edge_k = np.nonzero(many)
    rows = np.concatenate([centre, edge_p])
    pos = np.concatenate([pos_c[~limb], o[edge_p, edge_k] + t[edge_p, edge_k, None]
                          * d[edge_p, edge_k]])
    ray = np.concatenate([dc[~limb], d[edge_p, edge_k]])
    normal = (pos - np.asarray(sph.center)) / sph.radius
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    wts = np.concatenate([np.ones(centre.size), weight[edge_k]])
    return rows, normal, -ray, wts


def build_geometry(scene: Scene, env_type: str, env: EnvData, lighting=None) -> Geometry:
    """Trace the camera rays against the sphere and tabulate the lights.

    ``lighting``: the environment as light (``fitter.envlight.EnvLights``) or
    None (the opaque lobes see the point/directional lights only).
    """
    sph = scene.sphere
    if not sph.radius > 0:
        raise SceneError(f"sphere.radius = {sph.radius} must be > 0")
    cam_to_center = np.subtract(scene.camera.origin, sph.center)
    if scene.camera.type == "perspective" and np.linalg.norm(cam_to_center) <= sph.radius:
        raise SceneError("the camera origin lies inside the sphere")
    for light in scene.lights:
        if isinstance(light, PointLight):
            if np.linalg.norm(np.subtract(light.position, sph.center)) <= sph.radius:
                raise SceneError(f"point light at {light.position} lies inside the sphere")
    o, d = camera_rays(scene)
    _, _, weight = film_samples(scene)
    h, w, k2, _ = d.shape
    t = intersect_sphere(o, d, sph.center, sph.radius)
    hit_all = np.isfinite(t)

    if env_type == "envmap":
        # One compiled lookup: op by op it compiled ~50 kernels (3 s of a first fit).
        miss_rad = np.asarray(_LOOKUP(env_type, env, jnp.asarray(d)))  # (H, W, K, 3)
    else:  # a constant: no device round trip (each eager op compiles a kernel)
        miss_rad = np.broadcast_to(np.asarray(env.constant, dtype=np.float64), d.shape)
    background_image = np.einsum("hwkc,k->hwc", miss_rad, weight).reshape(h * w, 3)

    active = hit_all.any(axis=2).reshape(-1)
    pixel_index = np.nonzero(active)[0]
    hit = hit_all.reshape(h * w, k2)[pixel_index]
    o_a = o.reshape(h * w, k2, 3)[pixel_index]
    d_a = d.reshape(h * w, k2, 3)[pixel_index]
    t_a = np.where(hit, t.reshape(h * w, k2)[pixel_index], 0.0)
    pos = o_a + t_a[..., None] * d_a
    normal = (pos - np.asarray(sph.center)) / sph.radius
    normal = np.where(hit[..., None], normal, -d_a)
    pos = np.where(hit[..., None], pos, np.asarray(sph.center) + sph.radius * normal)
    miss_a = miss_rad.reshape(h * w, k2, 3)[pixel_index]
    background = np.einsum("pkc,k->pc", np.where(hit[..., None], 0.0, miss_a), weight)

    sun = (lighting.sun_dir, lighting.sun_irradiance) if lighting is not None else ()
    light_dir, falloff, color = light_terms(scene.lights, pos, *sun)
    cos = Cosines(*(np.asarray(a) for a in cosines(normal, light_dir, -d_a)))
    lit = hit & (cos.cos_i > 0) & (cos.cos_o > 0)
    stand_in = Cosines(1.0, 1.0, 1.0, 1.0, 1.0, 0.0)
    cos = Cosines(*(np.where(lit, a, s) for a, s in zip(cos, stand_in)))
    light_weight = np.where(lit, weight * cos.cos_i * falloff, 0.0)
    if lighting is not None:
        from .envlight import sky_stencil

        t_h = np.where(hit, t.reshape(h * w, k2)[pixel_index], 0.0)
        rows, e_n, e_v, e_w = env_samples(scene, hit, t_h, o_a, d_a, weight, pixel_index)
        ok = np.sum(e_n * e_v, -1) > 0
        rows, e_n, e_v, e_w = rows[ok], e_n[ok], e_v[ok], e_w[ok]
        e_dir, e_c = sky_stencil(lighting.sky, e_n, e_v)
        e_c *= e_w[:, None, None]
        # Keep only the cells that receive light: lit ones first, as many as the most any has.
        lit = np.any(e_c > 0, axis=-1)
        order = np.argsort(~lit, axis=1, kind="stable")[:, :max(int(lit.sum(1).max()), 1)]
        e_dir = np.take_along_axis(e_dir, order[..., None], 1)
        e_c = np.take_along_axis(e_c, order[..., None], 1)
        e_cos = Cosines(*(np.empty(e_dir.shape[:2]) for _ in Cosines._fields))
        for lo in range(0, e_dir.shape[0], 1024):  # in chunks: cache-sized temporaries
            sl = slice(lo, lo + 1024)
            part = cosines(np.broadcast_to(e_n[sl, None], e_dir[sl].shape), e_dir[sl],
                           np.broadcast_to(e_v[sl, None], e_dir[sl].shape))
            for dst, src in zip(e_cos, part):
                dst[sl] = src
    else:
        rows, e_c = np.zeros(0, np.int64), np.zeros((0, 0, 3))
        e_cos = Cosines(*(np.zeros((0, 0)),) * 6)
    return Geometry(pixel_index, hit, weight, pos, normal, d_a, cos, light_weight, color,
                    background, background_image, rows, e_cos, e_c)

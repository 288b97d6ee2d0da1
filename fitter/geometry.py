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

import jax.numpy as jnp
import numpy as np

from .bsdf.base import Cosines, cosines
from .camera import SceneError, camera_rays, film_samples
from .environment import EnvData, lookup
from .scene import DirectionalLight, PointLight, Scene


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

    def subset(self, rows: np.ndarray) -> "Geometry":
        """The geometry of the active pixels ``rows`` only (NumPy arrays)."""
        per_light = lambda a: np.asarray(a)[:, rows]  # noqa: E731
        pick = lambda a: np.asarray(a)[rows]  # noqa: E731
        return self._replace(
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


def build_geometry(scene: Scene, env_type: str, env: EnvData) -> Geometry:
    """Trace the camera rays against the sphere and tabulate the lights."""
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

    miss_rad = np.asarray(lookup(env_type, env, jnp.asarray(d)))  # (H, W, K, 3)
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

    light_dir, falloff, color = light_terms(scene.lights, pos)
    cos = Cosines(*(np.asarray(a) for a in cosines(normal, light_dir, -d_a)))
    lit = hit & (cos.cos_i > 0) & (cos.cos_o > 0)
    stand_in = Cosines(1.0, 1.0, 1.0, 1.0, 1.0, 0.0)
    cos = Cosines(*(np.where(lit, a, s) for a, s in zip(cos, stand_in)))
    light_weight = np.where(lit, weight * cos.cos_i * falloff, 0.0)
    return Geometry(pixel_index, hit, weight, pos, normal, d_a, cos, light_weight, color,
                    background, background_image)

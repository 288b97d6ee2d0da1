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

from .camera import SceneError, camera_rays
from .environment import EnvData, lookup
from .scene import DirectionalLight, PointLight, Scene


class Geometry(NamedTuple):
    """Per-sample arrays of the active pixels (P pixels x K = k*k samples).

    Attributes:
        pixel_index: (P,) int, flat index (row * W + col) of each active pixel.
        hit: (P, K) bool, sample hits the sphere.
        position, normal, ray_dir: (P, K, 3) hit point, unit outward normal,
            unit camera ray direction (towards the surface). Samples that
            miss hold a harmless stand-in (normal = -ray_dir).
        light_dir: (L, P, K, 3) unit direction towards each light.
        light_irradiance: (L, P, K, 3) RGB irradiance on a surface facing the
            light (W/m^2; intensity / r^2 for point lights).
        background: (P, 3) mean over K of what missing samples see (/K).
        background_image: (H*W, 3) the image with no sphere.
    """

    pixel_index: np.ndarray
    hit: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    ray_dir: np.ndarray
    light_dir: np.ndarray
    light_irradiance: np.ndarray
    background: np.ndarray
    background_image: np.ndarray


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
    """Unit directions to each light and RGB irradiance, each (L, ..., 3)."""
    dirs, irr = [], []
    for light in lights:
        if isinstance(light, PointLight):
            to = np.asarray(light.position, dtype=np.float64) - position
            r2 = np.einsum("...i,...i->...", to, to)
            dirs.append(to / np.sqrt(r2)[..., None])
            irr.append(np.asarray(light.intensity, dtype=np.float64) / r2[..., None])
        elif isinstance(light, DirectionalLight):
            v = -np.asarray(light.direction, dtype=np.float64)
            dirs.append(np.broadcast_to(v / np.linalg.norm(v), position.shape))
            irr.append(np.broadcast_to(np.asarray(light.irradiance, dtype=np.float64),
                                       position.shape))
        else:
            raise SceneError(f"unknown light {light!r}")
    shape = (0,) + position.shape
    if not dirs:
        return np.zeros(shape), np.zeros(shape)
    return np.stack(dirs), np.stack(irr)


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
    h, w, k2, _ = d.shape
    t = intersect_sphere(o, d, sph.center, sph.radius)
    hit_all = np.isfinite(t)

    miss_rad = np.asarray(lookup(env_type, env, jnp.asarray(d)))  # (H, W, K, 3)
    background_image = miss_rad.mean(axis=2).reshape(h * w, 3)

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
    light_dir, light_irr = light_terms(scene.lights, pos)
    miss_a = miss_rad.reshape(h * w, k2, 3)[pixel_index]
    background = np.where(hit[..., None], 0.0, miss_a).mean(axis=1)
    return Geometry(pixel_index, hit, pos, normal, d_a, light_dir, light_irr,
                    background, background_image)

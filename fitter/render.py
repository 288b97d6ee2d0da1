"""The differentiable forward model: parameters -> image of the sphere.

``render(params, scene)`` returns the (H, W, 3) linear RGB image. Internally a
``Renderer`` prepares the material-independent geometry once (``geometry``)
and jit-compiles ``Renderer.active``, which maps a complete parameter dict to
the (P, 3) values of the active pixels -- what the fitter differentiates.
Only the lobes the material names are evaluated, only the lights the scene
has are looped over, and refraction is only traced for a dielectric.

Pixel value = mean over the k*k sub-pixel samples of the radiance
L = sum_lights sum_brdf_lobes f(wi, wo) E_light cos_i  +  sum_specular L_lobe,
with cos_i, cos_o > 0 required for the light term (a convex sphere shadows
itself only through its own horizon).
"""

from __future__ import annotations

import functools
import os
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ._math import dot
from .bsdf.base import SurfaceHit
from .environment import EnvData, load_environment, lookup
from .geometry import Geometry, build_geometry
from .material import Material, MaterialError, lobe_params
from .scene import Scene


def complete_params(material: Material, params: Mapping[str, Any], dtype=jnp.float64):
    """Given parameters (may be JAX tracers) plus defaults, each of its lobe's shape."""
    specs = material.param_specs()
    options = material.option_keys()
    for key in params:
        if key not in specs and key not in options:
            raise MaterialError(f"unknown parameter {key!r} for lobes {list(material.lobes)}; "
                                f"known: {', '.join(specs)}")
    out = {}
    for key, spec in specs.items():
        value = params.get(key, spec.default)
        out[key] = jnp.broadcast_to(jnp.asarray(value, dtype=dtype), spec.shape)
    return out


def _surface_radiance(params, geo: Geometry, env: EnvData, sphere, *, material, env_type):
    """Radiance (P, K, 3) towards the camera at every sample (0 where it misses)."""
    n, wo = geo.normal, -geo.ray_dir
    co = dot(n, wo)
    total = jnp.zeros(n.shape, dtype=n.dtype)
    brdfs = [(lb, material.options_of(lb.name)) for lb in material.lobe_objects if lb.kind == "brdf"]
    if brdfs:
        for li in range(geo.light_dir.shape[0]):
            wi = geo.light_dir[li]
            ci = dot(n, wi)
            lit = geo.hit & (ci > 0) & (co > 0)
            f = sum(lb.eval(lobe_params(params, lb.name), opts, n, wi, wo) for lb, opts in brdfs)
            total = total + jnp.where(lit[..., None], f * geo.light_irradiance[li] * ci[..., None], 0.0)
    speculars = [lb for lb in material.lobe_objects if lb.kind == "specular"]
    if speculars:
        hit = SurfaceHit(geo.position, n, geo.ray_dir, sphere[0], sphere[1])
        env_fn = functools.partial(lookup, env_type, env)
        for lb in speculars:
            rad = lb.radiance(lobe_params(params, lb.name), material.options_of(lb.name), hit, env_fn)
            total = total + jnp.where(geo.hit[..., None], rad, 0.0)
    return total


@functools.partial(jax.jit, static_argnames=("material", "env_type"))
def render_active(params, geo: Geometry, env: EnvData, sphere, *, material, env_type):
    """Values (P, 3) of the active pixels for complete ``params``."""
    rad = _surface_radiance(params, geo, env, sphere, material=material, env_type=env_type)
    return jnp.mean(rad, axis=1) + geo.background


class Renderer:
    """A scene and material prepared for fast repeated, differentiable renders.

    Args:
        scene: the ``Scene``.
        material: a ``Material`` (lobes and options).
        dtype: ``jnp.float64`` (default) or ``jnp.float32`` (about 2x faster,
            loses accuracy for sharp lobes: e >~ 1e3, m <~ 0.01).
        base_dir: folder that a relative envmap path is resolved against.
    """

    def __init__(self, scene: Scene, material: Material, dtype=jnp.float64, base_dir=None):
        self.scene, self.material, self.dtype = scene, material, dtype
        self.env_type = scene.environment.type
        env64 = load_environment(scene.environment, base_dir)
        geo = build_geometry(scene, self.env_type, env64)
        self.pixel_index = geo.pixel_index
        cast = lambda a: jnp.asarray(a, dtype=dtype) if a.dtype.kind == "f" else jnp.asarray(a)
        self.geometry = Geometry(*(cast(a) for a in geo))
        self.env = EnvData(*(cast(np.asarray(a)) for a in env64))
        self.sphere = (jnp.asarray(scene.sphere.center, dtype=dtype),
                       jnp.asarray(scene.sphere.radius, dtype=dtype))

    @property
    def n_active(self) -> int:
        return int(self.pixel_index.shape[0])

    def params(self, params: Mapping[str, Any] | None = None):
        return complete_params(self.material, params or {}, self.dtype)

    def active(self, params: Mapping[str, Any]):
        """(P, 3) values of the active pixels; differentiable in ``params``."""
        return render_active(self.params(params), self.geometry, self.env, self.sphere,
                             material=self.material, env_type=self.env_type)

    def image(self, params: Mapping[str, Any]):
        """The full (H, W, 3) image."""
        vals = self.active(params)
        s = self.scene
        img = self.geometry.background_image.at[self.geometry.pixel_index].set(vals)
        return img.reshape(s.height, s.width, 3)


@functools.lru_cache(maxsize=16)
def _renderer(scene: Scene, material: Material, dtype, base_dir):
    return Renderer(scene, material, dtype, base_dir)


def render(params: Mapping[str, Any], scene: Scene, material: Material | None = None,
           *, dtype=jnp.float64, base_dir: str | None = None):
    """Render the sphere: ``{"lobe.param": value}`` -> (H, W, 3) linear RGB radiance.

    ``material`` defaults to the lobes named by the keys of ``params`` (string
    and bool values there are lobe options, e.g. ``"torrance_sparrow.geometry":
    "smith"``). Differentiable in the numeric values; the prepared scene is
    cached, so repeated calls only pay for the BSDF evaluation.
    """
    if material is None:
        material = Material.from_params(params)
    numeric = {k: v for k, v in params.items() if k not in material.option_keys()}
    base_dir = os.path.abspath(base_dir) if base_dir else None
    return _renderer(scene, material, jnp.dtype(dtype), base_dir).image(numeric)

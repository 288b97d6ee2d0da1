"""The differentiable forward model: parameters -> image of the sphere.

``render(params, scene)`` returns the (H, W, 3) linear RGB image. Internally a
``Renderer`` prepares the material-independent geometry once (``geometry``)
and jit-compiles ``Renderer.active``, which maps a complete parameter dict to
the (P, 3) values of the active pixels -- what the fitter differentiates.
Only the lobes the material names are evaluated, only the lights the scene
has are looped over, and refraction is only traced for a dielectric.

Pixel value = quadrature over the k*k sub-pixel samples of the radiance
L = sum_lights sum_brdf_lobes f(wi, wo) E_light cos_i  +  sum_specular L_lobe,
with cos_i, cos_o > 0 required for the light term (a convex sphere shadows
itself only through its own horizon). A constant/envmap environment lights
the brdf lobes too (as Mitsuba's emitters do): its sun is a set of extra
directional lights, the rest a per-sample stencil of cells
(``fitter.envlight``), summed per pixel.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from . import checks
from ._keep import recent
from ._math import to_device
from ._modules import make_callable
from .bsdf.base import SurfaceHit
from .environment import EnvData, load_environment, lookup
from .geometry import Geometry, build_geometry, with_kernels
from .blasthreads import one_blas_thread
from .hugepages import advice_off
from .limits import check_scene
from .material import EXPOSURE_KEY, Material, MaterialError, lobe_params
from .scene import Scene, SceneError, resolve_path


def complete_params(material: Material, params: Mapping[str, Any], dtype=jnp.float64):
    """Given parameters (may be JAX tracers) plus defaults, each of its lobe's shape.

    Concrete values are checked by ``Material.full_params`` (the config's
    check: key, size, finite, inside the lobe's box; ``MaterialError``
    naming the key); a tracer (``jax.grad``/``jit`` through the renderer)
    only by its shape, as its value is not known here.
    """
    specs = material.param_specs()
    checked = material.full_params({
        k: (np.full(np.shape(v), specs[k].default) if isinstance(v, jax.core.Tracer)
            and k in specs else v) for k, v in params.items()})
    out = {}
    for key, spec in specs.items():
        value = params.get(key, spec.default)
        if isinstance(value, str):  # a named value (a metal's eta): its numbers
            value = checked[key]
        if isinstance(value, jax.Array) or isinstance(value, jax.core.Tracer):
            out[key] = jnp.broadcast_to(jnp.asarray(value, dtype=dtype), spec.shape)
        else:  # a host value: no eager kernel to compile
            out[key] = to_device(np.broadcast_to(np.asarray(value, dtype=dtype), spec.shape))
    return out


def _with_local_jacobian(fn, theta, *args, value_and_jac=None):
    """``fn(theta, *args)`` whose derivative is J(theta) @ d(theta).

    A lobe depends on a handful of its own scalar parameters ``theta`` (n,),
    while the fitter's forward-mode Jacobian pushes one tangent per *fitted*
    coordinate through every sample. Computing the lobe's small local
    Jacobian (..., n) once and contracting it with the tangents makes the
    cost of a full Jacobian independent of how many other parameters are
    fitted. ``args`` (geometry, environment) are treated as constants.
    ``value_and_jac(theta, *args) -> (value, J)`` replaces ``jax.jacfwd``
    where a lobe gives its derivatives by hand (``Lobe.shape_grad``).
    """
    if value_and_jac is None:
        def value_and_jac(theta, *rest):
            jac, out = jax.jacfwd(lambda t: (fn(t, *rest),) * 2, has_aux=True)(theta)
            return out, jac

    @jax.custom_jvp
    def f(theta, *args):
        return fn(theta, *args)

    @f.defjvp
    def f_jvp(primals, tangents):
        theta, *rest = primals
        out, jac = value_and_jac(theta, *rest)
        return out, jnp.tensordot(jac, tangents[0], axes=1)

    return f(theta, *args)


def _param_vector(lobe, p, skip=None):
    """The lobe's parameters ``p`` (but ``skip``) as a flat vector, and its inverse."""
    names = [n for n in p if n != skip]
    sizes = [int(np.prod(jnp.shape(p[n]))) for n in names]
    theta = jnp.concatenate([jnp.reshape(p[n], (-1,)) for n in names]) if names else None

    def unflatten(t):
        out, i = {}, 0
        for n, k in zip(names, sizes):
            out[n] = t[i] if jnp.ndim(p[n]) == 0 else t[i:i + k]
            i += k
        return out

    return theta, unflatten


def _columns(g, dg, q):
    """[g, d g / d theta_0, ...] stacked: one slice per coordinate of theta.

    An RGB parameter of an RGB shape (``Lobe.shape_grad`` gives the diagonal)
    spreads over three columns, channel j in column j.
    """
    cols = [g]
    for name, v in q.items():
        d = jnp.broadcast_to(dg[name], g.shape)
        cols += [d] if jnp.ndim(v) == 0 else [d * jnp.eye(3, dtype=g.dtype)[j] for j in range(3)]
    return jnp.stack(cols)


#: Up to this many lights (a scene's own) a lobe's light sum is one einsum: summing
#: the sub-samples first made the 256^2 point-light solve 20 % slower (0.101 -> 0.121 s).
FEW_LIGHTS = 4


def _light_sum(g, rgb, weight, color):
    """Sum over lights and samples of shape * weight * light colour: g ([T,] L, P,
    K[, 3]) (``rgb``: the colour axis), weight (L, P, K), colour (L, 3) -> ([T,] P, 3)."""
    if rgb or weight.shape[0] <= FEW_LIGHTS:
        return jnp.einsum("...lpkc,lpk,lc->...pc" if rgb else "...lpk,lpk,lc->...pc",
                          g, weight, color)
    # Many lights (the sun's cells): K summed first; as one einsum XLA made a tiny
    # (T, L) x (L, 3) product per pixel of the Jacobian's columns (32 x 25 k: 108 -> 63 ms).
    return jnp.einsum("...lp,lc->...pc", jnp.sum(g * weight, -1), color)


def _lobe_sum(lobe, p, opts, reduce, cos, *args, flat_jac: bool = False):
    """``reduce(g, rgb, *args)`` of the lobe's shape g on ``cos`` (``rgb``: g has a
    colour axis beyond the cosines' shape), a reduction linear in g, differentiated
    in the lobe's own parameters by its local Jacobian (``_with_local_jacobian``):
    the value and every derivative column as one (n + 1)-stack, one reduction.
    ``flat_jac``: the columns evaluated on the cosines flattened (every field of
    cos_i's shape), then given their shape back."""
    theta, unflatten = _param_vector(lobe, p, skip=lobe.scale)

    def unit(theta, cos, *args):
        g = lobe.shape(unflatten(theta) if theta is not None else {}, opts, cos)
        return reduce(g, g.ndim > jnp.ndim(cos.cos_i), *args)

    def unit_and_jac(theta, cos, *args):
        q = unflatten(theta)
        shape = jnp.shape(cos.cos_i)
        if flat_jac:
            cos = cos.map(lambda a: jnp.reshape(a, -1))
        g, dg = lobe.shape_grad(q, opts, cos)
        cols = _columns(g, dg, q)
        if flat_jac:
            cols = cols.reshape(cols.shape[:1] + shape + cols.shape[2:])
        out = reduce(cols, g.ndim > jnp.ndim(cos.cos_i), *args)
        return out[0], jnp.moveaxis(out[1:], 0, -1)

    if theta is None:
        return unit(None, cos, *args)
    return _with_local_jacobian(unit, theta, cos, *args,
                                value_and_jac=unit_and_jac if lobe.shape_grad else None)


def _brdf_unit(lobe, p, opts, geo: Geometry):
    """Sum over the scene's lights and samples of shape * weight * light colour: (P, 3)."""
    return _lobe_sum(lobe, p, opts, _light_sum, geo.cosines, geo.light_weight, geo.light_color)


def _sun_unit(lobe, p, opts, sun):
    """Sum over each sun group's lights of shape * weight * colour (``SunCells``),
    the lobe evaluated once on every group's flat (light, sample) pairs: (Q, 3)
    for the sum Q of the groups' samples, in ``sun.index``'s order."""
    shapes = [np.shape(w) for w in sun.weight]
    cuts = np.cumsum([0] + [n_l * n_q for n_l, n_q in shapes])

    def group_sums(g, rgb, weights, colors):  # g: (..., E[, 3]) -> (..., Q, 3)
        tail = g.shape[-1:] if rgb else ()
        lead = g.shape[:g.ndim - 1 - len(tail)]
        out = []
        for (n_l, n_q), a, b, w, col in zip(shapes, cuts[:-1], cuts[1:], weights, colors):
            gi = (g[..., a:b, :] if rgb else g[..., a:b]).reshape(lead + (n_l, n_q, 1) + tail)
            out.append(_light_sum(gi, rgb, w[..., None], col))  # a sample is its own "pixel"
        return jnp.concatenate(out, axis=-2)

    return _lobe_sum(lobe, p, opts, group_sums, sun.cosines, sun.weight, sun.color)


def sky_parts(lobe, p, opts, geo: Geometry):
    """A ``Lobe.stencil_free`` lobe's light from the sky per unit of its scale, (P, 3)
    each: (its uniform part x each pixel's irradiance, its kernel's factor x the
    pixel's kernel sum or None without a kernel); ``p``: the lobe's parameters."""
    q = {k: v for k, v in p.items() if k != lobe.scale}
    uniform = lobe.uniform(q, opts) * geo.env_irradiance
    if lobe.kernel is None:
        return uniform, None
    return uniform, lobe.kernel_factor(q, opts) * geo.env_kernels[lobe.name]


def _env_unit(lobe, p, opts, geo: Geometry):
    """The sky's light (P, 3) per unit of the lobe's scale: its uniform part
    (``Lobe.uniform``) times each pixel's irradiance and its kernel's factor times
    the pixel's kernel sum (``Lobe.kernel``; both summed over the map, once per
    scene and material: no per-step sum), or else its shape summed over the sky
    stencil.

    The stencil's lobe is evaluated once per theta_o node and cell
    (``envlight.node_geometry``), then interpolated per env sample and summed
    against its cells (``envlight.sky_sum``). Its value and derivative columns
    are evaluated on the (T, N, M) points flat: XLA's CPU loop over them as a
    (columns, T, N, M) array ran ~4x slower (Torrance-Sparrow, env_plastic's
    Jacobian 82 -> 72 ms a step); its value alone keeps the (T, N, M) form (flat,
    the cost profile's evaluations took 0.23 -> 0.40 s).
    """
    from .envlight import sky_sum

    def stencil_sum(g, rgb, wnode, node, frac, color):  # g: (..., T, N, M[, 3]) -> (..., S, 3)
        mean = jnp.sum(g * wnode[..., None], -2) if rgb else jnp.sum(g * wnode, -1)  # a cell's
        return sky_sum(mean, node, frac, color)

    if lobe.stencil_free:
        uniform, kernel = sky_parts(lobe, p, opts, geo)
        return uniform if kernel is None else uniform + kernel
    out = jnp.zeros((geo.background.shape[0], 3), geo.env_irradiance.dtype)
    per_sample = _lobe_sum(lobe, p, opts, stencil_sum, geo.env_cosines, geo.env_node_weight,
                           geo.env_node, geo.env_frac, geo.env_color, flat_jac=True)
    # env samples -> their pixels; a sample of a pixel not fitted points past the end
    return out.at[geo.env_index].add(per_sample.astype(out.dtype), mode="drop")


def _specular(lobe, p, opts, geo: Geometry, env: EnvData, sphere, env_type):
    theta, unflatten = _param_vector(lobe, p)

    def call(fn, theta, geo, env, sphere):
        hit = SurfaceHit(geo.position, geo.normal, geo.ray_dir, sphere[0], sphere[1])
        return fn(unflatten(theta), opts, hit, functools.partial(lookup, env_type, env))

    def pixel_sum(rad, geo):  # (..., P, K, 3) -> (..., P, 3), over the hitting samples
        return jnp.einsum("...pkc,k->...pc", jnp.where(geo.hit[..., None], rad, 0.0),
                          geo.sample_weight)

    def radiance(theta, geo, env, sphere):
        return pixel_sum(call(lobe.radiance, theta, geo, env, sphere), geo)

    def radiance_and_jac(theta, geo, env, sphere):
        g, dg = call(lobe.radiance_grad, theta, geo, env, sphere)
        # Summed over samples first (linear), then spread over the columns.
        out = _columns(pixel_sum(g, geo), {k: pixel_sum(v, geo) for k, v in dg.items()},
                       unflatten(theta))
        return out[0], jnp.moveaxis(out[1:], 0, -1)

    return _with_local_jacobian(radiance, theta, geo, env, sphere,
                                value_and_jac=radiance_and_jac if lobe.radiance_grad else None)


@functools.partial(jax.jit, static_argnames=("material", "env_type"))
def render_active(params, geo: Geometry, env: EnvData, sphere, *, material, env_type):
    """Values (P, 3) of the active pixels for complete ``params``.

    BRDF lobes: reflectance * (sum over lights and sub-pixel samples of the
    lobe's shape * weight * light colour), exact by linearity and cheap to
    differentiate in the reflectance. Specular lobes: weighted sum of their
    radiance over the samples that hit. A material with an exposure
    (``Material.exposure``) multiplies the whole sum by ``params["exposure"]``.
    """
    value = geo.background
    for lobe in material.lobe_objects:
        p = lobe_params(params, lobe.name)
        opts = material.options_of(lobe.name)
        if lobe.kind == "brdf":
            if geo.light_weight.shape[0]:
                value = value + p[lobe.scale] * _brdf_unit(lobe, p, opts, geo)
            if geo.sky_lit:
                value = value + p[lobe.scale] * _env_unit(lobe, p, opts, geo)
            if geo.sun:
                # (a sample of a pixel not fitted points past the end)
                value = value + p[lobe.scale] * jnp.zeros_like(value).at[geo.sun.index].add(
                    _sun_unit(lobe, p, opts, geo.sun), mode="drop")
        else:
            value = value + _specular(lobe, p, opts, geo, env, sphere, env_type)
    if material.exposure:  # static: a material without it traces exactly as before
        value = value * params[EXPOSURE_KEY]
    return value


def exposed_background(material: Material, params, background_image):
    """The (H*W, 3) image without the sphere, times the exposure if the material has one."""
    if not material.exposure:
        return background_image
    return background_image * params[EXPOSURE_KEY]


#: Scenes' arrays kept for later calls beyond the most recent scene's
#: (``fitter._keep.recent``): small scenes stay for refits, a large one only
#: while it is the latest (one 256^2 env-lit scene: ~2 GB).
KEEP_BYTES = 2**29


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
        key_scene, key_dir = _prepare_key(scene, os.path.abspath(base_dir) if base_dir else None)
        geo, self.env, self.sphere = _prepare(key_scene, jnp.dtype(dtype), key_dir,
                                              env_light=bool(material.opaque),
                                              stencil=bool(material.stencil_lobes))
        geo = with_kernels(geo, material)
        if geo.env_kernels is not None:
            geo = geo._replace(env_kernels={k: to_device(v, dtype)
                                            for k, v in geo.env_kernels.items()})
        self.geometry = geo
        self.pixel_index = np.asarray(self.geometry.pixel_index)

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
        full = self.params(params)
        vals = render_active(full, self.geometry, self.env, self.sphere,
                             material=self.material, env_type=self.env_type)
        s = self.scene
        img = exposed_background(self.material, full, self.geometry.background_image)
        img = img.at[self.geometry.pixel_index].set(vals)
        return img.reshape(s.height, s.width, 3)


def _prepare_key(scene: Scene, base_dir):
    """(scene, base_dir) with an envmap's path made absolute, so that cases in different
    folders sharing one map and scene share the prepared geometry (its sky tabulation)."""
    env = scene.environment
    if env.type != "envmap" or not env.file or base_dir is None:
        return scene, base_dir
    path = resolve_path(env.file, base_dir)
    return scene.replace(environment=dataclasses.replace(env, file=path)), None


@recent(max_items=8, max_bytes=KEEP_BYTES)
@advice_off  # large short-lived NumPy arrays (``fitter.hugepages``)
@one_blas_thread
def _prepare(scene: Scene, dtype, base_dir, env_light: bool = False, stencil: bool = True):
    """Material-independent arrays of a scene (shared by every material).

    ``env_light``: tabulate the environment as light (for brdf lobes); ``stencil``:
    with the sky stencil's table (not where every lobe is ``Lobe.stencil_free``).
    """
    env64 = load_environment(scene.environment, base_dir)
    lighting = None
    if env_light:
        from .envlight import env_lights

        lighting = env_lights(scene.environment.type, env64.image,  # (kept with it: envlight)
                              np.asarray(env64.constant))
    geo = build_geometry(scene, scene.environment.type, env64, lighting, stencil=stencil)
    # float32 renders still get geometry computed in float64, then rounded.
    cast = lambda a: to_device(a, dtype) if jnp.result_type(a).kind == "f" \
        else to_device(a)  # noqa: E731
    sphere = (to_device(scene.sphere.center, dtype), to_device(scene.sphere.radius, dtype))
    # (the env samples stay on the host, for ``with_kernels``)
    dev = jax.tree_util.tree_map(cast, geo._replace(env_samples=None))
    return dev._replace(env_samples=geo.env_samples), jax.tree_util.tree_map(cast, env64), sphere


@recent(max_items=16, max_bytes=KEEP_BYTES)
def cached_renderer(scene: Scene, material: Material, dtype, base_dir):
    """The ``Renderer`` of a scene and material, shared by every call with equal arguments."""
    return Renderer(scene, material, dtype, base_dir)


def render(params: Mapping[str, Any], scene: Scene, material: Material | None = None,
           *, dtype=jnp.float64, base_dir: str | None = None):
    """Render the sphere: ``{"lobe.param": value}`` -> (H, W, 3) linear RGB radiance.

    ``material`` defaults to the lobes named by the keys of ``params`` (string
    and bool values there are lobe options, e.g. ``"torrance_sparrow.geometry":
    "smith"``); an ``"exposure"`` value multiplies the whole image, background
    included (``fitter.material.EXPOSURE``). Differentiable in the numeric values;
    the prepared scene is cached, so repeated calls only pay for the BSDF evaluation. A concrete
    value outside its lobe's box (NaN, m <= 0, rho > 1, ...) is a
    ``MaterialError`` naming the key and the range (``complete_params``); a
    bad scene a ``SceneError`` naming the field; a render this machine's memory
    cannot hold (``fitter.limits``) a ``ResourceError`` stating the estimate.
    """
    if not isinstance(params, Mapping):
        raise MaterialError("params: expected a dict {'lobe.param': value}, got "
                            + checks.show(params))
    if not isinstance(scene, Scene):
        raise SceneError(f"scene: expected a fitter.Scene, got {checks.show(scene)}")
    material = Material.given(material, params)
    check_scene("render", scene, material, base_dir=base_dir)
    numeric = {k: v for k, v in params.items() if k not in material.option_keys()}
    base_dir = os.path.abspath(base_dir) if base_dir else None
    return cached_renderer(scene, material, jnp.dtype(dtype), base_dir).image(numeric)


make_callable(__name__, render)  # fitter.render(...) is this function (see fitter._modules)

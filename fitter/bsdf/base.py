"""What a BSDF lobe is: its parameters, options and one evaluation function.

Convention (the lecture's, also pbrt's and Mitsuba's): all directions point
away from the surface. ``wi`` is towards the light, ``wo`` towards the viewer,
``n`` the unit outward normal; all are unit vectors of shape (..., 3).

A lobe is one of two kinds:

* ``"brdf"``: a finite BRDF evaluated under the scene's point and
  directional lights, written as f = scale * shape: ``scale`` names the
  lobe's reflectance parameter (RGB or scalar) and ``shape(p, opts, c) ->
  (...)`` the colourless angular part, a function of the ``Cosines`` of the
  direction pair only (every lecture BRDF is isotropic). The split lets the
  renderer average shape * irradiance over sub-pixel samples once and apply
  the reflectance per pixel, and lets the cosines be tabulated once per
  scene. A shape may instead be RGB, (..., 3), where the angular part
  itself has colour (a conductor's Fresnel term); its ``shape_grad``
  derivative in an RGB parameter is then the diagonal (..., 3), channel c
  by that parameter's channel c. ``Lobe.eval(p, opts, n, wi, wo) -> (..., 3)``
  gives f itself.
  ``shape`` must stay finite, with finite gradients, for any directions,
  including cos_i or cos_o <= 0 (the renderer weights those pairs by 0).
  Optionally ``shape_grad(p, opts, c) -> (shape, {name: d shape / d name})``
  gives the derivatives in the lobe's shape parameters by hand: forward-mode
  autodiff of a shape fuses poorly on CPU (Torrance-Sparrow at 256^2: 66 ms
  for its local Jacobian by ``jax.jacfwd``, 13 ms by hand), and the fitter
  evaluates it at every solver step. ``tests/test_stability.py`` checks every
  ``shape_grad`` against ``jax.jacfwd`` of ``shape``.
  Optionally ``uniform(p, opts)`` is the part of the shape that is the same
  for every pair of directions (Lambert's 1/pi, Oren-Nayar's A/pi), and
  ``kernel_factor(p, opts)`` x ``kernel(c)`` the rest, a parameter factor
  times a parameter-free function of the direction pair, of ``Cosines``'
  cos_i, cos_o and cos_io only (Oren-Nayar's B/pi x its angular term; none:
  the shape is uniform): an environment's sky lights
  both through sums over the map made once per scene (``fitter.irradiance``:
  the irradiance, and per pixel the kernel's own), not through the sky stencil,
  which sums the shapes of the other lobes.
* ``"specular"``: a delta lobe (mirror, smooth dielectric) that only sees the
  environment; ``radiance(p, opts, hit, env) -> (..., 3)`` returns the
  outgoing radiance towards the camera (``hit``: a ``SurfaceHit``; ``env``: a
  callable direction (..., 3) -> RGB radiance (..., 3)). Its ``scale``, if
  any, names a parameter the radiance is linear in (mirror's ``rho_m``); the
  renderer does not use it, the exposure's degeneracy check does. Optionally
  ``radiance_grad(p, opts, hit, env) -> (radiance, {name: d radiance / d
  name})`` gives its derivatives by hand, each (..., 3) (an RGB parameter:
  the diagonal, channel c by its channel c), as ``shape_grad`` does.
  Optionally ``start_search`` (a ``StartSearch``) finds a start for the
  solver by a coarse search where the cost has narrow basins
  (``fitter.fit._search``). Optionally ``cheapest_options(p, opts, hit,
  weight, env_max, tolerance) -> {option: value}`` lowers options that set
  the work (the dielectric's bounce count) as far as what they leave out
  stays below ``tolerance`` (3,) radiance in every pixel; the fitter passes
  its noise level.

Lobes add (the lecture's linearity of BRDFs). Adding a lobe is one module
defining ``LOBE = Lobe(...)`` plus one entry in ``fitter.bsdf.registry``: the
module holds the formula, its parameters and docs, its Mitsuba mapping
(``fitter.bsdf.mitsuba_map``) and the hints its property tests need
(``Hints``). Nothing else names a lobe.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Literal, Mapping, NamedTuple

import numpy as np

from .._lazy import jnp
from .mitsuba_map import MitsubaMapping


@dataclasses.dataclass(frozen=True)
class Param:
    """A continuous lobe parameter.

    Attributes:
        name: short name (the user-facing key is ``"lobe.name"``).
        size: 1 for a scalar, 3 for RGB.
        default: value used when a named lobe's parameter is not given.
        lower, upper: the documented valid box (inclusive); renders are
            finite with finite gradients everywhere inside it.
        transform: how the fitter maps it to an unconstrained coordinate,
            one of ``fitter.transforms.TRANSFORMS``.
        doc: meaning and units (configs/README.md's parameter table shows
            it; ``fitter.bsdf.tables``).
        free: whether the fitter frees it by default.
        named: values a user may give by name instead of numbers,
            ``{name: value}`` (a conductor's ``eta`` / ``k``: Mitsuba's metals,
            ``fitter.bsdf.metals``); None: numbers only.
    """

    name: str
    size: int
    default: float
    lower: float
    upper: float
    transform: str
    doc: str = ""
    free: bool = True  # fitted unless the user fixes it
    named: Mapping[str, Any] | None = dataclasses.field(default=None, compare=False,
                                                         repr=False)

    @property
    def shape(self) -> tuple[int, ...]:
        return () if self.size == 1 else (self.size,)


@dataclasses.dataclass(frozen=True)
class Option:
    """A discrete lobe setting (static: changing it recompiles).

    ``choices`` None: any int in [0, ``most``] (``most`` bounds the work a
    value asks for; None: unbounded). ``doc`` is configs/README.md's meaning.
    """

    name: str
    choices: tuple[Any, ...]
    default: Any
    doc: str = ""
    most: int | None = None


class Cosines(NamedTuple):
    """Cosines of a direction pair (wi, wo) about the normal n, arrays (...).

    With H = wi + wo and h = H / |H| the half vector: cos_h = n.h,
    cos_d = wo.h (= wi.h) and tan2_h = tan^2 of the angle between n and h,
    taken as |n x H|^2 / (n.H)^2 (accurate near 0, unlike 1/cos^2 - 1).
    Where n.H <= 0 or H = 0, cos_h = cos_d = tan2_h = 0. cot_i, cot_o =
    cos / sin of wi's and wo's angle to n (``COT_NORMAL`` where sin = 0):
    tabulated with the geometry, as a lobe's per-sample sqrt and division
    (Smith's G1) bound its renders; None where not tabulated (``cotangents``
    then takes them from the cosines).
    """

    cos_i: Any
    cos_o: Any
    cos_io: Any  # wi . wo
    cos_h: Any
    cos_d: Any
    tan2_h: Any
    cot_i: Any = None
    cot_o: Any = None

    def map(self, fn) -> "Cosines":
        """``fn`` applied to each field that is there (None stays None)."""
        return Cosines(*(None if a is None else fn(a) for a in self))


def cotangents(c: Cosines):
    """(cot_i, cot_o) of ``c``: its tabulated ones, else from cos_i, cos_o (JAX)."""
    if c.cot_i is not None:
        return c.cot_i, c.cot_o
    return _cot(c.cos_i, jnp), _cot(c.cos_o, jnp)


#: cot of a direction along the normal (sin = 0): finite in float32 too, and beyond
#: any roughness's reach (Smith's a = cot / m >= 1.6, so G1 = 1 there, as at sin = 0);
#: where sin > 0 cot <= 1 / sqrt(eps) (float64: 6.7e7).
COT_NORMAL = 1e30


#: Cosines where a sample is unlit (its weight is 0): finite stand-ins, so no lobe
#: formula sees a zero or negative cosine there (the double-where rule).
UNLIT = Cosines(1.0, 1.0, 1.0, 1.0, 1.0, 0.0, COT_NORMAL, COT_NORMAL)


def _cot(c, xp):
    """cos / sin of the angle whose cosine is ``c`` (``COT_NORMAL`` where sin = 0;
    the double where keeps sin = 0 out of the division and its derivative)."""
    s2 = 1.0 - c * c
    tilted = s2 > 0
    return xp.where(tilted, c / xp.sqrt(xp.where(tilted, s2, 1.0)), COT_NORMAL)


def cosines(n, wi, wo) -> Cosines:
    """``Cosines`` of unit vectors (..., 3).

    JAX arrays give JAX arrays (differentiable); NumPy arrays are computed in
    NumPy, as the renderer tabulates them once per scene.
    """
    if all(isinstance(a, np.ndarray) for a in (n, wi, wo)):
        return _cosines_np(n, wi, wo)
    dot_ = lambda a, b: jnp.sum(a * b, axis=-1)  # noqa: E731
    ci, co = dot_(n, wi), dot_(n, wo)
    h = wi + wo
    hh = dot_(h, h)
    nh = dot_(n, h)
    up = (nh > 0) & (hh > 0)
    inv = jnp.where(up, 1.0 / jnp.sqrt(jnp.where(up, hh, 1.0)), 0.0)
    cr = jnp.cross(n, h)
    tan2 = jnp.where(up, dot_(cr, cr) / jnp.where(up, nh * nh, 1.0), 0.0)
    return Cosines(ci, co, dot_(wi, wo), nh * inv, dot_(wo, h) * inv, tan2, _cot(ci, jnp),
                   _cot(co, jnp))


def _cosines_np(n, wi, wo) -> Cosines:
    """``cosines`` in NumPy per component (broadcasting as the arrays do): the same
    sums in the same order as the JAX path's, without np.cross's copies (1.2 s of
    a scene's sky tabulation at 97 x 5520 points)."""
    n, wi, wo = ((a[..., 0], a[..., 1], a[..., 2]) for a in (n, wi, wo))
    dot_ = lambda a, b: a[0] * b[0] + a[1] * b[1] + a[2] * b[2]  # noqa: E731
    ci, co = dot_(n, wi), dot_(n, wo)
    h = tuple(a + b for a, b in zip(wi, wo))
    hh = dot_(h, h)
    nh = dot_(n, h)
    up = (nh > 0) & (hh > 0)
    inv = np.where(up, 1.0 / np.sqrt(np.where(up, hh, 1.0)), 0.0)
    cr = (n[1] * h[2] - n[2] * h[1], n[2] * h[0] - n[0] * h[2], n[0] * h[1] - n[1] * h[0])
    tan2 = np.where(up, dot_(cr, cr) / np.where(up, nh * nh, 1.0), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        cots = _cot(ci, np), _cot(co, np)
    return Cosines(ci, co, dot_(wi, wo), nh * inv, dot_(wo, h) * inv, tan2, *cots)


class SurfaceHit(NamedTuple):
    """Where camera rays meet the sphere; arrays of shape (..., 3)."""

    position: Any
    normal: Any
    ray_dir: Any  # camera ray direction, pointing *into* the surface
    center: Any  # sphere center, (3,)
    radius: Any  # sphere radius, scalar


class Quadrature(NamedTuple):
    """Where the energy tests' quadrature puts its nodes for one lobe setting.

    ``axis``: ``"normal"`` (wo about n), ``"mirror"`` (wo about the mirror
    direction of wi) or ``"half"`` (half vectors h about n, wo = reflect(wi, h),
    dwo = 4 (wo.h) dwh); ``cap``: polar angle of the cap holding the lobe's
    mass; ``refine``: times more nodes in theta (a kink where the horizon cuts
    a broad lobe converges as N^-2).
    """

    axis: Literal["normal", "mirror", "half"] = "normal"
    cap: float = math.pi / 2
    refine: int = 1


class Point(NamedTuple):
    """A setting the property tests evaluate: lobe-local ``params`` and ``options``.

    ``conserving``: the energy test applies (0 < int f cos dwo <= 1 at every
    incidence for these params); False for settings that are valid but not
    bounded so (the lecture's un-normalised Phong) or reflect nothing.
    """

    id: str
    params: Mapping[str, Any]
    options: Mapping[str, Any] = {}
    conserving: bool = True


def _hemisphere(p) -> Quadrature:
    return Quadrature()


@dataclasses.dataclass(frozen=True, eq=False)
class Hints:
    """What the generic tests need to know about a lobe (not used to render).

    Attributes:
        points: settings for positivity, reciprocity and energy
            (``tests/test_bsdf_properties.py``), typically at the top of the
            reflectance box.
        example: a typical lobe-local parameter setting with distinct RGB
            channels (``tests/test_mitsuba_plugins.py``); options vary over
            their choices there.
        quadrature: ``quadrature(p) -> Quadrature`` for the energy integrals.
        reciprocal: f(wi, wo) = f(wo, wi) (Helmholtz).
    """

    points: tuple[Point, ...] = ()
    example: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    quadrature: Callable[[Mapping[str, Any]], Quadrature] = _hemisphere
    reciprocal: bool = True


class StartSearch(NamedTuple):
    """A lobe's coarse search for the solver's start (``fitter.fit._search``).

    ``rounds(p, free, box)``: one function per round, (best point so far) ->
    a grid, ``p`` with arrays of candidates (the start is the first round's
    best; ``free`` names the free parameters, ``box`` maps them to (lower,
    upper)). ``best(grid, opts, hit, env, cost) -> (p, spread)``: the point of
    the grid with the lowest ``cost(model (..., 3)) -> (3,)`` (per channel),
    and per parameter (an array of its shape) the largest relative change of
    the cost along it over the grid (0 where the pixels do not depend on it;
    the fit's start check is skipped when every free parameter's is above
    ``fitter.fit._search.SEEN_CHANGE``).
    """

    rounds: Callable
    best: Callable


@dataclasses.dataclass(frozen=True)
class Lobe:
    """One BSDF lobe (see the module docstring for ``kind``, ``shape``, ``radiance``).

    Attributes:
        variants: ``{(option, value): params}``: the parameters that replace
            ``params`` when that option has that value (e.g. a conductor's RGB
            ``eta`` and ``k``); ``params_for(opts)`` picks them.
        derived: ``derived(p, opts) -> {name: value}``, quantities the image
            determines better than the parameters (``fitter.bsdf.derived``);
            None: none.
        interior: ``interior(p, opts, at_edge) -> {name: value}``, where a fit
            stopped with parameters on their box's edge (``at_edge``: {name:
            bool array of its channels}): a point inside the box on the valley
            of nearly equal images to solve again from (``fitter.fit._corner``;
            a conductor's eta, k of the same F0). None or {}: none.
        complex_index: ``complex_index(opts) -> (real, imaginary)``, the names
            of the RGB parameters that are a complex index of refraction under
            ``opts`` (a conductor's eta, k), or None: the fit solves such a
            pair along its circles of equal F0 (``fitter.fit._valley``).
        transmissive: light passes through the sphere (refraction), so what
            the lobe shows depends on the sphere's interior.
        doc: the model in one line (the README's lobe table shows it).
        single_precision: its values in float32 are near enough float64's for
            the fit's two float32 estimates: the cost profile's pixel subset
            (``fitter.fit._profile.SINGLE``, whose error is measured either
            way) and the stated errors' finer model
            (``fitter.fit._discretisation.SINGLE``). False where float32
            rounds the lobe far more than its inputs (Phong's cos^e: e times).
        mitsuba: its Mitsuba 3 equivalent (``fitter.bsdf.mitsuba_map``).
        hints: what the property tests need (``Hints``).
    """

    name: str
    kind: Literal["brdf", "specular"]
    params: tuple[Param, ...]
    options: tuple[Option, ...] = ()
    scale: str | None = None
    shape: Callable | None = None
    shape_grad: Callable | None = None
    radiance: Callable | None = None
    radiance_grad: Callable | None = None
    start_search: StartSearch | None = None
    cheapest_options: Callable | None = None
    doc: str = ""
    mitsuba: MitsubaMapping | None = None
    transmissive: bool = False
    single_precision: bool = True
    hints: Hints = Hints()
    variants: Mapping[tuple[str, Any], tuple[Param, ...]] = dataclasses.field(
        default_factory=dict, compare=False)
    derived: Callable[[dict, dict], dict] | None = None
    interior: Callable[[dict, dict, dict], dict] | None = None
    complex_index: Callable[[dict], tuple | None] | None = None
    uniform: Callable[[dict, dict], Any] | None = None
    kernel_factor: Callable[[dict, dict], Any] | None = None
    kernel: Callable | None = None

    @property
    def stencil_free(self) -> bool:
        """Whether the sky lights this lobe without the stencil (``uniform``, ``kernel``)."""
        return self.kind == "brdf" and self.uniform is not None

    def params_for(self, opts: Mapping[str, Any]) -> tuple[Param, ...]:
        """The parameters under options ``opts`` (missing options: their defaults)."""
        for (name, value), params in self.variants.items():
            if opts.get(name, self.option(name).default) == value:
                return params
        return self.params

    def eval(self, p, opts, n, wi, wo):
        """BRDF value f(wi, wo) in 1/sr, RGB (..., 3), for a ``brdf`` lobe."""
        c = cosines(n, wi, wo)
        g = self.shape(p, opts, c)
        if jnp.ndim(g) == jnp.ndim(c.cos_i):  # a colourless shape
            g = g[..., None]
        scale = jnp.asarray(p[self.scale])
        return jnp.reshape(scale, (1,) * (g.ndim - 1) + (-1,)) * g * jnp.ones(3)

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    def option(self, name: str) -> Option:
        for o in self.options:
            if o.name == name:
                return o
        raise KeyError(name)

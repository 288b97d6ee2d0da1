"""What a BSDF lobe is: its parameters, options and one evaluation function.

Convention (the lecture's, also pbrt's and Mitsuba's): all directions point
away from the surface. ``wi`` is towards the light, ``wo`` towards the viewer,
``n`` the unit outward normal; all are unit vectors of shape (..., 3).

A lobe is one of two kinds:

* ``"brdf"``: a finite BRDF f(wi, wo) evaluated under the scene's point and
  directional lights; ``eval(p, opts, n, wi, wo) -> (..., 3)`` returns f in
  1/sr, RGB. The renderer multiplies by irradiance and the cosine and sums
  over lights, so ``eval`` must only be finite where cos_i <= 0 or
  cos_o <= 0; the renderer masks those pairs out.
* ``"specular"``: a delta lobe (mirror, smooth dielectric) that only sees the
  environment; ``radiance(p, opts, hit, env) -> (..., 3)`` returns the
  outgoing radiance towards the camera (``hit``: a ``SurfaceHit``; ``env``: a
  callable direction (..., 3) -> RGB radiance (..., 3)).

Lobes add (the lecture's linearity of BRDFs). Adding a lobe is one module
defining ``LOBE = Lobe(...)`` plus one entry in ``fitter.bsdf.registry``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Literal, NamedTuple


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
        doc: meaning and units.
        free: whether the fitter frees it by default.
    """

    name: str
    size: int
    default: float
    lower: float
    upper: float
    transform: str
    doc: str = ""
    free: bool = True  # fitted unless the user fixes it

    @property
    def shape(self) -> tuple[int, ...]:
        return () if self.size == 1 else (self.size,)


@dataclasses.dataclass(frozen=True)
class Option:
    """A discrete lobe setting (static: changing it recompiles)."""

    name: str
    choices: tuple[Any, ...]
    default: Any
    doc: str = ""


class SurfaceHit(NamedTuple):
    """Where camera rays meet the sphere; arrays of shape (..., 3)."""

    position: Any
    normal: Any
    ray_dir: Any  # camera ray direction, pointing *into* the surface
    center: Any  # sphere center, (3,)
    radius: Any  # sphere radius, scalar


@dataclasses.dataclass(frozen=True)
class Lobe:
    name: str
    kind: Literal["brdf", "specular"]
    params: tuple[Param, ...]
    options: tuple[Option, ...] = ()
    eval: Callable | None = None
    radiance: Callable | None = None
    doc: str = ""
    #: ``mitsuba(p, opts) -> dict``: the equivalent Mitsuba 3 BSDF dict (see ``fitter.mitsuba``).
    mitsuba: Callable | None = None

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

"""Scene description: camera, sphere, lights and environment.

All classes are frozen, hashable dataclasses of plain Python numbers and
tuples, so a scene can key a compilation cache. Conventions follow Mitsuba 3
so that a scene maps 1:1 onto a Mitsuba scene dict (see
``fitter.mitsuba.scene_dict``):

* world units are arbitrary but shared by positions, the radius and the
  Beer-Lambert path length;
* ``perspective.fov`` is the full field of view in degrees along the image x
  axis (Mitsuba's ``fov_axis="x"``);
* ``orthographic.half_width`` is half the width of the view in world units;
  the half height is ``half_width * height / width``;
* image row 0 is the top row; world directions follow ``look_at(origin,
  target, up)``;
* a pixel's value is the average radiance over the pixel square (Mitsuba's
  ``box`` reconstruction filter), estimated with a ``supersampling`` x
  ``supersampling`` product rule over the pixel: Gauss-Legendre nodes and
  weights by default (``pixel_rule = "gauss"``), or the midpoint grid.
"""

from __future__ import annotations

import dataclasses
from typing import Literal, Union

Vec3 = tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole (``perspective``) or ``orthographic`` camera.

    Attributes:
        type: ``"perspective"`` or ``"orthographic"``.
        origin, target, up: world-space look-at frame.
        fov: full horizontal field of view, degrees (perspective only).
        half_width: half the horizontal extent of the view, world units
            (orthographic only).
    """

    type: Literal["perspective", "orthographic"] = "perspective"
    origin: Vec3 = (0.0, 0.0, 4.0)
    target: Vec3 = (0.0, 0.0, 0.0)
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: float = 35.0
    half_width: float = 1.2


@dataclasses.dataclass(frozen=True)
class Sphere:
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 1.0


@dataclasses.dataclass(frozen=True)
class PointLight:
    """Isotropic point light; ``intensity`` is RGB radiant intensity, W/sr.

    Irradiance on a surface at distance r is ``intensity * cos(theta) / r**2``.
    """

    position: Vec3
    intensity: Vec3
    type: Literal["point"] = "point"


@dataclasses.dataclass(frozen=True)
class DirectionalLight:
    """Distant light; ``direction`` is the direction the light travels.

    ``irradiance`` is the RGB irradiance on a surface facing the light.
    """

    direction: Vec3
    irradiance: Vec3
    type: Literal["directional"] = "directional"


Light = Union[PointLight, DirectionalLight]


@dataclasses.dataclass(frozen=True)
class Environment:
    """What camera rays that miss the sphere, and mirror/dielectric rays, see.

    Attributes:
        type: ``"black"``, ``"constant"`` or ``"envmap"``.
        radiance: RGB radiance of a ``constant`` environment.
        file: path of an equirectangular EXR (``envmap``), Mitsuba's mapping.
        scale: multiplies the envmap's radiance.
    """

    type: Literal["black", "constant", "envmap"] = "black"
    radiance: Vec3 = (0.0, 0.0, 0.0)
    file: str | None = None
    scale: float = 1.0


@dataclasses.dataclass(frozen=True)
class Scene:
    """One sphere seen by one camera under any number of lights."""

    width: int = 128
    height: int = 128
    supersampling: int = 4
    camera: Camera = Camera()
    sphere: Sphere = Sphere()
    lights: tuple[Light, ...] = ()
    environment: Environment = Environment()
    pixel_rule: Literal["gauss", "midpoint"] = "gauss"

    def replace(self, **changes) -> "Scene":
        return dataclasses.replace(self, **changes)

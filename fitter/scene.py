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

``check_scene`` is the one scene validator: ``fitter.serialize`` calls it on
every ``[scene]`` table (adding the file name), the renderer on every scene
(``fitter.camera.camera_rays``).
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Literal, Union

from . import checks
from .errors import FitterError

Vec3 = tuple[float, float, float]
CAMERA_TYPES = ("perspective", "orthographic")
LIGHT_TYPES = ("point", "directional")
ENVIRONMENT_TYPES = ("black", "constant", "envmap")
PIXEL_RULES = ("gauss", "midpoint")
#: Widest perspective field of view, degrees: tan(fov / 2) stays finite.
MAX_FOV = 179.0


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


class SceneError(FitterError):
    """A scene that cannot be rendered; the message starts with the key (``scene.camera.up``)."""


def resolve_path(path: str, base_dir: str | None) -> str:
    """``path`` with ``~`` expanded, relative to ``base_dir`` (a config's folder) unless absolute."""
    path = os.path.expanduser(path)
    if base_dir is not None and not os.path.isabs(path):
        path = os.path.join(base_dir, path)
    return os.path.normpath(path)


def check_scene(scene: Scene) -> None:
    """Raise ``SceneError`` naming the first field that no renderer can use."""
    _check(checks.integer, scene.width, "scene.width", lo=1)
    _check(checks.integer, scene.height, "scene.height", lo=1)
    _check(checks.integer, scene.supersampling, "scene.supersampling", lo=1)
    _check(checks.choice, scene.pixel_rule, "scene.pixel_rule", PIXEL_RULES)
    sphere = scene.sphere
    _check(checks.vec3, sphere.center, "scene.sphere.center")
    _check(checks.number, sphere.radius, "scene.sphere.radius", lo=0.0, lo_open=True)
    _check_camera(scene.camera, sphere)
    for i, light in enumerate(scene.lights):
        _check_light(light, f"scene.lights[{i}]", sphere)
    _check_environment(scene.environment)


def _check(check, value, key, *args, **kwargs):
    try:
        return check(value, *args, **kwargs)
    except checks.Problem as exc:
        raise SceneError(f"{key}: {exc}") from None


def _check_camera(cam: Camera, sphere: Sphere) -> None:
    kind = _check(checks.choice, cam.type, "scene.camera.type", CAMERA_TYPES)
    origin = _check(checks.vec3, cam.origin, "scene.camera.origin")
    target = _check(checks.vec3, cam.target, "scene.camera.target")
    up = _check(checks.vec3, cam.up, "scene.camera.up", nonzero=True)
    view = [t - o for t, o in zip(target, origin)]
    if not any(view):
        raise SceneError("scene.camera.target: must differ from scene.camera.origin")
    cross = (view[1] * up[2] - view[2] * up[1], view[2] * up[0] - view[0] * up[2],
             view[0] * up[1] - view[1] * up[0])
    if math.hypot(*cross) <= 1e-9 * math.hypot(*view) * math.hypot(*up):
        raise SceneError("scene.camera.up: is parallel to the viewing direction (target - origin)")
    if math.dist(origin, sphere.center) <= sphere.radius:
        raise SceneError("scene.camera.origin: lies inside the sphere; place the camera outside it")
    if kind == "perspective":
        _check(checks.number, cam.fov, "scene.camera.fov", lo=0.0, hi=MAX_FOV, lo_open=True)
    else:
        _check(checks.number, cam.half_width, "scene.camera.half_width", lo=0.0, lo_open=True)


def _check_light(light, where: str, sphere: Sphere) -> None:
    if isinstance(light, PointLight):
        pos = _check(checks.vec3, light.position, f"{where}.position")
        if math.dist(pos, sphere.center) <= sphere.radius:
            raise SceneError(f"{where}.position: lies inside the sphere")
        _check(checks.vec3, light.intensity, f"{where}.intensity", nonneg=True)
    elif isinstance(light, DirectionalLight):
        _check(checks.vec3, light.direction, f"{where}.direction", nonzero=True)
        _check(checks.vec3, light.irradiance, f"{where}.irradiance", nonneg=True)
    else:
        raise SceneError(f"{where}: expected a PointLight or DirectionalLight, got "
                         f"{checks.show(light)}")


def _check_environment(env: Environment) -> None:
    where = "scene.environment"
    kind = _check(checks.choice, env.type, f"{where}.type", ENVIRONMENT_TYPES)
    if kind == "constant":
        _check(checks.vec3, env.radiance, f"{where}.radiance", nonneg=True)
    elif kind == "envmap":
        _check(checks.string, env.file, f"{where}.file")
        _check(checks.number, env.scale, f"{where}.scale", lo=0.0)

"""Scene, material and synth settings <-> plain dicts in the config layout, and TOML out.

The layer below ``fitter.config`` (which reads whole jobs from files) and
``fitter.mitsuba`` (which writes ``case.json``). Each table's writer
(``*_to_dict``, JSON/TOML-ready) sits next to its reader (``*_from_dict``),
which checks the table and raises ``ConfigError`` with one sentence naming
the file and the key. Unknown keys are errors (pbrt's ``ReportUnused``);
value checks share one wording (``fitter.checks``) and the scene's are
``fitter.scene.check_scene``, the API's own. Every key is documented in
``configs/README.md``.

Layout::

    [scene]            width, height, supersampling, pixel_rule
    [scene.camera]     type, origin, target, up, fov | half_width
    [scene.sphere]     center, radius
    [[scene.lights]]   type = "point" (position, intensity)
                       | "directional" (direction, irradiance)
    [scene.environment] type = "black" | "constant" (radiance, scale)
                       | "envmap" (file, scale)
    [material]         lobes; tables truth, init, fixed ("lobe.param" = value;
                       lobe options such as "torrance_sparrow.geometry" go in fixed)
    [synth]            spp, seed (Mitsuba target rendering)
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from typing import Any, Mapping

import numpy as np

from . import checks
from .bsdf import LOBES
from .errors import FitterError
from .material import EXPOSURE_KEY, Material, MaterialError
from .scene import (CAMERA_TYPES, ENVIRONMENT_TYPES, LIGHT_TYPES, Camera, DirectionalLight,
                    Environment, PointLight, Scene, SceneError, Sphere, check_scene,
                    resolve_path)


class ConfigError(FitterError):
    """A config a user must fix; the message is one sentence naming file and key."""


def plain(value):
    """JSON-ready: arrays -> lists, numpy scalars -> Python numbers, NaN/Inf -> None."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def base_dir_of(path: str, base_dir: str | None = None) -> str:
    """The absolute folder relative paths resolve against: ``base_dir``, else ``path``'s folder."""
    return os.path.abspath(base_dir or os.path.dirname(os.path.abspath(path)))


class Reader:
    """Typed access to the values of one file; every failure is a ``ConfigError`` naming the key."""

    def __init__(self, path: str):
        self.path = path

    def error(self, key: str, problem: str) -> ConfigError:
        sep = " " if problem.startswith("=") else ": "
        return ConfigError(f"{self.path}: {key}{sep}{problem}" if key else f"{self.path}: {problem}")

    def table(self, tbl, where: str, allowed) -> None:
        if not isinstance(tbl, Mapping):
            raise self.error(where, "expected a table")
        for key in tbl:
            if key not in allowed:
                name = f"{where}.{key}" if where else key
                hint = ("; the exposure is a parameter: [material.fixed] exposure = x if "
                        "known, [material.init] exposure = x to fit it"
                        if key == EXPOSURE_KEY else "")
                raise self.error(name, "unknown key; allowed keys here: "
                                 + ", ".join(sorted(allowed)) + hint)

    def sub(self, tbl, key, where="", required=False) -> dict:
        name = f"{where}.{key}" if where else key
        if key not in tbl:
            if required:
                raise self.error(name, f"missing table [{name}]")
            return {}
        value = tbl[key]
        if not isinstance(value, Mapping):
            raise self.error(name, f"expected a table [{name}], got {checks.show(value)}")
        return dict(value)

    def require(self, tbl, where: str, keys) -> None:
        for key in keys:
            if key not in tbl:
                raise self.error(f"{where}.{key}", "missing required key")

    def check(self, check, value, key, *args, **kwargs):
        """``check(value, ...)`` from ``fitter.checks``, its problem reported under ``key``."""
        try:
            return check(value, *args, **kwargs)
        except checks.Problem as exc:
            raise self.error(key, str(exc)) from None

    def number(self, value, key, lo=None, hi=None, lo_open=False) -> float:
        return self.check(checks.number, value, key, lo, hi, lo_open)

    def integer(self, value, key, lo=None) -> int:
        return self.check(checks.integer, value, key, lo)

    def vec3(self, value, key) -> tuple[float, float, float]:
        return self.check(checks.vec3, value, key)

    def choice(self, value, key, choices) -> str:
        return self.check(checks.choice, value, key, choices)

    def boolean(self, value, key) -> bool:
        return self.check(checks.boolean, value, key)

    def string(self, value, key) -> str:
        return self.check(checks.string, value, key)


# --------------------------------------------------------------------------- [scene]
# Readers check types and layout; ranges and geometry are check_scene's.


def scene_to_dict(scene: Scene) -> dict:
    """The ``[scene]`` table of ``scene`` (TOML/JSON-ready; inverse of ``scene_from_dict``)."""
    out = {"width": scene.width, "height": scene.height, "supersampling": scene.supersampling}
    if scene.pixel_rule != Scene().pixel_rule:
        out["pixel_rule"] = scene.pixel_rule
    return {**out, "camera": _camera_to_dict(scene.camera),
            "sphere": {"center": list(scene.sphere.center), "radius": scene.sphere.radius},
            "lights": [_light_to_dict(lt) for lt in scene.lights],
            "environment": _environment_to_dict(scene.environment)}


def scene_from_dict(data: Mapping[str, Any], path: str = "<scene>",
                    base_dir: str | None = None) -> Scene:
    """A ``[scene]`` table -> checked ``Scene``; relative paths resolve against ``base_dir``
    (default: the folder of ``path``)."""
    r, tbl, d = Reader(path), dict(data), Scene()
    r.table(tbl, "scene", {"width", "height", "supersampling", "pixel_rule", "camera", "sphere",
                           "lights", "environment"})
    sphere_tbl = r.sub(tbl, "sphere", "scene")
    r.table(sphere_tbl, "scene.sphere", {"center", "radius"})
    sphere = Sphere(center=r.vec3(sphere_tbl.get("center", d.sphere.center), "scene.sphere.center"),
                    radius=r.number(sphere_tbl.get("radius", d.sphere.radius),
                                    "scene.sphere.radius"))
    lights = tbl.get("lights", [])
    if not isinstance(lights, list):
        raise r.error("scene.lights", "expected an array of tables [[scene.lights]]")
    scene = Scene(
        width=r.integer(tbl.get("width", d.width), "scene.width"),
        height=r.integer(tbl.get("height", d.height), "scene.height"),
        supersampling=r.integer(tbl.get("supersampling", d.supersampling), "scene.supersampling"),
        pixel_rule=tbl.get("pixel_rule", d.pixel_rule),
        camera=_camera_from_dict(r, r.sub(tbl, "camera", "scene")), sphere=sphere,
        lights=tuple(_light_from_dict(r, lt, f"scene.lights[{i}]") for i, lt in enumerate(lights)),
        environment=_environment_from_dict(r, r.sub(tbl, "environment", "scene"),
                                           base_dir_of(path, base_dir)))
    try:
        check_scene(scene)
    except SceneError as exc:
        raise r.error("", str(exc)) from None
    return scene


def _camera_to_dict(cam: Camera) -> dict:
    out = {"type": cam.type, "origin": list(cam.origin), "target": list(cam.target),
           "up": list(cam.up)}
    if cam.type == "perspective":
        out["fov"] = cam.fov
    else:
        out["half_width"] = cam.half_width
    return out


def _camera_from_dict(r: Reader, tbl: dict) -> Camera:
    d = Camera()
    kind = r.choice(tbl.get("type", d.type), "scene.camera.type", CAMERA_TYPES)
    lens = "fov" if kind == "perspective" else "half_width"
    r.table(tbl, "scene.camera", {"type", "origin", "target", "up", lens})
    return Camera(type=kind, origin=r.vec3(tbl.get("origin", d.origin), "scene.camera.origin"),
                  target=r.vec3(tbl.get("target", d.target), "scene.camera.target"),
                  up=r.vec3(tbl.get("up", d.up), "scene.camera.up"),
                  fov=r.number(tbl.get("fov", d.fov), "scene.camera.fov"),
                  half_width=r.number(tbl.get("half_width", d.half_width),
                                      "scene.camera.half_width"))


#: Each light type's class and keys (in writing order).
_LIGHTS = {"point": (PointLight, ("position", "intensity")),
           "directional": (DirectionalLight, ("direction", "irradiance"))}


def _light_to_dict(lt) -> dict:
    return {"type": lt.type, **{k: list(getattr(lt, k)) for k in _LIGHTS[lt.type][1]}}


def _light_from_dict(r: Reader, tbl, where: str):
    if not isinstance(tbl, Mapping):
        raise r.error(where, "expected a table [[scene.lights]]")
    if "type" not in tbl:
        raise r.error(f"{where}.type", "missing; allowed values: "
                      + ", ".join(repr(c) for c in LIGHT_TYPES))
    cls, keys = _LIGHTS[r.choice(tbl["type"], f"{where}.type", LIGHT_TYPES)]
    r.table(tbl, where, {"type", *keys})
    r.require(tbl, where, keys)
    return cls(**{k: r.vec3(tbl[k], f"{where}.{k}") for k in keys})


def _environment_to_dict(env: Environment) -> dict:
    out: dict[str, Any] = {"type": env.type}
    if env.type == "constant":
        out["radiance"] = list(env.radiance)
        if env.scale != 1.0:
            out["scale"] = env.scale
    elif env.type == "envmap":
        out.update(file=env.file, scale=env.scale)
    return out


def _environment_from_dict(r: Reader, tbl: dict, base_dir: str) -> Environment:
    where = "scene.environment"
    kind = r.choice(tbl.get("type", "black"), f"{where}.type", ENVIRONMENT_TYPES)
    if kind == "black":
        r.table(tbl, where, {"type"})
        return Environment()
    if kind == "constant":
        r.table(tbl, where, {"type", "radiance", "scale"})
        r.require(tbl, where, ("radiance",))
        return Environment(type="constant", radiance=r.vec3(tbl["radiance"], f"{where}.radiance"),
                           scale=r.number(tbl.get("scale", 1.0), f"{where}.scale", lo=0.0))
    r.table(tbl, where, {"type", "file", "scale"})
    r.require(tbl, where, ("file",))
    file = resolve_path(r.string(tbl["file"], f"{where}.file"), base_dir)
    if not os.path.isfile(file):
        raise r.error(f"{where}.file", f"envmap file {file} not found")
    return Environment(type="envmap", file=file,
                       scale=r.number(tbl.get("scale", 1.0), f"{where}.scale"))


# --------------------------------------------------------------------------- [material]


def material_to_dict(material: Material, truth=None, init=None, fixed=None) -> dict:
    """The ``[material]`` table: lobes, options folded into ``fixed``, numeric tables."""
    out: dict[str, Any] = {"lobes": list(material.lobes)}
    fixed_all = {k: v for k, v in material.options}
    fixed_all.update(_listed(fixed or {}))
    if material.exposure and not any(EXPOSURE_KEY in (v or {}) for v in (truth, init, fixed)):
        fixed_all[EXPOSURE_KEY] = 1.0  # the material keeps its exposure when read back
    for name, values in (("truth", truth), ("init", init)):
        if values:
            out[name] = _listed(values)
    if fixed_all:
        out["fixed"] = fixed_all
    return out


def material_from_dict(data: Mapping[str, Any], path: str = "<material>"):
    """A ``[material]`` table -> ``(Material, truth, init, fixed)``.

    truth, init, fixed: ``{"lobe.param": float or tuple of 3 floats}``
    (numeric only; lobe options given in ``fixed`` go into the material).
    """
    r, tbl = Reader(path), dict(data)
    r.table(tbl, "material", {"lobes", "truth", "init", "fixed", "options"})
    if "lobes" not in tbl:
        raise r.error("material.lobes", "missing; name the summed lobes, e.g. "
                      "[\"lambert\", \"torrance_sparrow\"]; known lobes: " + ", ".join(LOBES))
    lobes = tbl["lobes"]
    if isinstance(lobes, str):
        lobes = [s.strip() for s in lobes.split("+")]
    if not isinstance(lobes, list) or not all(isinstance(x, str) for x in lobes):
        raise r.error("material.lobes", f"expected a list of lobe names, got {checks.show(lobes)}")
    for name in lobes:
        if name not in LOBES:
            raise r.error("material.lobes", f"unknown lobe {name!r}; known lobes: "
                          + ", ".join(LOBES))
    tables = {name: r.sub(tbl, name, "material") for name in ("truth", "init", "fixed", "options")}
    options = dict(tables["options"])
    for key in options:
        if not _is_option_key(key):
            raise r.error(f"material.options.{key}", "is not a lobe option of "
                          + ", ".join(lobes) + "; options: " + _all_options(lobes))
    for key, value in tables["fixed"].items():
        if _is_option_key(key):
            if key in options and options[key] != value:
                raise r.error(f"material.fixed.{key}", "conflicts with material.options")
            options[key] = value
    exposure = any(EXPOSURE_KEY in tables[n] for n in ("truth", "init", "fixed"))
    try:
        material = Material.make(lobes, options, exposure=exposure)
    except MaterialError as exc:
        raise r.error("material", str(exc)) from None
    truth = _values(r, material, tables["truth"], "material.truth", allow_options=True)
    init = _values(r, material, tables["init"], "material.init", allow_options=False)
    fixed = _values(r, material, tables["fixed"], "material.fixed", allow_options=True)
    both = sorted(set(init) & set(fixed))
    if both:
        raise r.error(f"material.init.{both[0]}", "is also in material.fixed; a parameter is "
                      "either fitted from an initial value or fixed")
    return material, truth, init, fixed


def _listed(values: Mapping[str, Any]) -> dict:
    return {k: list(v) if isinstance(v, (tuple, list)) else v for k, v in values.items()}


def _option_names(lobe: str) -> set[str]:
    return {o.name for o in LOBES[lobe].options} if lobe in LOBES else set()


def _is_option_key(key: str) -> bool:
    lobe, _, name = key.partition(".")
    return name in _option_names(lobe)


def _all_options(lobes) -> str:
    names = [f"{lb}.{o}" for lb in lobes for o in sorted(_option_names(lb))]
    return ", ".join(names) if names else "(none)"


def _values(r: Reader, material: Material, tbl: dict, where: str, allow_options: bool):
    """Numeric ``{"lobe.param": float | tuple}``, validated against the lobes' boxes."""
    specs = material.param_specs()
    chosen = dict(material.options)
    out = {}
    for key, value in tbl.items():
        name = f"{where}.{key}"
        if key in chosen:
            if not allow_options:
                raise r.error(name, "is a lobe option, not a parameter; set it in material.fixed")
            if value != chosen[key] or type(value) is not type(chosen[key]):
                raise r.error(name, f"= {checks.show(value)} differs from the material's option "
                              f"value {chosen[key]!r}")
            continue
        if key not in specs:
            raise r.error(name, f"unknown parameter for lobes {', '.join(material.lobes)}; "
                          "known: " + ", ".join(specs))
        spec = specs[key]
        if isinstance(value, str) and spec.named is not None:  # "Au": Param.named
            try:
                arr = material.full_params({key: value})[key]
            except MaterialError as exc:
                raise r.error(name, str(exc)) from None
            out[key] = float(arr) if arr.ndim == 0 else tuple(float(x) for x in arr)
            continue
        if isinstance(value, str):
            lobe, _, pname = key.partition(".")
            named_with = [f"{lobe}.{opt} = {val!r}" for (opt, val), ps in
                          (LOBES[lobe].variants.items() if lobe in LOBES else ())
                          if any(p.name == pname and p.named for p in ps)]
            if named_with:
                raise r.error(name, f"= {value!r}: a name is allowed only with "
                              f"{named_with[0]} (in material.fixed); give numbers here")
        if isinstance(value, list):
            nums = [r.number(v, name) for v in value]
            if len(nums) not in (1, spec.size):
                raise r.error(name, f"expected {spec.size} value(s), got {len(nums)}")
        else:
            nums = [r.number(value, name)]
        if any(x < spec.lower or x > spec.upper for x in nums):
            raise r.error(name, f"= {checks.show(value)} is outside the lobe's valid range "
                          f"[{spec.lower:g}, {spec.upper:g}]")
        try:
            arr = material.full_params({key: nums if len(nums) > 1 else nums[0]})[key]
        except MaterialError as exc:
            raise r.error(name, str(exc)) from None
        out[key] = float(arr) if arr.ndim == 0 else tuple(float(x) for x in arr)
    return out


# --------------------------------------------------------------------------- [synth]


@dataclasses.dataclass(frozen=True)
class SynthOptions:
    """The ``[synth]`` table: how ``fitter synth`` renders a target with Mitsuba."""

    spp: int = 256
    seed: int = 0


def synth_to_dict(synth: SynthOptions) -> dict:
    return dataclasses.asdict(synth)


def synth_from_dict(data: Mapping[str, Any], path: str = "<synth>") -> SynthOptions:
    r, tbl, d = Reader(path), dict(data), SynthOptions()
    r.table(tbl, "synth", {"spp", "seed"})
    return SynthOptions(spp=r.integer(tbl.get("spp", d.spp), "synth.spp", lo=1),
                        seed=r.integer(tbl.get("seed", d.seed), "synth.seed", lo=0))


# --------------------------------------------------------------------------- TOML


def dumps_toml(data: Mapping[str, Any]) -> str:
    """Write the config layout (nested tables, arrays of tables, scalars, lists) as TOML."""
    lines: list[str] = []
    _emit_table(lines, data, [])
    return "\n".join(lines).lstrip("\n") + "\n"


def _emit_table(lines, tbl, prefix) -> None:
    scalars = {k: v for k, v in tbl.items() if not _is_table(v) and not _is_table_array(v)}
    if prefix and (scalars or not tbl):
        lines.append(f"\n[{'.'.join(_key(p) for p in prefix)}]")
    for key, value in scalars.items():
        lines.append(f"{_key(key)} = {_value(value)}")
    for key, value in tbl.items():
        if _is_table(value):
            _emit_table(lines, value, prefix + [key])
        elif _is_table_array(value):
            for item in value:
                lines.append(f"\n[[{'.'.join(_key(p) for p in prefix + [key])}]]")
                for k, v in item.items():
                    lines.append(f"{_key(k)} = {_value(v)}")


def _is_table(v) -> bool:
    return isinstance(v, Mapping)


def _is_table_array(v) -> bool:
    return isinstance(v, (list, tuple)) and bool(v) and all(isinstance(x, Mapping) for x in v)


def _key(k: str) -> str:
    bare = k.replace("_", "").replace("-", "").isalnum()
    return k if bare else _string(k)


def _string(s: str) -> str:
    """A TOML basic string: JSON's escapes are TOML's, except DEL, which TOML forbids raw."""
    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")

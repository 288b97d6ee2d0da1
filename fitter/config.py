"""Fit jobs as TOML files: parsed with ``tomllib`` (data only) into frozen dataclasses.

``load_config(path) -> Job`` validates everything a user can get wrong and
raises ``ConfigError`` with one sentence naming the file, the key and what is
allowed. Unknown keys are errors (pbrt's ``ReportUnused``). Relative paths
(``fit.target``, ``scene.environment.file``) resolve against the config
file's folder. Every key is documented in ``configs/README.md``.

Layout::

    [scene]            width, height, supersampling, pixel_rule
    [scene.camera]     type, origin, target, up, fov | half_width
    [scene.sphere]     center, radius
    [[scene.lights]]   type = "point" (position, intensity)
                       | "directional" (direction, irradiance)
    [scene.environment] type = "black" | "constant" (radiance)
                       | "envmap" (file, scale)
    [material]         lobes; tables truth, init, fixed ("lobe.param" = value;
                       lobe options such as "torrance_sparrow.geometry" go in fixed)
    [fit]              target, solver, n_starts, max_steps, rtol, atol, ...
    [synth]            spp, seed (Mitsuba target rendering)
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from typing import Any, Mapping

from .bsdf import LOBES
from .material import Material, MaterialError
from .scene import Camera, DirectionalLight, Environment, PointLight, Scene, Sphere
from .errors import FitterError

FALLBACK_SOLVERS = ("levenberg_marquardt", "dogleg", "gauss_newton", "bfgs", "adam")
LOSSES = ("l2", "huber", "cauchy")
DTYPES = ("float64", "float32")
MASKS = ("interior", "active")
CAMERA_TYPES = ("perspective", "orthographic")
LIGHT_TYPES = ("point", "directional")
ENVIRONMENT_TYPES = ("black", "constant", "envmap")


class ConfigError(FitterError):
    """A config a user must fix; the message is one sentence naming file and key."""


def solvers() -> tuple[str, ...]:
    """Solver names the fit engine accepts (``fitter.fit.SOLVERS``)."""
    try:
        from .fit import SOLVERS
    except ImportError:
        return FALLBACK_SOLVERS
    return tuple(SOLVERS)


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """The ``[fit]`` table; see ``configs/README.md`` for every key.

    Attributes:
        target: absolute path of the target image, or None (given on the
            command line instead).
        solver: one of ``fitter.fit.SOLVERS``.
        n_starts: number of starts (the lowest-cost one is kept).
        max_steps: solver step limit per start (None: the engine's default
            for the solver).
        rtol, atol: solver tolerances (None: the engine's defaults).
        mask: which pixels are fitted: ``"interior"`` (every sub-pixel
            sample hits the sphere) or ``"active"`` (any sample hits).
        noise_sigma: per-pixel noise standard deviation of the target (linear
            units) if known; enables the chi^2 goodness-of-fit test.
        loss: ``"l2"``, ``"huber"`` or ``"cauchy"``.
        validate: re-render the fit with Mitsuba and compare.
        validate_spp: samples per pixel of that re-render.
        saturation: pixels with any channel at or above this linear value
            are excluded (None: only clipped pixels of 8-bit files).
        dtype: ``"float64"`` or ``"float32"`` for the forward model.
    """

    target: str | None = None
    solver: str = "levenberg_marquardt"
    n_starts: int = 1
    max_steps: int | None = None
    rtol: float | None = None
    atol: float | None = None
    mask: str = "interior"
    noise_sigma: float | None = None
    loss: str = "l2"
    validate: bool = True
    validate_spp: int = 256
    saturation: float | None = None
    dtype: str = "float64"

    def replace(self, **changes) -> "FitOptions":
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class SynthOptions:
    """The ``[synth]`` table: how ``fitter synth`` renders a target with Mitsuba."""

    spp: int = 256
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class Job:
    """One validated fit job.

    Attributes:
        path: the config file (absolute) or a label for dict-built jobs.
        base_dir: folder that relative paths were resolved against.
        scene, material: the ``Scene`` and ``Material``.
        truth, init, fixed: ``{"lobe.param": float or tuple of 3 floats}``
            (numeric only; lobe options live in ``material.options``).
        fit: the ``FitOptions``; synth: the ``SynthOptions``.
    """

    path: str
    base_dir: str
    scene: Scene
    material: Material
    truth: dict[str, Any]
    init: dict[str, Any]
    fixed: dict[str, Any]
    fit: FitOptions
    synth: SynthOptions = SynthOptions()

    @property
    def name(self) -> str:
        """The config's stem, e.g. ``"plastic"`` for ``configs/plastic.toml``."""
        return os.path.splitext(os.path.basename(self.path))[0]

    def replace(self, **changes) -> "Job":
        return dataclasses.replace(self, **changes)


# --------------------------------------------------------------------------- loading


def load_config(path: str) -> Job:
    """Read and validate the TOML fit job at ``path``; raises ``ConfigError``."""
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, expected a TOML config file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not valid TOML (not UTF-8 text)") from None
    return job_from_dict(data, path)


def job_from_dict(data: Mapping[str, Any], path: str = "<config>",
                  base_dir: str | None = None) -> Job:
    """Validate a config already parsed into a dict (the TOML layout).

    ``base_dir`` defaults to the folder of ``path``.
    """
    r = _Reader(path)
    if base_dir is None:
        base_dir = os.path.dirname(os.path.abspath(path))
    base_dir = os.path.abspath(base_dir)
    r.table(data, "", {"scene", "material", "fit", "synth"})
    scene = _scene(r, r.sub(data, "scene", required=True), base_dir)
    material, truth, init, fixed = _material(r, r.sub(data, "material", required=True))
    fit = _fit(r, r.sub(data, "fit"), base_dir)
    synth = _synth(r, r.sub(data, "synth"))
    return Job(os.path.abspath(path) if not path.startswith("<") else path, base_dir,
               scene, material, truth, init, fixed, fit, synth)


def scene_from_dict(data: Mapping[str, Any], path: str = "<scene>",
                    base_dir: str | None = None) -> Scene:
    """The inverse of ``scene_to_dict``: a ``[scene]`` table -> ``Scene``."""
    base_dir = os.path.abspath(base_dir or os.path.dirname(os.path.abspath(path)))
    return _scene(_Reader(path), dict(data), base_dir)


class _Reader:
    """Typed access to TOML values; every failure is a ``ConfigError`` naming the key."""

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
                raise self.error(name, "unknown key; allowed keys here: "
                                 + ", ".join(sorted(allowed)))

    def sub(self, tbl, key, where="", required=False) -> dict:
        name = f"{where}.{key}" if where else key
        if key not in tbl:
            if required:
                raise self.error(name, f"missing table [{name}]")
            return {}
        value = tbl[key]
        if not isinstance(value, Mapping):
            raise self.error(name, f"expected a table [{name}], got {_show(value)}")
        return dict(value)

    def number(self, value, key, lo=None, hi=None, lo_open=False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(key, f"expected a number, got {_show(value)}")
        x = float(value)
        if not math.isfinite(x):
            raise self.error(key, f"expected a finite number, got {_show(value)}")
        below = lo is not None and (x <= lo if lo_open else x < lo)
        if below or (hi is not None and x > hi):
            raise self.error(key, f"{_show(value)} is outside the allowed range "
                             + _range_text(lo, hi, lo_open))
        return x

    def integer(self, value, key, lo=None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {_show(value)}")
        if lo is not None and value < lo:
            raise self.error(key, f"expected an integer >= {lo}, got {value}")
        return int(value)

    def vec3(self, value, key, nonneg=False, nonzero=False) -> tuple[float, float, float]:
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise self.error(key, f"expected a list of 3 numbers, got {_show(value)}")
        out = tuple(self.number(v, key, lo=0.0 if nonneg else None) for v in value)
        if nonzero and not any(out):
            raise self.error(key, "must not be the zero vector")
        return out

    def choice(self, value, key, choices) -> str:
        if value not in choices or not isinstance(value, str):
            raise self.error(key, f"{_show(value)} is not allowed; allowed values: "
                             + ", ".join(repr(c) for c in choices))
        return value

    def boolean(self, value, key) -> bool:
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {_show(value)}")
        return value

    def string(self, value, key) -> str:
        if not isinstance(value, str) or not value:
            raise self.error(key, f"expected a non-empty string, got {_show(value)}")
        return value


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _range_text(lo, hi, lo_open) -> str:
    left = "(" if lo_open else "["
    return f"{left}{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]"


def _resolve(base_dir: str, path: str) -> str:
    path = os.path.expanduser(path)
    return os.path.normpath(path if os.path.isabs(path) else os.path.join(base_dir, path))


# --------------------------------------------------------------------------- scene


def _scene(r: _Reader, tbl: dict, base_dir: str) -> Scene:
    r.table(tbl, "scene", {"width", "height", "supersampling", "pixel_rule", "camera", "sphere",
                           "lights", "environment"})
    d = Scene()
    width = r.integer(tbl.get("width", d.width), "scene.width", lo=1)
    height = r.integer(tbl.get("height", d.height), "scene.height", lo=1)
    k = r.integer(tbl.get("supersampling", d.supersampling), "scene.supersampling", lo=1)
    rule = r.choice(tbl.get("pixel_rule", d.pixel_rule), "scene.pixel_rule", ("gauss", "midpoint"))
    sphere = _sphere(r, r.sub(tbl, "sphere", "scene"))
    camera = _camera(r, r.sub(tbl, "camera", "scene"), sphere)
    lights_raw = tbl.get("lights", [])
    if not isinstance(lights_raw, list):
        raise r.error("scene.lights", "expected an array of tables [[scene.lights]]")
    lights = tuple(_light(r, lt, f"scene.lights[{i}]", sphere) for i, lt in enumerate(lights_raw))
    env = _environment(r, r.sub(tbl, "environment", "scene"), base_dir)
    return Scene(width=width, height=height, supersampling=k, camera=camera, sphere=sphere,
                 lights=lights, environment=env, pixel_rule=rule)


def _sphere(r: _Reader, tbl: dict) -> Sphere:
    r.table(tbl, "scene.sphere", {"center", "radius"})
    d = Sphere()
    return Sphere(center=r.vec3(tbl.get("center", d.center), "scene.sphere.center"),
                  radius=r.number(tbl.get("radius", d.radius), "scene.sphere.radius",
                                  lo=0.0, lo_open=True))


def _camera(r: _Reader, tbl: dict, sphere: Sphere) -> Camera:
    d = Camera()
    kind = r.choice(tbl.get("type", d.type), "scene.camera.type", CAMERA_TYPES)
    lens = "fov" if kind == "perspective" else "half_width"
    r.table(tbl, "scene.camera", {"type", "origin", "target", "up", lens})
    origin = r.vec3(tbl.get("origin", d.origin), "scene.camera.origin")
    target = r.vec3(tbl.get("target", d.target), "scene.camera.target")
    up = r.vec3(tbl.get("up", d.up), "scene.camera.up", nonzero=True)
    view = [t - o for t, o in zip(target, origin)]
    if not any(view):
        raise r.error("scene.camera.target", "must differ from scene.camera.origin")
    cross = (view[1] * up[2] - view[2] * up[1], view[2] * up[0] - view[0] * up[2],
             view[0] * up[1] - view[1] * up[0])
    if math.hypot(*cross) <= 1e-9 * math.hypot(*view) * math.hypot(*up):
        raise r.error("scene.camera.up", "is parallel to the viewing direction (target - origin)")
    if _dist(origin, sphere.center) <= sphere.radius:
        raise r.error("scene.camera.origin", "lies inside the sphere; place the camera outside it")
    fov = r.number(tbl.get("fov", d.fov), "scene.camera.fov", lo=0.0, hi=179.0, lo_open=True)
    half = r.number(tbl.get("half_width", d.half_width), "scene.camera.half_width",
                    lo=0.0, lo_open=True)
    return Camera(type=kind, origin=origin, target=target, up=up, fov=fov, half_width=half)


def _dist(a, b) -> float:
    return math.sqrt(sum((x - y) ** 2 for x, y in zip(a, b)))


def _light(r: _Reader, tbl, where: str, sphere: Sphere):
    if not isinstance(tbl, Mapping):
        raise r.error(where, "expected a table [[scene.lights]]")
    if "type" not in tbl:
        raise r.error(f"{where}.type", "missing; allowed values: "
                      + ", ".join(repr(c) for c in LIGHT_TYPES))
    kind = r.choice(tbl["type"], f"{where}.type", LIGHT_TYPES)
    if kind == "point":
        r.table(tbl, where, {"type", "position", "intensity"})
        _require(r, tbl, where, ("position", "intensity"))
        pos = r.vec3(tbl["position"], f"{where}.position")
        if _dist(pos, sphere.center) <= sphere.radius:
            raise r.error(f"{where}.position", "lies inside the sphere")
        return PointLight(position=pos, intensity=r.vec3(tbl["intensity"], f"{where}.intensity",
                                                         nonneg=True))
    r.table(tbl, where, {"type", "direction", "irradiance"})
    _require(r, tbl, where, ("direction", "irradiance"))
    return DirectionalLight(direction=r.vec3(tbl["direction"], f"{where}.direction", nonzero=True),
                            irradiance=r.vec3(tbl["irradiance"], f"{where}.irradiance",
                                              nonneg=True))


def _require(r: _Reader, tbl, where: str, keys) -> None:
    for key in keys:
        if key not in tbl:
            raise r.error(f"{where}.{key}", "missing required key")


def _environment(r: _Reader, tbl: dict, base_dir: str) -> Environment:
    kind = r.choice(tbl.get("type", "black"), "scene.environment.type", ENVIRONMENT_TYPES)
    where = "scene.environment"
    if kind == "black":
        r.table(tbl, where, {"type"})
        return Environment()
    if kind == "constant":
        r.table(tbl, where, {"type", "radiance"})
        _require(r, tbl, where, ("radiance",))
        return Environment(type="constant",
                           radiance=r.vec3(tbl["radiance"], f"{where}.radiance", nonneg=True))
    r.table(tbl, where, {"type", "file", "scale"})
    _require(r, tbl, where, ("file",))
    file = _resolve(base_dir, r.string(tbl["file"], f"{where}.file"))
    if not os.path.isfile(file):
        raise r.error(f"{where}.file", f"envmap file {file} not found")
    scale = r.number(tbl.get("scale", 1.0), f"{where}.scale", lo=0.0)
    return Environment(type="envmap", file=file, scale=scale)


# --------------------------------------------------------------------------- material


def _option_names(lobe: str) -> set[str]:
    return {o.name for o in LOBES[lobe].options} if lobe in LOBES else set()


def _is_option_key(key: str) -> bool:
    lobe, _, name = key.partition(".")
    return name in _option_names(lobe)


def _material(r: _Reader, tbl: dict):
    r.table(tbl, "material", {"lobes", "truth", "init", "fixed", "options"})
    if "lobes" not in tbl:
        raise r.error("material.lobes", "missing; name the summed lobes, e.g. "
                      "[\"lambert\", \"torrance_sparrow\"]; known lobes: " + ", ".join(LOBES))
    lobes = tbl["lobes"]
    if isinstance(lobes, str):
        lobes = [s.strip() for s in lobes.split("+")]
    if not isinstance(lobes, list) or not all(isinstance(x, str) for x in lobes):
        raise r.error("material.lobes", f"expected a list of lobe names, got {_show(lobes)}")
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
    try:
        material = Material.make(lobes, options)
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


def _all_options(lobes) -> str:
    names = [f"{lb}.{o}" for lb in lobes for o in sorted(_option_names(lb))]
    return ", ".join(names) if names else "(none)"


def _values(r: _Reader, material: Material, tbl: dict, where: str, allow_options: bool):
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
                raise r.error(name, f"= {_show(value)} differs from the material's option "
                              f"value {chosen[key]!r}")
            continue
        if key not in specs:
            raise r.error(name, f"unknown parameter for lobes {', '.join(material.lobes)}; "
                          "known: " + ", ".join(specs))
        spec = specs[key]
        if isinstance(value, list):
            nums = [r.number(v, name) for v in value]
            if len(nums) not in (1, spec.size):
                raise r.error(name, f"expected {spec.size} value(s), got {len(nums)}")
        else:
            nums = [r.number(value, name)]
        if any(x < spec.lower or x > spec.upper for x in nums):
            raise r.error(name, f"= {_show(value)} is outside the lobe's valid range "
                          f"[{spec.lower:g}, {spec.upper:g}]")
        try:
            arr = material.full_params({key: nums if len(nums) > 1 else nums[0]})[key]
        except MaterialError as exc:
            raise r.error(name, str(exc)) from None
        out[key] = float(arr) if arr.ndim == 0 else tuple(float(x) for x in arr)
    return out


# --------------------------------------------------------------------------- fit / synth


def _fit(r: _Reader, tbl: dict, base_dir: str) -> FitOptions:
    fields = {f.name for f in dataclasses.fields(FitOptions)}
    r.table(tbl, "fit", fields)
    d = FitOptions()
    target = None
    if "target" in tbl:
        target = _resolve(base_dir, r.string(tbl["target"], "fit.target"))
    noise = tbl.get("noise_sigma")
    sat = tbl.get("saturation")
    steps, rtol, atol = tbl.get("max_steps"), tbl.get("rtol"), tbl.get("atol")
    return FitOptions(
        target=target,
        solver=r.choice(tbl.get("solver", d.solver), "fit.solver", solvers()),
        n_starts=r.integer(tbl.get("n_starts", d.n_starts), "fit.n_starts", lo=1),
        max_steps=None if steps is None else r.integer(steps, "fit.max_steps", lo=1),
        rtol=None if rtol is None else r.number(rtol, "fit.rtol", lo=0.0, lo_open=True),
        atol=None if atol is None else r.number(atol, "fit.atol", lo=0.0, lo_open=True),
        mask=r.choice(tbl.get("mask", d.mask), "fit.mask", MASKS),
        noise_sigma=None if noise is None else r.number(noise, "fit.noise_sigma", lo=0.0,
                                                        lo_open=True),
        loss=r.choice(tbl.get("loss", d.loss), "fit.loss", LOSSES),
        validate=r.boolean(tbl.get("validate", d.validate), "fit.validate"),
        validate_spp=r.integer(tbl.get("validate_spp", d.validate_spp), "fit.validate_spp",
                               lo=1),
        saturation=None if sat is None else r.number(sat, "fit.saturation", lo=0.0,
                                                     lo_open=True),
        dtype=r.choice(tbl.get("dtype", d.dtype), "fit.dtype", DTYPES),
    )


def _synth(r: _Reader, tbl: dict) -> SynthOptions:
    r.table(tbl, "synth", {"spp", "seed"})
    d = SynthOptions()
    return SynthOptions(spp=r.integer(tbl.get("spp", d.spp), "synth.spp", lo=1),
                        seed=r.integer(tbl.get("seed", d.seed), "synth.seed", lo=0))


# --------------------------------------------------------------------------- writing


def scene_to_dict(scene: Scene) -> dict:
    """The ``[scene]`` table of ``scene`` (TOML/JSON-ready; inverse of ``scene_from_dict``)."""
    cam = scene.camera
    camera = {"type": cam.type, "origin": list(cam.origin), "target": list(cam.target),
              "up": list(cam.up)}
    if cam.type == "perspective":
        camera["fov"] = cam.fov
    else:
        camera["half_width"] = cam.half_width
    lights = []
    for lt in scene.lights:
        if lt.type == "point":
            lights.append({"type": "point", "position": list(lt.position),
                           "intensity": list(lt.intensity)})
        else:
            lights.append({"type": "directional", "direction": list(lt.direction),
                           "irradiance": list(lt.irradiance)})
    env = scene.environment
    environment: dict[str, Any] = {"type": env.type}
    if env.type == "constant":
        environment["radiance"] = list(env.radiance)
    elif env.type == "envmap":
        environment.update(file=env.file, scale=env.scale)
    out = {"width": scene.width, "height": scene.height, "supersampling": scene.supersampling}
    if scene.pixel_rule != Scene().pixel_rule:
        out["pixel_rule"] = scene.pixel_rule
    return {**out, "camera": camera,
            "sphere": {"center": list(scene.sphere.center), "radius": scene.sphere.radius},
            "lights": lights, "environment": environment}


def material_to_dict(material: Material, truth=None, init=None, fixed=None) -> dict:
    """The ``[material]`` table: lobes, options folded into ``fixed``, numeric tables."""
    out: dict[str, Any] = {"lobes": list(material.lobes)}
    fixed_all = {k: v for k, v in material.options}
    fixed_all.update(_listed(fixed or {}))
    for name, values in (("truth", truth), ("init", init)):
        if values:
            out[name] = _listed(values)
    if fixed_all:
        out["fixed"] = fixed_all
    return out


def job_to_dict(job: Job) -> dict:
    """The whole job in the TOML layout (paths absolute)."""
    fit = {k: v for k, v in dataclasses.asdict(job.fit).items() if v is not None}
    return {"scene": scene_to_dict(job.scene),
            "material": material_to_dict(job.material, job.truth, job.init, job.fixed),
            "fit": fit, "synth": dataclasses.asdict(job.synth)}


def _listed(values: Mapping[str, Any]) -> dict:
    return {k: list(v) if isinstance(v, (tuple, list)) else v for k, v in values.items()}


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
    return k if bare else '"' + k.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")

"""A material: which lobes are summed, their options, and parameter handling.

Parameters are addressed as ``"lobe.param"`` (``"lambert.rho_d"``,
``"torrance_sparrow.m"``). A parameter of a named lobe that is not given takes
the lobe's documented default. RGB parameters accept a scalar (grey) or three
values.

One parameter belongs to no lobe: ``"exposure"`` (``EXPOSURE``), a camera
exposure / light scale multiplying the whole rendered radiance. A material has
it only when asked (``Material.make(..., exposure=True)``; a config or a fit
naming ``exposure`` in its truth, init or fixed values), so a material without
it renders and fits exactly as before. Like ``torrance_sparrow.rho_s`` it is
fixed by default (at 1) and freed by giving it an initial value.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from . import checks
from .bsdf import LOBES
from .bsdf.base import Lobe, Param
from .errors import FitterError


class MaterialError(FitterError):
    """A material or parameter specification a user must fix (message names the key)."""


#: The key of the exposure parameter (no lobe's: it scales the whole image).
EXPOSURE_KEY = "exposure"
#: Camera exposure / light scale: the rendered radiance (lights, environment and
#: background alike) times this scalar. Fixed at 1 unless given an initial value.
#: Box [1e-3, 1e3], fitted in log: an unknown scale may be off by decades.
EXPOSURE = Param(EXPOSURE_KEY, 1, 1.0, 1e-3, 1e3, "log",
                 "camera exposure / light scale: multiplies the whole rendered radiance "
                 "(lights, environment, background)", free=False)


@dataclasses.dataclass(frozen=True)
class Material:
    """Names of the summed lobes and their (static) options.

    Attributes:
        lobes: lobe names, e.g. ``("lambert", "torrance_sparrow")``.
        options: sorted ``(("lobe.option", value), ...)`` pairs; missing ones
            take the lobe's default. Build with ``Material.make``.
        exposure: whether the parameters include ``"exposure"`` (``EXPOSURE``),
            which multiplies the whole rendered radiance.
    """

    lobes: tuple[str, ...]
    options: tuple[tuple[str, Any], ...] = ()
    exposure: bool = False

    @classmethod
    def make(cls, lobes, options: Mapping[str, Any] | None = None,
             exposure: bool = False) -> "Material":
        if isinstance(lobes, str):
            lobes = tuple(s.strip() for s in lobes.split("+"))
        if not isinstance(lobes, (list, tuple)):
            raise MaterialError("material: expected a Material, a list of lobe names or a "
                                f"'lambert+phong' string, got {checks.show(lobes)}")
        lobes = tuple(lobes)
        if not lobes:
            raise MaterialError("material.lobes is empty; name at least one of: "
                                + ", ".join(LOBES))
        for name in lobes:
            if name not in LOBES:
                raise MaterialError(f"unknown lobe {name!r}; known lobes: {', '.join(LOBES)}")
        if len(set(lobes)) != len(lobes):
            raise MaterialError(f"material.lobes names a lobe twice: {list(lobes)}")
        full = {}
        for name in lobes:
            for opt in LOBES[name].options:
                full[f"{name}.{opt.name}"] = opt.default
        for key, value in (options or {}).items():
            lobe, opt = _split_key(key, lobes)
            try:
                spec = LOBES[lobe].option(opt)
            except KeyError:
                raise MaterialError(f"{key!r} is not an option of lobe {lobe!r}") from None
            if spec.choices is None:
                if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                    raise MaterialError(f"{key} = {value!r}: expected an integer >= 0")
                if spec.most is not None and value > spec.most:
                    raise MaterialError(f"{key} = {value!r} is over the limit of {spec.most}")
            elif value not in spec.choices or type(value) is not type(spec.default):
                raise MaterialError(f"{key} = {value!r}: allowed values are "
                                    + ", ".join(repr(c) for c in spec.choices))
            full[key] = value
        return cls(lobes, tuple(sorted(full.items())), bool(exposure))

    def with_exposure(self) -> "Material":
        """This material with the ``exposure`` parameter (itself if it has it)."""
        return self if self.exposure else dataclasses.replace(self, exposure=True)

    @classmethod
    def given(cls, material, values: Mapping[str, Any]) -> "Material":
        """``material`` (a ``Material``, a lobe list or a ``"lambert+phong"``
        string; None: the lobes the keys of ``values`` name, ``from_params``)
        with the option values ``values`` holds (``"torrance_sparrow.geometry":
        "smith"``) in place of its own, and the exposure where ``values`` has
        one: how ``render`` and ``fit`` (its init and fixed) read a lobe string
        beside parameters that name options."""
        if material is None:
            return cls.from_params(values)
        material = material if isinstance(material, Material) else cls.make(material)
        options = {k: v for k, v in values.items() if k in material.option_keys()}
        if options:
            material = cls.make(material.lobes, {**dict(material.options), **options},
                                exposure=material.exposure)
        return material.with_exposure() if EXPOSURE_KEY in values else material

    @property
    def lobe_objects(self) -> tuple[Lobe, ...]:
        return tuple(LOBES[n] for n in self.lobes)

    @property
    def single_precision(self) -> bool:
        """Whether every lobe allows the fit's float32 estimates (``Lobe.single_precision``)."""
        return all(lb.single_precision for lb in self.lobe_objects)

    @property
    def opaque(self) -> list[str]:
        """Names of the opaque (``brdf``) lobes: those lights and an environment light."""
        return [lb.name for lb in self.lobe_objects if lb.kind == "brdf"]

    @property
    def stencil_lobes(self) -> list[str]:
        """Names of the opaque lobes an environment's sky lights through the sky
        stencil (not ``Lobe.stencil_free``): without any, no sky table is made."""
        return [lb.name for lb in self.lobe_objects if lb.kind == "brdf" and not lb.stencil_free]

    def options_of(self, lobe: str) -> dict[str, Any]:
        return lobe_params(dict(self.options), lobe)

    def param_specs(self) -> dict[str, Param]:
        """``{"lobe.param": Param}`` for every parameter of every lobe, in order
        (as the material's options select them: ``Lobe.params_for``), then
        ``"exposure"`` if the material has it."""
        specs = {f"{n}.{p.name}": p for n in self.lobes
                 for p in LOBES[n].params_for(self.options_of(n))}
        if self.exposure:
            specs[EXPOSURE_KEY] = EXPOSURE
        return specs

    def option_keys(self) -> set[str]:
        return {k for k, _ in self.options}

    def full_params(self, params: Mapping[str, Any] | None = None) -> dict[str, np.ndarray]:
        """Complete, validated float64 parameters: given values, defaults elsewhere.

        A parameter with named values (``Param.named``: a conductor's ``eta``
        and ``k``) may be given by name, e.g. ``"Au"``. Raises MaterialError naming the key for an unknown key, a wrong size,
        a non-finite value or a value outside the lobe's documented box.
        """
        specs = self.param_specs()
        out = {k: _shaped(s.default, s) for k, s in specs.items()}
        if params is not None and not isinstance(params, Mapping):
            raise MaterialError("parameters: expected a dict {'lobe.param': value}, got "
                                + checks.show(params))
        for key, value in (params or {}).items():
            if key in self.option_keys():
                continue
            if key not in specs:
                hint = ("; a material has it when it is named in the truth, init or fixed "
                        "values (Material.make(..., exposure=True))"
                        if key == EXPOSURE_KEY else "")
                raise MaterialError(
                    f"unknown parameter {key!r} for lobes {list(self.lobes)}; known: "
                    + ", ".join(specs) + hint)
            spec = specs[key]
            name = value if isinstance(value, str) else None
            if name is not None and spec.named is not None:
                if name not in spec.named:
                    raise MaterialError(f"{key} = {name!r} is not a known name; known: "
                                        + ", ".join(spec.named))
                value = spec.named[name]
            try:
                arr = np.asarray(value)
            except Exception:  # noqa: BLE001 (whatever a foreign object raises)
                arr = np.asarray(None)
            if arr.dtype.kind not in "iuf":  # bool, str, object: not numbers
                raise MaterialError(f"{key}: expected a number"
                                    + (" or 3 numbers" if spec.size == 3 else "")
                                    + f", got {checks.show(value)}")
            if arr.shape not in ((), (1,), spec.shape):
                raise MaterialError(f"{key}: expected {spec.size} value(s), got {arr.size}")
            shown = checks.show(arr.item() if arr.size == 1 else arr.tolist())
            if name is not None:
                shown = f"{name!r} ({shown})"
            arr = _shaped(arr, spec)
            if not np.all(np.isfinite(arr)):
                raise MaterialError(f"{key} = {shown} is not finite")
            if np.any(arr < spec.lower) or np.any(arr > spec.upper):
                raise MaterialError(f"{key} = {shown} is outside its valid range "
                                    f"[{spec.lower:g}, {spec.upper:g}]")
            out[key] = arr
        return out

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> "Material":
        """Infer the material from ``"lobe.x"`` keys; string/bool values are options;
        an ``"exposure"`` key gives it the exposure."""
        lobes, options = [], {}
        for key, value in params.items():
            if key == EXPOSURE_KEY:
                continue
            lobe = key.split(".", 1)[0]
            if lobe not in lobes:
                lobes.append(lobe)
            # A string is an option value, unless the key names a parameter
            # (a conductor's eta = "Au": ``Param.named``).
            if isinstance(value, bool) or (lobe in LOBES and _is_option(
                    lobe, key.split(".", 1)[-1])) or (isinstance(value, str) and not (
                    lobe in LOBES and _is_param(lobe, key.split(".", 1)[-1]))):
                options[key] = value
        return cls.make(lobes, options, exposure=EXPOSURE_KEY in params)


def _is_option(lobe: str, name: str) -> bool:
    return any(o.name == name for o in LOBES[lobe].options)


def _is_param(lobe: str, name: str) -> bool:
    return any(p.name == name for ps in (LOBES[lobe].params, *LOBES[lobe].variants.values())
               for p in ps)


def _split_key(key: str, lobes) -> tuple[str, str]:
    lobe, _, name = key.partition(".")
    if not name or lobe not in lobes:
        raise MaterialError(f"{key!r} does not name a lobe of this material "
                            f"(lobes: {list(lobes)}); expected 'lobe.name'")
    return lobe, name


def _shaped(value, spec: Param) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if spec.size == 1:
        return arr.reshape(())
    return np.broadcast_to(arr, (spec.size,)).copy()


def lobe_params(params: Mapping[str, Any], lobe: str) -> dict[str, Any]:
    """The ``{"param": value}`` sub-dict of one lobe from flat ``"lobe.param"`` keys
    (options too: ``"lobe.option"``)."""
    prefix = lobe + "."
    return {k[len(prefix):]: v for k, v in params.items() if k.startswith(prefix)}

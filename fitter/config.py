"""Fit jobs as TOML files: parsed with ``tomllib`` (data only) into frozen dataclasses.

``load_config(path) -> Job`` validates everything a user can get wrong and
raises ``ConfigError`` with one sentence naming the file, the key and what is
allowed. Unknown keys are errors (pbrt's ``ReportUnused``). Relative paths
(``fit.target``, ``scene.environment.file``) resolve against the config
file's folder. Every key is documented in ``configs/README.md``.

Layout: ``[scene]``, ``[material]`` and ``[synth]`` as in ``fitter.serialize``
(their readers and writers, re-exported here), plus::

    [fit]              target, solver, n_starts, max_steps, rtol, atol, ...
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from typing import Any, Mapping

from . import checks
from .fit import LOSSES, SOLVERS
from .imageio import ENCODINGS
from .material import Material
from .scene import Scene, resolve_path
from .serialize import (  # the table readers and writers; re-exported for cli.py and tests
    ConfigError as ConfigError,
    Reader,
    SynthOptions as SynthOptions,
    base_dir_of,
    dumps_toml as dumps_toml,
    material_from_dict as material_from_dict,
    material_to_dict as material_to_dict,
    scene_from_dict as scene_from_dict,
    scene_to_dict as scene_to_dict,
    synth_from_dict,
    synth_to_dict,
)

MASKS = ("interior", "active")


def solvers() -> tuple[str, ...]:
    """Solver names the fit engine accepts (``fitter.fit.SOLVERS``)."""
    return SOLVERS


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
        target_encoding: how the target file's values are encoded
            (``imageio.ENCODINGS``: "auto", "srgb" or "linear").
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
    target_encoding: str = "auto"

    def replace(self, **changes) -> "FitOptions":
        return dataclasses.replace(self, **changes)


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


# --------------------------------------------------------------------------- reading


def load_config(path: str) -> Job:
    """Read and validate the TOML fit job at ``path``; raises ``ConfigError``."""
    try:
        with open(path, "rb") as fh:
            text = fh.read().decode("utf-8-sig")  # editors on Windows write a BOM
        data = tomllib.loads(text)
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
    r = Reader(path)
    base_dir = base_dir_of(path, base_dir)
    r.table(data, "", {"scene", "material", "fit", "synth"})
    scene = scene_from_dict(r.sub(data, "scene", required=True), path, base_dir)
    material, truth, init, fixed = material_from_dict(r.sub(data, "material", required=True),
                                                      path)
    fit = _fit_from_dict(r, r.sub(data, "fit"), base_dir)
    synth = synth_from_dict(r.sub(data, "synth"), path)
    return Job(os.path.abspath(path) if not path.startswith("<") else path, base_dir,
               scene, material, truth, init, fixed, fit, synth)


def job_to_dict(job: Job) -> dict:
    """The whole job in the TOML layout (paths absolute)."""
    fit = {k: v for k, v in dataclasses.asdict(job.fit).items() if v is not None}
    return {"scene": scene_to_dict(job.scene),
            "material": material_to_dict(job.material, job.truth, job.init, job.fixed),
            "fit": fit, "synth": synth_to_dict(job.synth)}


def _fit_from_dict(r: Reader, tbl: dict, base_dir: str) -> FitOptions:
    fields = {f.name for f in dataclasses.fields(FitOptions)}
    r.table(tbl, "fit", fields)
    d = FitOptions()
    target = None
    if "target" in tbl:
        target = resolve_path(r.string(tbl["target"], "fit.target"), base_dir)

    def rule(name):  # checks.FIT_RULES: the same rule as fitter.fit's keyword
        value = tbl.get(name, getattr(d, name))
        return None if value is None else r.check(checks.fit_option, name, f"fit.{name}",
                                                  value)

    return FitOptions(
        target=target,
        solver=r.choice(tbl.get("solver", d.solver), "fit.solver", solvers()),
        mask=r.choice(tbl.get("mask", d.mask), "fit.mask", MASKS),
        loss=r.choice(tbl.get("loss", d.loss), "fit.loss", LOSSES),
        target_encoding=r.choice(tbl.get("target_encoding", d.target_encoding),
                                 "fit.target_encoding", ENCODINGS),
        **{name: rule(name) for name in ("n_starts", "max_steps", "rtol", "atol",
                                         "noise_sigma", "validate", "validate_spp",
                                         "saturation", "dtype")},
    )

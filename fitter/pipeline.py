"""One fit job from start to end: target -> fit -> rendered fit -> validation -> truth errors.

``run_job(job, target, saturated) -> Outcome`` is what ``fitter fit`` (and a
batch of jobs) runs; the CLI only reads inputs, writes ``outcome`` and prints
it. ``Outcome.to_dict()`` is the result-JSON contract (configs/README.md).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import platform
import time
from typing import TYPE_CHECKING, Any, Callable, ContextManager, Mapping

import numpy as np

from .imageio import ImageError, encoding_note
from .serialize import plain

if TYPE_CHECKING:  # the fit engine imports JAX: only when a job runs
    from .config import Job
    from .fit.result import FitResult

#: ``stage(text)`` wraps each step of a job (progress display); default silent.
#: What it yields, if not None, is called with progress lines of the step
#: (``fitter.fit``'s ``progress``: starts done, their steps and cost).
Stage = Callable[[str], ContextManager]


@dataclasses.dataclass(frozen=True)
class Validation:
    """The Mitsuba re-render of a fit compared with the target (``fitter.metrics``)."""

    image: np.ndarray  # (H, W, 3) linear RGB
    spp: int
    seed: int
    rmse: float
    psnr_db: float
    delta_e2000_mean: float
    delta_e2000_max: float
    n_pixels: int
    renderer: str = "mitsuba"

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "image"}
        return plain({"renderer": d.pop("renderer"), "spp": d.pop("spp"),
                      "seed": d.pop("seed"), **d})


@dataclasses.dataclass(frozen=True)
class TruthError:
    """A fitted parameter against the config's truth (arrays of the parameter's shape)."""

    truth: np.ndarray
    fit: np.ndarray
    abs: np.ndarray  # |fit - truth|
    rel: np.ndarray  # abs / |truth|, NaN where truth is 0
    sigmas: np.ndarray | None  # abs / stderr, NaN where stderr is 0; None without stderr

    def to_dict(self) -> dict:
        d = {"truth": self.truth, "fit": self.fit, "abs": self.abs, "rel": self.rel}
        if self.sigmas is not None:
            d["sigmas"] = self.sigmas
        return plain(d)

    @property
    def worst_sigmas(self) -> float:
        """The largest finite error / stderr, NaN when there is none."""
        if self.sigmas is None:
            return math.nan
        s = np.atleast_1d(np.asarray(self.sigmas, dtype=float))
        return float(np.nanmax(s)) if np.isfinite(s).any() else math.nan


@dataclasses.dataclass(frozen=True)
class Outcome:
    """Everything one job produced (images are (H, W, 3) linear RGB float64)."""

    job: Job
    target_path: str
    target: np.ndarray
    fit: FitResult
    rendered: np.ndarray  # the forward model at the fitted parameters
    validation: Validation | None
    truth_error: dict[str, TruthError]  # empty without [material.truth]
    stage_times: dict[str, float]  # seconds per stage, in order

    @property
    def residual(self) -> np.ndarray:
        return self.target - self.rendered

    @property
    def fitted(self) -> np.ndarray:
        """(H, W) bool: the pixels the fit used."""
        return self.fit.fitted

    @property
    def converged(self) -> bool:
        return self.fit.converged

    def to_dict(self) -> dict:
        """The result JSON: ``FitResult.to_dict()`` plus solver, truth errors, paths, validation."""
        d = self.fit.to_dict()
        d["solver"] = self.job.fit.solver
        if self.truth_error:
            d["truth_error"] = {k: te.to_dict() for k, te in self.truth_error.items()}
        d["target"] = self.target_path
        d["config"] = self.job.path
        if self.validation is not None:
            d["validation"] = self.validation.to_dict()
        d["software"] = software()
        return plain(d)


#: Libraries whose installed versions a result records (a warm run's solve comes
#: from a trace cached under these versions, without importing optimistix).
RECORDED = ("jax", "jaxlib", "optimistix", "equinox", "lineax", "numpy", "mitsuba", "drjit")


def software() -> dict[str, str]:
    """The versions that made a result: fitter's, Python's and the installed
    ``RECORDED`` libraries' (6 ms of package metadata; one not installed is absent)."""
    from importlib import metadata

    from . import __version__

    out = {"fitter": __version__, "python": platform.python_version()}
    for name in RECORDED:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def _silent(text: str) -> ContextManager:
    return contextlib.nullcontext()


def run_job(job: Job, target: np.ndarray, saturated: np.ndarray | None = None, *,
            target_path: str = "", stage: Stage = _silent, compare=None) -> Outcome:
    """Fit ``job`` to ``target``, render the fit, validate it (``job.fit.validate``).

    Args:
        job: a loaded config (``fitter.config.load_config``).
        target: (H, W, 3) linear RGB, checked by ``read_target``.
        saturated: (H, W) bool pixels clipped in an 8-bit file (excluded).
        target_path: recorded in the result.
        stage: progress wrapper, called with a short text per step.
        compare: scores the validation instead of ``fitter.metrics.compare``
            (``validate``).
    """
    preflight(job)
    times: dict[str, float] = {}

    @contextlib.contextmanager
    def timed(key: str, text: str):
        t0 = time.perf_counter()
        with stage(text) as note:
            yield note
        times[key] = time.perf_counter() - t0

    if saturated is None:
        saturated = np.zeros(target.shape[:2], dtype=bool)
    with timed("fit", f"fitting ({job.fit.solver}, {job.fit.n_starts} start(s))") as note:
        result = fit_job(job, target, saturated, progress=note)
    with timed("render", "rendering the fit"):
        rendered = render_params(job, result.params)
    validation = None
    if job.fit.validate:
        spp = job.fit.validate_spp
        with timed("validate", f"validating with Mitsuba ({spp} spp)"):
            validation = validate(job, result.params, target, saturated, spp, compare)
    truth = truth_error(result.params, result.stderr, job.truth) if job.truth else {}
    note = encoding_note(target_path or (job.fit.target or ""), job.fit.target_encoding)
    if note:
        result.warnings.append(note)
    return Outcome(job=job, target_path=target_path or (job.fit.target or ""), target=target,
                   fit=result, rendered=rendered, validation=validation, truth_error=truth,
                   stage_times=times)


def preflight(job: Job) -> None:
    """Refuse, before any work, a job over the limits of ``fitter.limits``."""
    from . import limits

    from .envlight import unlit
    from .serialize import ConfigError

    reason = unlit(job.scene, job.material, job.base_dir)
    if reason:
        raise ConfigError(f"{job.path}: {reason}")
    limits.check_scene("fit", job.scene, job.material, where=job.path, base_dir=job.base_dir,
                       n_starts=job.fit.n_starts)
    if job.fit.validate:
        limits.check_spp(job.fit.validate_spp, "fit.validate_spp", where=job.path)


def fit_job(job: Job, target: np.ndarray, saturated: np.ndarray,
            progress: Callable[[str], None] | None = None) -> FitResult:
    """The fit engine on ``job``'s scene, material and ``[fit]`` options;
    ``progress`` gets the fit's progress lines (``fitter.fit``)."""
    import jax.numpy as jnp

    from . import fit as engine

    opts = job.fit
    kwargs = {k: getattr(opts, k) for k in ("rtol", "atol", "max_steps")
              if getattr(opts, k) is not None}
    return engine.fit(
        target, job.scene, job.material, init=job.init, fixed=job.fixed,
        solver=opts.solver, mask=opts.mask, exclude=saturated if saturated.any() else None,
        noise_sigma=opts.noise_sigma, loss=opts.loss, saturation=opts.saturation,
        n_starts=opts.n_starts, dtype=getattr(jnp, opts.dtype), base_dir=job.base_dir,
        progress=progress, **kwargs)


def render_params(job: Job, params: Mapping[str, Any]) -> np.ndarray:
    """The forward model's (H, W, 3) image of ``params`` (defaults filled in).

    Uses the fit's prepared renderer (``cached_renderer``) and one compiled
    render whose trace the fit's persistent cache keeps (``fit._cache``): an
    eager render compiles a small kernel per operation (0.2-0.3 s a run).
    """
    import jax
    import jax.numpy as jnp

    from .compilation_cache import FAST_COMPILE
    from .fit._cache import compile_cached
    from .render import cached_renderer, exposed_background, render_active

    material, scene = job.material, job.scene
    full = job.material.full_params(params)
    numeric = {k: v for k, v in full.items() if k not in material.option_keys()}
    rend = cached_renderer(scene, material, jnp.dtype("float64"),
                           os.path.abspath(job.base_dir) if job.base_dir else None)
    p = rend.params(numeric)
    args = (p, rend.geometry, rend.env, rend.sphere)
    env_type = rend.env_type

    def active(p, geo, env, sphere):
        return render_active(p, geo, env, sphere, material=material, env_type=env_type)

    shapes = jax.tree_util.tree_map(lambda a: (jnp.shape(a), str(jnp.result_type(a))), args)
    exe = compile_cached(active, args, repr(("render_active", material, env_type, str(shapes))),
                         FAST_COMPILE)
    vals = np.asarray(exe(*args))
    img = np.array(exposed_background(material, p, rend.geometry.background_image))
    img[np.asarray(rend.pixel_index)] = vals
    return img.reshape(scene.height, scene.width, 3)


def validation_seed(job: Job) -> int:
    """Sampler seed of validation renders: never the synth seed, so that a
    validation at the target's spp does not reproduce the target's noise."""
    return job.synth.seed + 1


def validate(job: Job, params: Mapping[str, Any], target: np.ndarray,
             saturated: np.ndarray | None, spp: int, compare=None) -> Validation:
    """Mitsuba re-render of ``params`` and its comparison with ``target``.

    ``compare(target, image, mask)``: ``fitter.metrics.compare``'s scores
    computed elsewhere (``fitter.report_process``), or None for this process
    to compute them."""
    from . import metrics, mitsuba

    full = job.material.full_params(params)
    seed = validation_seed(job)
    img = np.asarray(mitsuba.render(job.scene, job.material, full, spp=spp, seed=seed,
                                    base_dir=job.base_dir), dtype=np.float64)
    from .render import cached_renderer

    # Score the sphere's pixels only (the background is the environment in both).
    rend = cached_renderer(job.scene, job.material, np.dtype("float64"),
                           os.path.abspath(job.base_dir) if job.base_dir else None)
    mask = np.zeros(job.scene.height * job.scene.width, bool)
    mask[np.asarray(rend.pixel_index)] = True
    mask = mask.reshape(job.scene.height, job.scene.width)
    if saturated is not None and saturated.any():
        mask &= ~saturated
    scores = compare(target, img, mask) if compare is not None else None
    if scores is None:
        scores = metrics.compare(target, img, mask=mask)
    return Validation(image=img, spp=spp, seed=seed, **scores)


def truth_error(params: Mapping[str, Any], stderr: Mapping[str, Any],
                truth: Mapping[str, Any]) -> dict[str, TruthError]:
    """Per truth parameter, the fit's error (and in standard errors where one exists)."""
    out = {}
    for key, t in truth.items():
        t = np.asarray(t, dtype=np.float64)
        f = np.asarray(params[key], dtype=np.float64)
        err = np.abs(f - t)
        rel = np.where(t != 0, err / np.where(t != 0, np.abs(t), 1.0), np.nan)
        sigmas = None
        if key in stderr:
            s = np.asarray(stderr[key], dtype=np.float64)
            with np.errstate(divide="ignore", invalid="ignore"):
                sigmas = np.where(s > 0, err / s, np.nan)
        out[key] = TruthError(truth=t, fit=f, abs=err, rel=rel, sigmas=sigmas)
    return out


def truth_params(job: Job) -> dict[str, Any]:
    """Complete parameters of the config's truth (fixed values where truth is silent)."""
    return job.material.full_params({**job.fixed, **job.truth})


def read_target(path: str, scene, encoding: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Target (H, W, 3) linear float64 and (H, W) saturated mask, checked against ``scene``;
    ``encoding``: how the file's values are encoded (``imageio.ENCODINGS``).

    Raises ``ImageError`` naming the file for a missing/unreadable file, a
    size other than the scene's, NaN/Inf or negative pixel values.
    """
    from .imageio import check_radiance, read_image

    if os.path.isdir(path):
        raise ImageError(f"{path}: is a folder, expected a target image file")
    img, saturated = read_image(path, with_saturation=True, encoding=encoding)
    h, w = img.shape[:2]
    if (w, h) != (scene.width, scene.height):
        raise ImageError(f"{path}: image is {w}x{h} pixels but the scene is "
                         f"{scene.width}x{scene.height} (scene.width x scene.height)")
    check_radiance(img, path, "a target")
    return img, saturated


"""The ``fitter`` command line: fit, synth, validate, render, bench.

Every command reads one TOML job (``fitter.config``). Exit codes:

* 0: done (for ``fit``: the fit converged);
* 1: an unexpected internal error (with a traceback);
* 2: bad input (config, image, parameters, command line): one sentence on
  stderr naming the file/key/value, and no output written;
* 3: ``fit`` ran but the fit did not converge (``status`` is ``"max_steps"``
  or ``"failed"``); all outputs are still written.

Outputs of ``fitter fit`` go to ``--out`` (default ``out/<config stem>``
relative to the working directory), staged and swapped in by
``fitter.outdir``: only a folder fitter wrote is ever replaced, and an
interrupted or failed run leaves no half-written folder. ``--json`` prints exactly one JSON document on stdout;
progress and log lines go to stderr (silenced by ``--quiet``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import sys
import tempfile
import time
from typing import Any, Mapping, Sequence

import numpy as np

from .config import Job, dumps_toml, job_to_dict, load_config, solvers
from .imageio import ImageError
from .outdir import staged_dir
from .errors import FitterError

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_NOT_CONVERGED = 0, 1, 2, 3


class UsageError(FitterError):
    """A command-line mistake (message is one sentence)."""


# --------------------------------------------------------------------------- entry point


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    parser = _parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv[:1] == ["bench"]:  # REMAINDER does not take a leading "--option"
            args = argparse.Namespace(rest=argv[1:], run=cmd_bench)
        else:
            args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse printed usage and the reason
        return EXIT_OK if exc.code == 0 else EXIT_INPUT
    _enable_compilation_cache()
    try:
        with _sigterm_as_interrupt():
            return args.run(args)
    except KeyboardInterrupt:
        print("fitter: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if _is_user_error(exc):
            print(f"fitter: error: {exc}", file=sys.stderr)
            return EXIT_INPUT
        raise


def _enable_compilation_cache() -> None:
    """Keep compiled solvers on disk, so a repeated job skips XLA compilation.

    Folder: ``$FITTER_CACHE_DIR``, else ``$XDG_CACHE_HOME/fitter/jax`` (default
    ``~/.cache/fitter/jax``); ``FITTER_CACHE_DIR=""`` turns it off.
    """
    import os

    folder = os.environ.get("FITTER_CACHE_DIR")
    if folder is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        folder = os.path.join(base, "fitter", "jax")
    if not folder:
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """Let SIGTERM unwind like Ctrl-C so staged output folders are removed."""
    import signal

    def handler(signum, frame):
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _is_user_error(exc: BaseException) -> bool:
    return isinstance(exc, FitterError)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fitter",
        description="Recover BSDF parameters from images of a sphere (JAX forward model, "
                    "Mitsuba 3 validation). Configs are documented in configs/README.md.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    f = sub.add_parser("fit", help="fit a material to a target image",
                       description="Fit the material of CONFIG to its target image and write "
                                   "result.json, fit.exr, residual.exr, validation.exr and "
                                   "report.png to OUT. Exit 0 converged, 2 bad input, "
                                   "3 not converged.")
    f.add_argument("config", metavar="CONFIG.toml")
    f.add_argument("--target", metavar="IMG", help="target image (overrides fit.target)")
    f.add_argument("--out", metavar="DIR", help="output folder (default: out/<config stem>)")
    f.add_argument("--json", action="store_true",
                   help="print the result as one JSON document on stdout")
    f.add_argument("--solver", help="override fit.solver (one of: %s)" % ", ".join(
        _solver_names()))
    f.add_argument("--validate", action=argparse.BooleanOptionalAction, default=None,
                   help="re-render the fit with Mitsuba and compare (default: fit.validate)")
    f.add_argument("--quiet", action="store_true", help="no progress or log output")
    f.set_defaults(run=cmd_fit)

    s = sub.add_parser("synth", help="render a target with Mitsuba from [material.truth]",
                       description="Render CONFIG's scene with its [material.truth] in Mitsuba "
                                   "and write target.exr, preview.png and case.json to OUT "
                                   "(default: the folder of fit.target).")
    s.add_argument("config", metavar="CONFIG.toml")
    s.add_argument("--out", metavar="DIR")
    s.add_argument("--spp", type=int, help="samples per pixel (default: synth.spp)")
    s.add_argument("--seed", type=int, help="random seed (default: synth.seed)")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(run=cmd_synth)

    v = sub.add_parser("validate", help="re-render a fitted result with Mitsuba and compare",
                       description="Render CONFIG's scene with the parameters of RESULT.json "
                                   "in Mitsuba and compare with the target image.")
    v.add_argument("config", metavar="CONFIG.toml")
    v.add_argument("result", metavar="RESULT.json")
    v.add_argument("--target", metavar="IMG", help="target image (overrides fit.target)")
    v.add_argument("--spp", type=int, help="samples per pixel (default: fit.validate_spp)")
    v.add_argument("--out", metavar="IMG", help="also write the Mitsuba render here")
    v.add_argument("--json", action="store_true")
    v.add_argument("--quiet", action="store_true")
    v.set_defaults(run=cmd_validate)

    r = sub.add_parser("render", help="render with the JAX forward model",
                       description="Render CONFIG's scene with the forward model "
                                   "(fitter.render) and write the image (EXR/HDR linear, "
                                   "PNG/JPEG/TIFF sRGB).")
    r.add_argument("config", metavar="CONFIG.toml")
    r.add_argument("--params", metavar="RESULT.json",
                   help="parameters: a result.json or a flat {\"lobe.param\": value} JSON "
                        "(default: the config's [material.truth] and [material.fixed])")
    r.add_argument("--out", metavar="IMG", required=True)
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(run=cmd_render)

    b = sub.add_parser("bench", help="benchmarks (fitter.bench)", add_help=False)
    b.add_argument("rest", nargs=argparse.REMAINDER)
    b.set_defaults(run=cmd_bench)
    return p


def _solver_names() -> tuple[str, ...]:
    try:
        return solvers()
    except Exception:  # the help text must not depend on the engine importing
        return ("levenberg_marquardt",)


# --------------------------------------------------------------------------- console


class _Log:
    """Progress spinner and log lines on stderr; silent when ``quiet``."""

    def __init__(self, quiet: bool):
        from rich.console import Console

        self.console = Console(stderr=True, quiet=quiet, highlight=False)

    @contextlib.contextmanager
    def stage(self, text: str):
        t0 = time.perf_counter()
        with self.console.status(text + " ..."):
            yield
        self.console.print(f"[dim]{text}: {time.perf_counter() - t0:.2f} s[/dim]")

    def print(self, *args, **kwargs):
        self.console.print(*args, **kwargs)


# --------------------------------------------------------------------------- inputs


def read_target(path: str, scene) -> tuple[np.ndarray, np.ndarray]:
    """Target (H, W, 3) linear float64 and (H, W) saturated mask, checked against ``scene``.

    Raises ``ImageError`` naming the file for a missing/unreadable file, a
    size other than the scene's, NaN/Inf or negative pixel values.
    """
    from .imageio import read_image

    if os.path.isdir(path):
        raise ImageError(f"{path}: is a folder, expected a target image file")
    img, saturated = read_image(path, with_saturation=True)
    h, w = img.shape[:2]
    if (w, h) != (scene.width, scene.height):
        raise ImageError(f"{path}: image is {w}x{h} pixels but the scene is "
                         f"{scene.width}x{scene.height} (scene.width x scene.height)")
    bad = ~np.isfinite(img)
    if bad.any():
        raise ImageError(f"{path}: {int(bad.any(axis=-1).sum())} pixel(s) are NaN or Inf")
    if (img < 0).any():
        raise ImageError(f"{path}: {int((img < 0).any(axis=-1).sum())} pixel(s) have negative "
                         f"values (minimum {img.min():.3g}); a target must be linear "
                         "radiance >= 0")
    return img, saturated


def _target_path(job: Job, override: str | None) -> str:
    if override:
        return os.path.abspath(override)
    if job.fit.target is None:
        raise UsageError(f"{job.path}: fit.target is not set; add it to [fit] or pass --target")
    return job.fit.target


def read_params(path: str, job: Job) -> dict[str, Any]:
    """Parameters from a result.json (its ``params``) or a flat JSON dict, validated."""
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise UsageError(f"{path}: parameter file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UsageError(f"{path}: not a readable JSON file ({exc})") from None
    if isinstance(data, dict) and isinstance(data.get("params"), dict):
        data = data["params"]
    if not isinstance(data, dict):
        raise UsageError(f"{path}: expected a JSON object of \"lobe.param\" values "
                         "or a result.json with a \"params\" object")
    options = dict(job.material.options)
    numeric = {}
    for key, value in data.items():
        if key in options:
            if value != options[key]:
                raise UsageError(f"{path}: {key} = {value!r} differs from the config's "
                                 f"value {options[key]!r}")
            continue
        numeric[key] = value
    try:
        full = job.material.full_params(numeric)
    except (ValueError, TypeError) as exc:
        raise UsageError(f"{path}: {exc}") from None
    return full


def truth_params(job: Job) -> dict[str, Any]:
    """Complete parameters of the config's truth (fixed values where truth is silent)."""
    return job.material.full_params({**job.fixed, **job.truth})


# --------------------------------------------------------------------------- outputs


def _plain(value):
    """JSON-ready: arrays -> lists, numpy scalars -> float, NaN/Inf -> None."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def truth_error(params: Mapping[str, Any], stderr: Mapping[str, Any],
                truth: Mapping[str, Any]) -> dict:
    """Per truth parameter: ``truth``, ``abs`` |fit - truth|, ``rel`` abs/|truth|
    (None where truth is 0) and ``sigmas`` abs/stderr when a stderr exists."""
    out = {}
    for key, t in truth.items():
        t = np.asarray(t, dtype=np.float64)
        f = np.asarray(params[key], dtype=np.float64)
        err = np.abs(f - t)
        entry = {"truth": t, "fit": f, "abs": err,
                 "rel": np.where(t != 0, err / np.where(t != 0, np.abs(t), 1.0), np.nan)}
        if key in stderr:
            s = np.asarray(stderr[key], dtype=np.float64)
            with np.errstate(divide="ignore", invalid="ignore"):
                entry["sigmas"] = np.where(s > 0, err / s, np.nan)
        out[key] = _plain(entry)
    return out


def _write_json(path: str, data) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2, allow_nan=False)
        fh.write("\n")


# --------------------------------------------------------------------------- commands


def cmd_fit(args) -> int:
    log = _Log(args.quiet)
    job = load_config(args.config)
    if args.solver is not None:
        if args.solver not in solvers():
            raise UsageError(f"--solver {args.solver!r} is not allowed; allowed values: "
                             + ", ".join(repr(n) for n in solvers()))
        job = job.replace(fit=job.fit.replace(solver=args.solver))
    if args.validate is not None:
        job = job.replace(fit=job.fit.replace(validate=args.validate))
    target_path = _target_path(job, args.target)
    target, saturated = read_target(target_path, job.scene)
    job = job.replace(fit=job.fit.replace(target=target_path))  # config.toml records it
    out = os.path.abspath(args.out or os.path.join("out", job.name))

    with staged_dir(out) as tmp:
        result = run_fit(job, target, saturated, log)
        result["target"] = target_path
        result["config"] = job.path
        fit_img = _render_fit(job, result["params"], log)
        residual = target - fit_img
        validation_img = None
        if job.fit.validate:
            validation_img, result["validation"] = _validate(job, result["params"], target,
                                                             saturated, job.fit.validate_spp, log)
        result = _plain(result)
        with log.stage("writing outputs"):
            from .imageio import write_image
            from .report import make_report

            write_image(os.path.join(tmp, "fit.exr"), fit_img)
            write_image(os.path.join(tmp, "residual.exr"), residual)
            if validation_img is not None:
                write_image(os.path.join(tmp, "validation.exr"), validation_img)
            _write_json(os.path.join(tmp, "result.json"), result)
            with open(os.path.join(tmp, "config.toml"), "w", encoding="utf-8") as fh:
                fh.write(dumps_toml(job_to_dict(job)))
            make_report(os.path.join(tmp, "report.png"), target=target, fit=fit_img,
                        validation=validation_img, result=result,
                        fitted=fitted_pixels(job, target, saturated),
                        title=f"{job.name}: {' + '.join(job.material.lobes)}")
    if args.json:
        print(json.dumps(result, indent=2, allow_nan=False))
    else:
        _print_summary(log, result, out)
    return EXIT_OK if result["status"] == "converged" else EXIT_NOT_CONVERGED


def run_fit(job: Job, target: np.ndarray, saturated: np.ndarray, log: _Log) -> dict:
    """Run the fit engine on ``job`` and return the result dict (+ truth_error)."""
    import jax.numpy as jnp

    from . import fit as fit_engine

    opts = job.fit
    kwargs = {k: getattr(opts, k) for k in ("rtol", "atol", "max_steps")
              if getattr(opts, k) is not None}
    with log.stage(f"fitting ({opts.solver}, {opts.n_starts} start(s))"):
        res = fit_engine.fit(
            target, job.scene, job.material, init=job.init, fixed=job.fixed,
            solver=opts.solver, mask=opts.mask, exclude=saturated if saturated.any() else None,
            noise_sigma=opts.noise_sigma, loss=opts.loss, saturation=opts.saturation,
            n_starts=opts.n_starts, dtype=getattr(jnp, opts.dtype), base_dir=job.base_dir,
            **kwargs)
    result = res.to_dict()
    result["solver"] = opts.solver
    if job.truth:
        result["truth_error"] = truth_error(res.params, res.stderr, job.truth)
    return result


def fitted_pixels(job: Job, target: np.ndarray, saturated: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels the fit engine uses for this job and target."""
    from .fit import select_pixels
    from .render import Renderer

    renderer = Renderer(job.scene, job.material, base_dir=job.base_dir)
    rows, _, _ = select_pixels(renderer, target, job.fit.mask,
                               saturated if saturated.any() else None, job.fit.saturation)
    mask = np.zeros(job.scene.height * job.scene.width, dtype=bool)
    mask[np.asarray(renderer.pixel_index)[rows]] = True
    return mask.reshape(job.scene.height, job.scene.width)


def _render_fit(job: Job, params: Mapping[str, Any], log: _Log) -> np.ndarray:
    from .render import render

    with log.stage("rendering the fit"):
        full = job.material.full_params(params)
        return np.asarray(render(full, job.scene, job.material, base_dir=job.base_dir))


def validation_seed(job: Job) -> int:
    """Sampler seed of validation renders: never the synth seed, so that a
    validation at the target's spp does not reproduce the target's noise."""
    return job.synth.seed + 1


def _validate(job: Job, params, target, saturated, spp: int, log: _Log):
    """Mitsuba re-render of ``params`` and its comparison with ``target``."""
    from . import metrics, mitsuba

    full = job.material.full_params(params)
    seed = validation_seed(job)
    with log.stage(f"validating with Mitsuba ({spp} spp)"):
        img = np.asarray(mitsuba.render(job.scene, job.material, full, spp=spp, seed=seed,
                                        base_dir=job.base_dir), dtype=np.float64)
        mask = ~saturated if saturated.any() else None
        cmp = metrics.compare(target, img, mask=mask)
    return img, {"renderer": "mitsuba", "spp": spp, "seed": seed, **_plain(cmp)}


def _print_summary(log: _Log, result: dict, out: str) -> None:
    from rich.table import Table

    ok = result["status"] == "converged"
    table = Table(title=f"[{'green' if ok else 'red'}]{result['status']}[/] "
                        f"after {result['iterations']} steps -- {result.get('message', '')}")
    table.add_column("parameter", no_wrap=True)
    table.add_column("fit")
    table.add_column("± stderr")
    has_truth = "truth_error" in result
    if has_truth:
        table.add_column("truth")
        table.add_column("|error|")
    for key, value in result["params"].items():
        row = [key, _fmt(value), _fmt(result["stderr"].get(key), ".2g")]
        if key in result.get("unidentifiable", []):
            row[2] = "unidentifiable"
        if has_truth:
            te = result["truth_error"].get(key)
            row += [_fmt(te["truth"]), _fmt(te["abs"], ".2g")] if te else ["", ""]
        table.add_row(*row)
    from rich.console import Console

    console = Console(highlight=False, width=max(Console().width, 110))
    console.print(table)
    line = f"image RMSE {result['image_rmse']:.4g}"
    if "validation" in result:
        v = result["validation"]
        line += (f"; Mitsuba PSNR {v['psnr_db']:.1f} dB, ΔE2000 mean {v['delta_e2000_mean']:.3g}"
                 f" max {v['delta_e2000_max']:.3g}")
    console.print(line + f"; time {result['time_s']['total']:.2f} s")
    for w in result.get("warnings", []):
        console.print(f"[yellow]warning:[/] {w}")
    console.print(f"outputs in {out}")


def _fmt(value, spec: str = ".5g") -> str:
    if value is None:
        return ""
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v, spec) for v in value) + "]"
    return format(value, spec)


def cmd_synth(args) -> int:
    log = _Log(args.quiet)
    job = load_config(args.config)
    if not job.truth:
        raise UsageError(f"{job.path}: [material.truth] is missing; synth renders the "
                         "truth parameters")
    spp = job.synth.spp if args.spp is None else args.spp
    seed = job.synth.seed if args.seed is None else args.seed
    if spp < 1:
        raise UsageError(f"--spp {spp}: expected an integer >= 1")
    if args.out:
        out = os.path.abspath(args.out)
    elif job.fit.target:
        out = os.path.dirname(job.fit.target)
    else:
        out = os.path.abspath(os.path.join("out", job.name))
    if os.path.exists(out) and not os.path.isdir(out):
        raise UsageError(f"{out}: exists and is not a folder; choose another --out")
    from .mitsuba import synth

    params = truth_params(job)
    os.makedirs(out, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".synth.tmp-", dir=out)
    try:
        with log.stage(f"rendering {job.name} with Mitsuba ({spp} spp)"):
            synth.write_case(tmp, job.scene, job.material, params, spp=spp, seed=seed,
                             base_dir=job.base_dir, extra={"config": job.path},
                             paths_relative_to=out)
        for name in sorted(os.listdir(tmp)):
            os.replace(os.path.join(tmp, name), os.path.join(out, name))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.print(f"wrote {out}")
    if job.fit.target and os.path.dirname(job.fit.target) == out and \
            not os.path.exists(job.fit.target):
        log.print(f"[yellow]warning:[/] fit.target {job.fit.target} is not the written "
                  "target.exr")
    return EXIT_OK


def cmd_validate(args) -> int:
    log = _Log(args.quiet)
    job = load_config(args.config)
    params = read_params(args.result, job)
    target, saturated = read_target(_target_path(job, args.target), job.scene)
    spp = job.fit.validate_spp if args.spp is None else args.spp
    if spp < 1:
        raise UsageError(f"--spp {spp}: expected an integer >= 1")
    img, report = _validate(job, params, target, saturated, spp, log)
    if args.out:
        from .imageio import write_image

        write_image(args.out, img)
    if args.json:
        print(json.dumps(_plain(report), indent=2, allow_nan=False))
    else:
        print(f"Mitsuba ({spp} spp) vs target: PSNR {report['psnr_db']:.2f} dB, "
              f"RMSE {report['rmse']:.4g}, ΔE2000 mean {report['delta_e2000_mean']:.3g} "
              f"max {report['delta_e2000_max']:.3g}")
    return EXIT_OK


def cmd_render(args) -> int:
    log = _Log(args.quiet)
    job = load_config(args.config)
    params = read_params(args.params, job) if args.params else truth_params(job)
    from .imageio import write_image

    img = _render_fit(job, params, log)
    write_image(args.out, img)
    log.print(f"wrote {os.path.abspath(args.out)}")
    return EXIT_OK


def cmd_bench(args) -> int:
    import importlib.util

    if importlib.util.find_spec("fitter.bench") is None:
        print("fitter: error: benchmarks are not available in this installation "
              "(no fitter.bench module)", file=sys.stderr)
        return EXIT_INPUT
    from . import bench

    return int(bench.main(args.rest) or 0)

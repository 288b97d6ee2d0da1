"""The ``fitter`` command line: fit, synth, validate, render.

Benchmarks are a script of the source checkout (``python benchmarks/run.py``).

Every command reads one TOML job (``fitter.config``); ``fitter fit`` runs it
through ``fitter.pipeline`` and this module only parses, reads, writes and
prints. Exit codes:

* 0: done (for ``fit``: the fit converged);
* 1: an unexpected internal error (with a traceback);
* 2: bad input (config, image, parameters, command line, output folder, a
  request over ``fitter.limits``) or a file operation the machine refused
  (disk full, read-only): one sentence on stderr naming the file/key/value,
  and no output written;
* 3: ``fit`` ran but the fit did not converge (``status`` is ``"max_steps"``
  or ``"failed"``); all outputs are still written.

Outputs of ``fitter fit`` go to ``--out`` (default ``out/<config stem>``
relative to the working directory), staged and swapped in by
``fitter.outdir``: only a folder fitter wrote is ever replaced, and an
interrupted or failed run leaves no half-written folder. ``--json`` prints
exactly one JSON document on stdout; progress and log lines go to stderr
(silenced by ``--quiet``). JAX, Mitsuba and the config reader are imported
only once a command runs, so ``--help`` and usage errors answer at once. The
program (console script, ``python -m fitter``) is ``fitter.program.run``:
``main`` and then a fast exit.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
import tempfile
import time
from typing import Any, Sequence

from . import __version__
from .compilation_cache import enable_compilation_cache
from .errors import FitterError
from .interrupt import check_interrupt, signals_as_interrupt
from .outputs import write_outcome

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_NOT_CONVERGED = 0, 1, 2, 3


class UsageError(FitterError):
    """A command-line mistake (message is one sentence)."""


# --------------------------------------------------------------------------- entry point


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    parser = _parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse printed usage and the reason
        return EXIT_OK if exc.code == 0 else EXIT_INPUT
    try:
        with signals_as_interrupt():
            return args.run(args)
    except KeyboardInterrupt:
        print("fitter: interrupted", file=sys.stderr)
        return 130
    except FitterError as exc:
        print(f"fitter: error: {_printable(str(exc))}", file=sys.stderr)
        return EXIT_INPUT
    except OSError as exc:  # disk full, read-only or vanished folder: the machine, not fitter
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"fitter: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_INPUT


def _printable(text: str) -> str:
    """``text`` with control characters escaped: a key or path from a config
    must not drive the user's terminal."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fitter",
        description="Recover BSDF parameters from images of a sphere (JAX forward model, "
                    "Mitsuba 3 validation). Configs are documented in configs/README.md.")
    p.add_argument("--version", action="version", version=f"fitter {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    f = sub.add_parser("fit", help="fit a material to a target image",
                       description="Fit the material of CONFIG to its target image and write "
                                   "result.json, fit.exr, residual.exr, validation.exr, "
                                   "report.png and scene.xml to OUT. Exit 0 converged, 2 bad input, "
                                   "3 not converged.")
    f.add_argument("config", metavar="CONFIG.toml")
    f.add_argument("--target", metavar="IMG", help="target image (overrides fit.target)")
    f.add_argument("--out", metavar="DIR", help="output folder (default: out/<config stem>)")
    f.add_argument("--json", action="store_true",
                   help="print the result as one JSON document on stdout")
    f.add_argument("--solver", help="override fit.solver (levenberg_marquardt, ...; "
                                    "see configs/README.md)")
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

    b = sub.add_parser("batch", help="fit many configs at once on Dask",
                       description="Fit every CONFIG (files, folders of *.toml, globs) on a "
                                   "Dask cluster: an embedded one sized to this machine, or "
                                   "--scheduler. Each job's outputs go to OUT/<config stem> "
                                   "(as fitter fit writes them), with OUT/summary.csv and "
                                   "OUT/summary.png; finished jobs whose config and target "
                                   "are unchanged are skipped. Exit 0 all converged, 2 bad "
                                   "command line, 3 some not converged or failed.")
    b.add_argument("configs", nargs="+", metavar="CONFIG")
    b.add_argument("--out", metavar="DIR", required=True, help="batch output folder")
    b.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler (tcp://HOST:PORT) whose workers have "
                        "fitter installed (default: an embedded LocalCluster)")
    b.add_argument("--workers", type=int, metavar="N",
                   help="worker processes of the embedded cluster (default: CPU cores)")
    b.add_argument("--validate", action=argparse.BooleanOptionalAction, default=None,
                   help="Mitsuba validation of every fit (default: each config's "
                        "fit.validate)")
    b.add_argument("--quiet", action="store_true", help="no progress or log output")
    b.set_defaults(run=cmd_batch)

    e = sub.add_parser("export", help="write scene.xml and material.json of a fit's output",
                       description="Write OUTDIR/scene.xml (the fit as a Mitsuba 3 scene) and "
                                   "OUTDIR/material.json from OUTDIR's config.toml and "
                                   "result.json, as `fitter fit` wrote them.")
    e.add_argument("outdir", metavar="OUTDIR")
    e.set_defaults(run=cmd_export)

    return p


# --------------------------------------------------------------------------- console


class _Log:
    """Progress spinner and log lines on stderr; silent when ``quiet``."""

    def __init__(self, quiet: bool):
        from rich.console import Console

        self.console = Console(stderr=True, quiet=quiet, highlight=False)
        if quiet:  # library warnings too (JAX's, Mitsuba's): results go to --out
            import logging
            import warnings

            warnings.simplefilter("ignore")
            logging.disable(logging.WARNING)

    @contextlib.contextmanager
    def stage(self, text: str):
        """A spinner with the elapsed seconds while the stage runs, then its time;
        yields ``note(line)``, which shows ``line`` (the stage's progress, e.g. a
        start's steps and cost) after the stage's text on the spinner line."""
        from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

        check_interrupt()
        t0 = time.perf_counter()
        if not self.console.is_terminal:  # (a log file: no spinner, whose end is a blank line)
            yield lambda line: check_interrupt()
        else:
            with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                          console=self.console, transient=True) as bar:
                task = bar.add_task(text + " ...", total=None)

                def note(line: str) -> None:
                    check_interrupt()  # a stage boundary: a remembered signal stops here
                    bar.update(task, description=f"{text} ... {_printable(line)}",
                               refresh=True)

                yield note
        check_interrupt()
        self.console.print(f"[dim]{text}: {time.perf_counter() - t0:.2f} s[/dim]")

    def print(self, *args, **kwargs):
        self.console.print(*args, **kwargs)


# --------------------------------------------------------------------------- inputs


def _load(path: str):
    from .config import load_config

    return load_config(path)


def _target_path(job, override: str | None) -> str:
    if override:
        return os.path.abspath(override)
    if job.fit.target is None:
        raise UsageError(f"{job.path}: fit.target is not set; add it to [fit] or pass --target")
    return job.fit.target


def _image_out(path: str, flag: str = "--out") -> str:
    """An image file to write; a folder or a missing parent is a usage error."""
    path = os.path.abspath(path)
    if os.path.isdir(path):
        raise UsageError(f"{flag} {path}: is a folder; give an image file name "
                         "(e.g. image.exr)")
    return path


def read_params(path: str, job) -> dict[str, Any]:
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


# --------------------------------------------------------------------------- commands


def cmd_fit(args) -> int:
    from . import pipeline
    from .outdir import check_out, staged_dir

    log = _Log(args.quiet)
    job = _load(args.config)
    if args.solver is not None:
        from .config import solvers

        if args.solver not in solvers():
            raise UsageError(f"--solver {args.solver!r} is not allowed; allowed values: "
                             + ", ".join(repr(n) for n in solvers()))
        job = job.replace(fit=job.fit.replace(solver=args.solver))
    if args.validate is not None:
        job = job.replace(fit=job.fit.replace(validate=args.validate))
    target_path = _target_path(job, args.target)
    target, saturated = pipeline.read_target(target_path, job.scene,
                                             job.fit.target_encoding)
    job = job.replace(fit=job.fit.replace(target=target_path))  # config.toml records it
    out = check_out(args.out or os.path.join("out", job.name))  # before any fitting
    from .report_process import start

    # imports matplotlib (and colour-science to score the validation) on the other
    # core while JAX imports here
    report = start(metrics=job.fit.validate)
    try:
        enable_compilation_cache()
        with staged_dir(out) as tmp:
            outcome = pipeline.run_job(job, target, saturated, target_path=target_path,
                                       stage=log.stage,
                                       compare=report.compare if report is not None else None)
            result = outcome.to_dict()
            with log.stage("writing outputs"):
                write_outcome(tmp, outcome, result, report=report)
            check_interrupt()  # a swallowed signal must not let the new result replace --out
    finally:
        if report is not None:
            report.close()
    if args.json:
        print(json.dumps(result, indent=2, allow_nan=False))
    else:
        _print_summary(outcome, out)
    return EXIT_OK if outcome.converged else EXIT_NOT_CONVERGED


def _print_summary(outcome, out: str) -> None:
    from rich.console import Console
    from rich.table import Table

    from .report import fmt, stated_error

    res = outcome.fit
    table = Table(title=f"[{'green' if res.converged else 'red'}]{res.status}[/] "
                        f"after {res.iterations} steps -- {res.message}")
    table.add_column("parameter", no_wrap=True)
    table.add_column("fit")
    table.add_column("± stderr")
    if outcome.truth_error:
        table.add_column("truth")
        table.add_column("|error|")
    for key, value in res.params.items():
        row = [key, fmt(value), stated_error(res, key, ".2g")]
        if outcome.truth_error:
            te = outcome.truth_error.get(key)
            row += [fmt(te.truth), fmt(te.abs, ".2g")] if te else ["", ""]
        table.add_row(*row)
    console = Console(highlight=False, width=max(Console().width, 110))
    console.print(table)
    line = f"image RMSE {fmt(res.rmse, '.4g')}"
    v = outcome.validation
    if v is not None:
        line += (f"; Mitsuba PSNR {v.psnr_db:.1f} dB, ΔE2000 mean {v.delta_e2000_mean:.3g}"
                 f" max {v.delta_e2000_max:.3g}")
    console.print(line + f"; time {res.time_compile + res.time_run:.2f} s")
    for w in res.warnings:
        console.print(f"[yellow]warning:[/] {w}")
    console.print(f"outputs in {out}")


def cmd_synth(args) -> int:
    log = _Log(args.quiet)
    job = _load(args.config)
    if not job.truth:
        raise UsageError(f"{job.path}: [material.truth] is missing; synth renders the "
                         "truth parameters")
    spp = job.synth.spp if args.spp is None else args.spp
    seed = job.synth.seed if args.seed is None else args.seed
    if spp < 1:
        raise UsageError(f"--spp {spp}: expected an integer >= 1")
    from .limits import check_spp

    check_spp(spp, "--spp" if args.spp is not None else "synth.spp", where=job.path)
    if args.out:
        out = os.path.abspath(args.out)
    elif job.fit.target:
        out = os.path.dirname(job.fit.target)
    else:
        out = os.path.abspath(os.path.join("out", job.name))
    if os.path.exists(out) and not os.path.isdir(out):
        raise UsageError(f"{out}: exists and is not a folder; choose another --out")
    from . import pipeline
    from .mitsuba import synth
    from .outdir import make_folders, remove_made

    params = pipeline.truth_params(job)
    made, tmp = make_folders(out), None
    try:
        tmp = tempfile.mkdtemp(prefix=".synth.tmp-", dir=out)
        with log.stage(f"rendering {job.name} with Mitsuba ({spp} spp)"):
            synth.write_case(tmp, job.scene, job.material, params, spp=spp, seed=seed,
                             base_dir=job.base_dir, extra={"config": job.path},
                             paths_relative_to=out)
        for name in sorted(os.listdir(tmp)):
            os.replace(os.path.join(tmp, name), os.path.join(out, name))
    except BaseException:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
        remove_made(made)  # (the folders it made for this run: none of the user's)
        raise
    shutil.rmtree(tmp, ignore_errors=True)
    log.print(f"wrote {out}")
    if job.fit.target and os.path.dirname(job.fit.target) == out and \
            not os.path.exists(job.fit.target):
        log.print(f"[yellow]warning:[/] fit.target {job.fit.target} is not the written "
                  "target.exr")
    return EXIT_OK


def cmd_validate(args) -> int:
    from . import pipeline

    log = _Log(args.quiet)
    job = _load(args.config)
    params = read_params(args.result, job)
    target, saturated = pipeline.read_target(_target_path(job, args.target), job.scene,
                                             job.fit.target_encoding)
    spp = job.fit.validate_spp if args.spp is None else args.spp
    if spp < 1:
        raise UsageError(f"--spp {spp}: expected an integer >= 1")
    from .limits import check_spp

    check_spp(spp, "--spp" if args.spp is not None else "fit.validate_spp", where=job.path)
    out = _image_out(args.out) if args.out else None
    with log.stage(f"validating with Mitsuba ({spp} spp)"):
        v = pipeline.validate(job, params, target, saturated, spp)
    if out:
        from .imageio import write_image

        write_image(out, v.image)
    if args.json:
        print(json.dumps(v.to_dict(), indent=2, allow_nan=False))
    else:
        print(f"Mitsuba ({spp} spp) vs target: PSNR {v.psnr_db:.2f} dB, "
              f"RMSE {v.rmse:.4g}, ΔE2000 mean {v.delta_e2000_mean:.3g} "
              f"max {v.delta_e2000_max:.3g}")
    return EXIT_OK


def cmd_render(args) -> int:
    from . import pipeline

    log = _Log(args.quiet)
    job = _load(args.config)
    out = _image_out(args.out)
    params = read_params(args.params, job) if args.params else pipeline.truth_params(job)
    from .imageio import write_image
    from .limits import check_scene

    check_scene("render", job.scene, job.material, where=job.path, base_dir=job.base_dir)
    enable_compilation_cache()
    with log.stage("rendering"):
        img = pipeline.render_params(job, params)
    write_image(out, img)
    log.print(f"wrote {out}")
    return EXIT_OK


def cmd_export(args) -> int:
    from .mitsuba.export import export_outdir

    print("wrote " + " and ".join(export_outdir(args.outdir)))
    return EXIT_OK


def cmd_batch(args) -> int:
    from .batch import command  # imports Dask: only here, so --help stays fast

    return command(args)

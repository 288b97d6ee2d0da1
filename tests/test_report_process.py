"""report.png from the helper process (``fitter.report_process``) is the report
drawn in-process, and a helper that fails leaves the report to the caller."""

from __future__ import annotations

import os

import numpy as np
from test_report import _outcome

from fitter.metrics import compare
from fitter.outputs import write_outcome
from fitter.report import make_report
from fitter.report_process import ReportProcess


def _reference(tmp_path, outcome, title) -> bytes:
    path = tmp_path / "ref.png"
    make_report(str(path), outcome, title=title)
    return path.read_bytes()


def test_the_helper_draws_the_report_drawn_in_process(tmp_path):
    outcome = _outcome("solver tolerances met", ["a warning"])
    helper = ReportProcess()
    helper.send(outcome, "quickstart: lambert + torrance_sparrow")
    png = helper.receive()
    assert png is not None
    assert png == _reference(tmp_path, outcome, "quickstart: lambert + torrance_sparrow")
    assert helper.proc.returncode == 0


def test_write_outcome_draws_the_report_itself_when_the_helper_died(tmp_path):
    outcome = _outcome("solver tolerances met", [])
    helper = ReportProcess()
    helper.proc.kill()  # e.g. killed by the system before the fit ended
    helper.proc.wait()
    folder = tmp_path / "out"
    folder.mkdir()
    write_outcome(str(folder), outcome, outcome.to_dict(), report=helper)
    title = f"{outcome.job.name}: {' + '.join(outcome.job.material.lobes)}"
    assert (folder / "report.png").read_bytes() == _reference(tmp_path, outcome, title)
    assert {"result.json", "fit.exr", "residual.exr", "config.toml"} <= set(os.listdir(folder))


def test_an_unused_helper_is_stopped(tmp_path):
    helper = ReportProcess()
    helper.close()  # the fit failed or was interrupted: nothing to draw
    assert helper.proc.returncode is not None
    assert helper.receive() is None


def _images():
    rng = np.random.default_rng(3)
    target = rng.uniform(0.0, 1.2, (12, 10, 3))
    image = target + rng.normal(0.0, 0.02, target.shape)
    mask = np.zeros((12, 10), bool)
    mask[2:9, 1:8] = True
    return target, image, mask


def test_the_helper_scores_as_in_process_then_draws(tmp_path):
    """Reference: ``fitter.metrics.compare`` in this process (same values, bit
    for bit); the report drawn after a score is still the in-process one."""
    target, image, mask = _images()
    helper = ReportProcess(metrics=True)
    assert helper.compare(target, image, mask) == compare(target, image, mask=mask)
    outcome = _outcome("solver tolerances met", [])
    helper.send(outcome, "after a score")
    assert helper.receive() == _reference(tmp_path, outcome, "after a score")


def test_a_failed_or_dead_helper_leaves_the_score_to_the_caller():
    """A request the helper cannot score (a mask of no pixel) answers None and
    stops it; a dead helper answers None; ``validate``'s caller then scores
    in-process (``pipeline.validate``: ``compare`` None -> ``metrics.compare``)."""
    target, image, mask = _images()
    helper = ReportProcess(metrics=True)
    assert helper.compare(target, image, np.zeros_like(mask)) is None
    assert helper.proc.returncode is not None
    dead = ReportProcess(metrics=True)
    dead.proc.kill()
    dead.proc.wait()
    assert dead.compare(target, image, mask) is None


def test_validate_uses_the_scores_it_is_given_and_scores_itself_without(tmp_path, monkeypatch):
    """``pipeline.validate``: a ``compare`` answer is what the validation reports;
    a None answer (the failed helper above) leaves the scoring to
    ``fitter.metrics.compare`` here, the reference (Mitsuba's render replaced by
    a fixed image: only the scoring is under test)."""
    from small_case import write_case

    from fitter import mitsuba, pipeline
    from fitter.config import load_config

    job = load_config(write_case(str(tmp_path)))
    target, saturated = pipeline.read_target(job.fit.target, job.scene)
    image = target * 1.01 + 0.002
    monkeypatch.setattr(mitsuba, "render", lambda *a, **k: image)
    params = job.material.full_params({**job.fixed, **job.truth})
    mine = pipeline.validate(job, params, target, saturated, 4)
    assert mine.n_pixels > 0 and mine.rmse > 0
    given = {"rmse": 1.0, "psnr_db": 2.0, "delta_e2000_mean": 3.0, "delta_e2000_max": 4.0,
             "n_pixels": 5}
    told = pipeline.validate(job, params, target, saturated, 4, lambda *a: given)
    assert (told.rmse, told.psnr_db, told.n_pixels) == (1.0, 2.0, 5)
    failed = pipeline.validate(job, params, target, saturated, 4, lambda *a: None)
    assert failed.to_dict() == mine.to_dict()

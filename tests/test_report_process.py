"""report.png from the helper process (``fitter.report_process``) is the report
drawn in-process, and a helper that fails leaves the report to the caller."""

from __future__ import annotations

import os

from test_report import _outcome

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

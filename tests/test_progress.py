"""Progress while a fit runs (issue 16, item 6): each start's steps and cost
reach the caller's ``progress`` and the CLI's spinner line.

The compiled solve cannot call back into Python (its trace is cached on disk),
so progress comes between compiled calls: one call per start.
"""

from __future__ import annotations

import io
import re

import numpy as np
from small_case import SMALL, write_case

import fitter
from fitter import cli
from fitter.config import load_config
from fitter.imageio import read_image


def _small_job(tmp_path, n_starts):
    data = {**SMALL, "fit": {**SMALL["fit"], "n_starts": n_starts}}
    path = write_case(str(tmp_path), data)
    return path, load_config(path)


def test_each_start_reports_its_steps_and_cost(tmp_path):
    _, job = _small_job(tmp_path, 2)
    target = read_image(job.fit.target)
    lines = []
    res = fitter.fit(target, job.scene, job.material, init=job.init, fixed=job.fixed,
                     n_starts=2, progress=lines.append)
    done = [ln for ln in lines if " done: " in ln]
    assert [ln.split(" done")[0] for ln in done] == ["start 1/2", "start 2/2"], lines
    # the numbers shown are the starts' own: the cost each start ended at
    for line, start in zip(done, res.starts):
        steps, cost = re.search(r"(\d+) steps, cost (\S+)", line).groups()
        assert int(steps) >= 1
        np.testing.assert_allclose(float(cost), start["cost"], rtol=1e-3)
    assert lines.index("solving from start 1/2") < lines.index(done[0]), lines
    assert any(ln.startswith("solving from start 2/2 (best cost so far") for ln in lines), lines
    # the same fit without progress gives the same answer
    quiet = fitter.fit(target, job.scene, job.material, init=job.init, fixed=job.fixed,
                       n_starts=2)
    for key, value in res.params.items():
        np.testing.assert_array_equal(np.asarray(value), np.asarray(quiet.params[key]))


def test_the_cli_spinner_line_shows_the_starts_as_they_finish(tmp_path, monkeypatch):
    path, _ = _small_job(tmp_path, 2)
    screen = io.StringIO()
    init = cli._Log.__init__

    def on_a_terminal(self, quiet):
        init(self, quiet)
        from rich.console import Console

        self.console = Console(file=screen, force_terminal=True, width=160)

    monkeypatch.setattr(cli._Log, "__init__", on_a_terminal)
    code = cli.main(["fit", path, "--out", str(tmp_path / "out")])
    assert code == 0
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", screen.getvalue())  # no colours
    assert "fitting (levenberg_marquardt, 2 start(s)) ... start 1/2 done:" in text
    assert "start 2/2 done:" in text
    assert re.search(r"fitting \(levenberg_marquardt, 2 start\(s\)\): [\d.]+ s", text)


def test_a_fit_out_of_steps_says_so_in_the_products_words(tmp_path):
    _, job = _small_job(tmp_path, 1)
    target = read_image(job.fit.target)
    res = fitter.fit(target, job.scene, job.material, init=job.init, fixed=job.fixed,
                     max_steps=1)
    assert res.status == "max_steps"
    assert "max_steps" in res.message and "root-find" not in res.message

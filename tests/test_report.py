"""report.png: text never overlaps another panel or runs off the figure."""

from __future__ import annotations

import os

import numpy as np

from fitter.config import load_config
from fitter.fit import FitResult
from fitter.pipeline import Outcome, truth_error
from fitter.report import build_report, make_report

CONFIG = os.path.join(os.path.dirname(__file__), os.pardir, "configs", "quickstart.toml")


def _outcome(message, warnings):
    job = load_config(CONFIG)
    h, w = job.scene.height, job.scene.width
    params = {"lambert.rho_d": np.array([0.6, 0.4, 0.2]), "torrance_sparrow.m": 0.15,
              "torrance_sparrow.eta": 1.5, "torrance_sparrow.rho_s": 1.0}
    stderr = {"lambert.rho_d": np.array([1e-3, 2e-3, 3e-3]), "torrance_sparrow.m": 1e-4}
    result = FitResult(
        params=params, stderr=stderr, free=list(params)[:3],
        unidentifiable=["torrance_sparrow.eta"], correlation=np.eye(4),
        coordinates=["a", "b", "c", "d"], status="failed", message=message, iterations=200,
        cost=1.0, image_rmse=np.array([0.1, 0.1, 0.1]), n_pixels=100, n_excluded=0,
        time_compile=1.0, time_run=2.0, warnings=warnings, starts=[],
        fitted=np.ones((h, w), dtype=bool))
    image = np.full((h, w, 3), 0.3)
    return Outcome(job=job, target_path="t.exr", target=image, fit=result,
                   rendered=image * 0.9, validation=None,
                   truth_error=truth_error(params, stderr, job.truth), stage_times={})


def _texts_inside(fig):
    from matplotlib.table import Table
    from matplotlib.text import Text

    renderer = fig.canvas.get_renderer()
    fig.draw(renderer)
    page = fig.bbox
    outside = []
    for artist in fig.findobj(lambda a: isinstance(a, (Text, Table))):
        if isinstance(artist, Text) and not artist.get_text():
            continue
        e = artist.get_window_extent(renderer)
        if e.x0 < page.x0 - 1 or e.x1 > page.x1 + 1 or e.y0 < page.y0 - 1 or e.y1 > page.y1 + 1:
            outside.append(artist)
    return outside


def test_long_messages_and_many_warnings_stay_inside_the_figure_and_their_panels(tmp_path):
    long_word = "/very/long/path/" * 12 + "target.exr"
    message = "the solver stopped: " + "the residual is many times the noise " * 12 + long_word
    warnings = [f"warning {i}: " + "a parameter sits at its bound and " * 6 + long_word
                for i in range(12)]
    fig = build_report(_outcome(message, warnings), "x" * 300)
    assert _texts_inside(fig) == []
    # The facts (status, message, warnings) stay in their own panel, clear of the table.
    renderer = fig.canvas.get_renderer()
    table_ax, facts_ax = fig.axes[-2], fig.axes[-1]
    facts = facts_ax.texts[0].get_window_extent(renderer)
    assert facts.x0 >= facts_ax.get_window_extent(renderer).x0 - 1
    assert facts.x0 >= table_ax.tables[0].get_window_extent(renderer).x1
    assert "more in result.json" in facts_ax.texts[0].get_text()
    make_report(str(tmp_path / "report.png"), _outcome(message, warnings))
    assert (tmp_path / "report.png").stat().st_size > 10_000


def test_a_short_report_keeps_its_full_font():
    fig = build_report(_outcome("solver tolerances met", []), "quickstart")
    assert _texts_inside(fig) == []
    assert fig.axes[-1].texts[0].get_fontsize() == 10


def test_display_encoding_is_colour_sciences_srgb():
    # The report writes the sRGB transfer function out (colour's import is slow);
    # colour-science is the reference it must equal.
    import colour

    from fitter.imageio import linear_to_srgb

    x = np.concatenate([np.linspace(-0.1, 1.2, 1301), [0.0031308, 0.0031309]])
    expected = colour.cctf_encoding(np.clip(x, 0.0, 1.0), function="sRGB")
    assert np.max(np.abs(linear_to_srgb(x) - expected)) < 1e-15

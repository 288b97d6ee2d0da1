"""``report.png``: one picture that says whether a fit is good.

Top: the verdict (status, Mitsuba PSNR / colour difference) in green or red.
Middle: target | fit | residual heat map | Mitsuba validation, the three
renders on one display scale. Bottom: the parameter table (fit ± stderr,
truth and error when known) and the fit's figures and warnings.

Matplotlib runs on the Agg backend (no display needed).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .pipeline import Outcome

#: Percentile of the target's pixel values mapped to display white.
WHITE_PERCENTILE = 99.5
#: Percentile of |residual| that sets the residual colour scale.
RESIDUAL_PERCENTILE = 99.5
#: |fit - truth| in standard errors: within NOISE_SIGMAS the error is what the
#: pixel noise explains (green); beyond BIAS_SIGMAS the fit is wrong (red); in
#: between it is a small bias beyond the noise, e.g. a model/renderer mismatch
#: (amber). Measured: good fits land at 0.2-1.4 sigma, failed ones at 1e4-1e7
#: sigma (shared/notes/numerics.md, Cramer-Rao section).
NOISE_SIGMAS = 3.0
BIAS_SIGMAS = 100.0

#: Mean CIEDE2000 of the Mitsuba re-render against the target: below
#: INVISIBLE_DE the difference is not visible side by side, below JND_DE it
#: is at most just noticeable (Sharma et al. 2005; see fitter.metrics).
INVISIBLE_DE = 1.0
JND_DE = 2.3
#: The largest per-pixel CIEDE2000 bounds the badge too: a mean below 1 can hide
#: a visible spot (a roughplastic sphere fitted with lambert + torrance_sparrow:
#: mean below 1, max 6.7). A max up to JND_DE is invisible, up to MAX_NOTICEABLE_DE
#: at most just noticeable where it sits, above it visible.
MAX_NOTICEABLE_DE = 5.0

#: Smallest font a text is shrunk to before lines are dropped (points).
MIN_FONT = 6.5

GOOD, WARN, BAD, NEUTRAL = "#1a7f37", "#e08a00", "#c62828", "#555555"


def display(image: np.ndarray, white: float) -> np.ndarray:
    """Linear (H, W, 3) -> sRGB-encoded display values in [0, 1], ``white`` -> 1."""
    from .imageio import linear_to_srgb

    return linear_to_srgb(np.asarray(image, dtype=np.float64) / white)


def make_report(path: str, outcome: Outcome, title: str = "") -> None:
    """Write the report PNG of a job's ``outcome`` (``fitter.pipeline``) to ``path``."""
    fig = build_report(outcome, title)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fig.savefig(path, format="png")


def new_figure():
    """(figure, axes by panel name): the report's page before anything is drawn on it.

    Nothing here depends on the outcome, so ``fitter.report_process`` makes it
    while the fit still runs (7 axes, ~0.07 s); ``build_report`` fills it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(17, 8.6), dpi=100)  # no pyplot: no global state, faster import
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(3, 4, height_ratios=[0.45, 4.2, 2.1], hspace=0.18, wspace=0.12,
                            left=0.02, right=0.98, top=0.97, bottom=0.03)
    axes = {"headline": fig.add_subplot(grid[0, :])}
    for col, name in enumerate(("target", "fit", "residual", "validation")):
        axes[name] = fig.add_subplot(grid[1, col])
    axes["table"] = fig.add_subplot(grid[2, :3])
    axes["facts"] = fig.add_subplot(grid[2, 3])
    return fig, axes


def build_report(outcome: Outcome, title: str = "", page=None):
    """The report as a matplotlib ``Figure``; every text is fitted inside its panel.

    The residual panel greys out the pixels the fit did not use; ``title`` is
    the headline, e.g. the config name and lobes. ``page``: an unused
    ``new_figure()`` to draw on (default: a new one).
    """
    target = np.asarray(outcome.target, dtype=np.float64)
    fit = np.asarray(outcome.rendered, dtype=np.float64)
    positive = target[target > 0]
    white = float(np.percentile(positive, WHITE_PERCENTILE)) if positive.size else 1.0

    fig, axes = page or new_figure()
    _headline(axes["headline"], outcome, title)

    panels = [(target, "target"), (fit, "fit (JAX forward model)")]
    for key, (img, name) in zip(("target", "fit"), panels):
        ax = axes[key]
        ax.imshow(display(img, white), interpolation="nearest")
        _frame(ax, name)
    _residual(fig, axes["residual"], target - fit, outcome.fitted)
    for key in ("validation", "table", "facts"):  # after the colour bar, as if made now
        fig.delaxes(axes[key])
        fig.add_axes(axes[key])
    ax = axes["validation"]
    if outcome.validation is not None:
        ax.imshow(display(outcome.validation.image, white), interpolation="nearest")
        _frame(ax, "validation (Mitsuba 3)")
    else:
        ax.text(0.5, 0.5, "not validated\n(--no-validate)", ha="center", va="center",
                color=NEUTRAL, fontsize=13)
        _frame(ax, "validation (Mitsuba 3)")
    fig.text(0.02, 0.005, f"display: linear / {white:.3g} (target's {WHITE_PERCENTILE} "
             "percentile), sRGB", fontsize=8, color=NEUTRAL)

    _param_table(axes["table"], outcome)
    _facts(axes["facts"], outcome)
    return fig


def _frame(ax, title: str) -> None:
    ax.set_title(title, fontsize=12)
    ax.set_xticks([])
    ax.set_yticks([])


def _headline(ax, outcome: Outcome, title: str) -> None:
    ax.axis("off")
    res = outcome.fit
    x_text = _badge(ax, 0.0, *fit_badge(res))
    bits = [title] if title else []
    v = outcome.validation
    if v is not None:
        de = v.delta_e2000_mean
        x_text = _badge(ax, x_text, *mitsuba_badge(de, v.delta_e2000_max))
        bits.append(f"PSNR {fmt(v.psnr_db, '.1f')} dB, "
                    f"ΔE2000 mean {fmt(de, '.2g')}, max {fmt(v.delta_e2000_max, '.2g')}")
    bits.append(f"image RMSE {fmt(res.rmse, '.3g')}")
    text = ax.text(x_text, 0.5, "  |  ".join(bits), fontsize=12, va="center")
    _fit_inside(text, ax)


def fit_badge(res) -> tuple[str, str]:
    """(label, colour) of the fit's verdict: a fit whose residual shows the lobes
    cannot explain the image says so; a converged fit whose stated errors are
    mostly systematic is amber, naming the larger part: a structured residual or
    the model's own discretisation (``fit._verdict``'s warnings)."""
    if "cannot explain the image" in res.message:
        return f"MODEL CANNOT EXPLAIN THE IMAGE ({res.status})", BAD
    if "likely a clipped highlight" in res.message:
        return f"TARGET LOOKS CLIPPED ({res.status})", BAD
    if not res.converged:
        return f"NOT CONVERGED ({res.status})", BAD
    if any(w.startswith("the residual is spatially structured") for w in res.warnings):
        return "CONVERGED, STRUCTURED RESIDUAL", WARN
    if any(w.startswith("the stated errors are mostly the model's own discretisation")
           for w in res.warnings):
        return "CONVERGED, ERRORS MOSTLY DISCRETISATION", WARN
    return "CONVERGED", GOOD


def mitsuba_badge(mean_de: float, max_de: float) -> tuple[str, str]:
    """(label, colour) of the Mitsuba agreement from the mean and the max CIEDE2000."""
    if not (np.isfinite(mean_de) and np.isfinite(max_de)):
        return "Mitsuba: n/a", BAD
    if mean_de <= INVISIBLE_DE and max_de <= JND_DE:
        return "MITSUBA: NO VISIBLE DIFFERENCE", GOOD
    if mean_de <= JND_DE and max_de <= MAX_NOTICEABLE_DE:
        return "MITSUBA: JUST NOTICEABLE", WARN
    return "MITSUBA: VISIBLE DIFFERENCE", BAD


def _badge(ax, x: float, text: str, colour: str) -> float:
    """Draw a coloured label at axes x; return the x just right of it."""
    t = ax.text(x, 0.5, text, color="white", fontsize=15, fontweight="bold", va="center",
                bbox={"boxstyle": "round,pad=0.4", "facecolor": colour, "edgecolor": "none"})
    box = t.get_bbox_patch()
    renderer = ax.figure.canvas.get_renderer()
    t.draw(renderer)  # sizes the bbox patch
    right = box.get_window_extent(renderer).x1
    return ax.transAxes.inverted().transform((right, 0))[0] + 0.015


def _residual(fig, ax, residual: np.ndarray, fitted) -> None:
    import matplotlib

    res = residual.mean(axis=-1)
    if fitted is not None:
        res = np.where(fitted, res, np.nan)
    finite = np.abs(res[np.isfinite(res)])
    scale = float(np.percentile(finite, RESIDUAL_PERCENTILE)) if finite.size else 0.0
    scale = scale if scale > 0 else 1e-12
    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.6")
    im = ax.imshow(res, cmap=cmap, vmin=-scale, vmax=scale, interpolation="nearest")
    _frame(ax, "residual: target − fit (RGB mean)" if fitted is None
           else "residual (grey: not fitted)")
    bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    bar.ax.tick_params(labelsize=8)
    bar.formatter.set_powerlimits((-2, 3))


def _param_table(ax, outcome: Outcome) -> None:
    ax.axis("off")
    res, truth = outcome.fit, outcome.truth_error
    header = ["parameter", "fit ± stderr"] + (["truth", "|fit − truth|", "error / stderr"]
                                              if truth else [])
    rows, colours = [], []
    for key, value in res.params.items():
        err = stated_error(res, key, ".4g", "unidentifiable (see warnings)")
        row = [key, f"{fmt(value, '.4g')} ± {err}" if key in res.stderr
               else f"{fmt(value, '.4g')} ({err})"]
        colour = "white"
        if truth:
            te = truth.get(key)
            if te:
                row += [fmt(te.truth, ".4g"), fmt(te.abs, ".4g"),
                        fmt(te.sigmas, ".4g") if te.sigmas is not None else ""]
                worst = te.worst_sigmas
                if np.isfinite(worst):
                    # a fit that did not converge has no trustworthy stderr to excuse a bias
                    bias = BIAS_SIGMAS if res.converged else NOISE_SIGMAS
                    colour = ("#e8f5e9" if worst <= NOISE_SIGMAS else
                              "#fff3e0" if worst <= bias else "#ffebee")
            else:
                row += ["", "", ""]
        if key in res.unidentifiable:
            colour = "#eeeeee"
        rows.append(row)
        colours.append([colour] * len(row))
    if not rows:
        return
    table = ax.table(cellText=rows, colLabels=header, cellColours=colours, loc="upper left",
                     cellLoc="left", colLoc="left")
    table.auto_set_font_size(False)
    table.set_fontsize(10)
    table.scale(1.0, 1.6)
    table.auto_set_column_width(list(range(len(header))))
    renderer = ax.figure.canvas.get_renderer()
    size = 10.0
    while size > MIN_FONT and not _inside(table.get_window_extent(renderer), ax, renderer):
        size -= 0.5
        table.set_fontsize(size)
    if truth:
        ax.set_title(f"|fit − truth| vs stderr: green <= {NOISE_SIGMAS:g} (noise), "
                     f"amber <= {BIAS_SIGMAS:g} (small bias), red beyond (wrong)",
                     fontsize=9, loc="left", color=NEUTRAL)


def _facts(ax, outcome: Outcome) -> None:
    ax.axis("off")
    res = outcome.fit
    lines = [
        f"status: {res.status}",
        f"message: {_wrap(res.message, 44)}",
        f"solver: {outcome.job.fit.solver}, {res.iterations} steps",
        f"cost: {fmt(res.cost, '.4g')}",
        f"pixels: {res.n_pixels} fitted, {res.n_excluded} excluded",
        f"time: {fmt(res.time_compile + res.time_run, '.2f')} s "
        f"(compile {fmt(res.time_compile, '.2f')} s, run {fmt(res.time_run, '.2f')} s)",
    ]
    v = outcome.validation
    if v is not None:
        lines.append(f"Mitsuba {v.spp} spp: RMSE {fmt(v.rmse, '.3g')}")
    for w in res.warnings:
        lines.append("warning: " + _wrap(w, 44))
    text = ax.text(0.0, 1.0, "\n".join(lines), va="top", ha="left", fontsize=10,
                   family="monospace")
    _fit_inside(text, ax)


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n  ".join(textwrap.wrap(text, width)) or ""


def _inside(extent, ax, renderer) -> bool:
    box = ax.get_window_extent(renderer)
    return (extent.x0 >= box.x0 - 1 and extent.x1 <= box.x1 + 1
            and extent.y0 >= box.y0 - 1 and extent.y1 <= box.y1 + 1)


def _fit_inside(text, ax) -> None:
    """Shrink ``text`` to fit its axes; past ``MIN_FONT``, drop its last lines
    with a note (the full text is in result.json)."""
    renderer = ax.figure.canvas.get_renderer()
    size = text.get_fontsize()
    while size > MIN_FONT and not _inside(text.get_window_extent(renderer), ax, renderer):
        size -= 0.5
        text.set_fontsize(size)
    lines = text.get_text().split("\n")
    while len(lines) > 1 and not _inside(text.get_window_extent(renderer), ax, renderer):
        lines = lines[:-2] + ["... (more in result.json)"]
        text.set_text("\n".join(lines))
    if not _inside(text.get_window_extent(renderer), ax, renderer):  # one line, too wide
        text.set_text(text.get_text()[:60] + "...")

def stated_error(res, key: str, spec: str, unidentifiable: str = "unidentifiable") -> str:
    """A parameter's error column: its stderr, or why it has none (unidentifiable, fixed)."""
    if key in res.unidentifiable:
        return unidentifiable
    return fmt(res.stderr[key], spec) if key in res.stderr else "fixed"


def fmt(value, spec: str = ".5g") -> str:
    """A number, an array or a list of numbers as text; "n/a" for None or NaN."""
    if value is None:
        return "n/a"
    a = np.asarray(value, dtype=np.float64)
    if a.ndim > 0:
        return "[" + ", ".join(fmt(v, spec) for v in a.reshape(-1)) + "]"
    return "n/a" if np.isnan(a) else format(float(a), spec)

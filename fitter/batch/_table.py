"""The batch's table: ``summary.csv`` (one row per job) and ``summary.png``.

Columns: ``config``, ``out`` (job folder relative to the batch folder),
``status`` (converged / max_steps / failed / error), ``resumed`` (result kept
from an earlier run), one column per parameter coordinate
(``lambert.rho_d[0]``), its ``stderr:`` and, with a truth, ``truth:``
columns, ``image_rmse``, ``psnr_db`` (Mitsuba validation, empty when not
run), ``time_s`` and ``error``. Both files are written atomically.
"""

from __future__ import annotations

import csv
import math
from typing import Any, Sequence

from ..imageio import atomic_write

HEAD = ("config", "out", "status", "resumed")
TAIL = ("image_rmse", "psnr_db", "time_s", "error")


def columns(rows: Sequence[dict[str, Any]]) -> list[str]:
    """HEAD, the parameter coordinates (first-seen order) then their stderr: and
    truth: columns, TAIL."""
    params: list[str] = []
    for row in rows:
        for key in row:
            if key not in HEAD and key not in TAIL and ":" not in key and key not in params:
                params.append(key)
    extra = [f"{p}:{c}" for p in ("stderr", "truth") for c in params
             if any(f"{p}:{c}" in row for row in rows)]
    return [*HEAD, *params, *extra, *TAIL]


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)  # repr: round-trips exactly
    return str(value)


def write_csv(path: str, rows: Sequence[dict[str, Any]]) -> None:
    cols = columns(rows)

    def write(tmp):
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(cols)
            for row in rows:
                w.writerow([_cell(row.get(c)) for c in cols])

    atomic_write(path, write)


def read_csv(path: str) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def write_figure(path: str, rows: Sequence[dict[str, Any]]) -> None:
    """One panel per parameter coordinate: the fitted value ± stderr of every job
    with a result (x: job), the truth as a cross where known."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cols = columns(rows)
    done = [r for r in rows if r.get("status") != "error"]
    params = [c for c in cols if c not in HEAD and c not in TAIL and ":" not in c
              and any(f"stderr:{c}" in r for r in done)]  # fitted somewhere, not fixed
    n = max(len(params), 1)
    ncol = min(n, 3)
    nrow = math.ceil(n / ncol)
    fig = Figure(figsize=(4.2 * ncol, 2.8 * nrow + 0.4), layout="constrained")
    FigureCanvasAgg(fig)
    fig.suptitle(f"{len(done)} of {len(rows)} job(s) with a result; "
                 f"{sum(r.get('status') == 'converged' for r in rows)} converged")
    if not params:
        ax = fig.add_subplot(1, 1, 1)
        ax.text(0.5, 0.5, "no job has a result", ha="center", va="center")
        ax.set_axis_off()
    for i, p in enumerate(params):
        ax = fig.add_subplot(nrow, ncol, i + 1)
        pts = [(j, r) for j, r in enumerate(done) if _finite(r.get(p))]
        xs = [j for j, _ in pts]
        ys = [r[p] for _, r in pts]
        errs = [r.get(f"stderr:{p}") if _finite(r.get(f"stderr:{p}")) else 0.0 for _, r in pts]
        colors = ["tab:blue" if r["status"] == "converged" else "tab:red" for _, r in pts]
        ax.errorbar(xs, ys, yerr=errs, fmt="none", ecolor="0.4", capsize=2, lw=0.8)
        ax.scatter(xs, ys, c=colors, s=14, zorder=3)
        truth = [(j, r[f"truth:{p}"]) for j, r in pts if _finite(r.get(f"truth:{p}"))]
        if truth:
            ax.scatter(*zip(*truth), marker="x", c="k", s=18, zorder=4, label="truth")
            ax.legend(fontsize=7, loc="best")
        ax.set_title(p, fontsize=9)
        if len(done) <= 24:
            ax.set_xticks(range(len(done)), [r["out"] for r in done], rotation=60,
                          ha="right", fontsize=6)
        else:
            ax.set_xlabel("job (row of summary.csv with a result)", fontsize=7)
        ax.tick_params(labelsize=7)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)

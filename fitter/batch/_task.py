"""The task a Dask worker runs for one job, and the summary row of a result.

``run_entry`` is what is submitted: it reads the target, runs
``fitter.pipeline.run_job`` and, with an output folder, writes exactly what
``fitter fit`` writes (``fitter.outputs.write_outcome``), staged and swapped in by
``fitter.outdir.staged_dir``, plus the resume key. Every error a job can
meet becomes an error row: a bad job never fails the batch. Compiled solvers
stay in the worker process (``fitter.fit._compile``) and on disk
(``fitter.compilation_cache``), so jobs of one scene and material compile once.
"""

from __future__ import annotations

import math
import os
import time
from typing import Any

import numpy as np

from ..errors import FitterError
from ._jobs import Entry, one_line, write_key

#: Dask event topic of job starts (the client's progress display counts them);
#: each batch adds its own id, so that batches sharing a cluster count their own.
TOPIC = "fitter-batch"
STATUSES = ("converged", "max_steps", "failed", "error")


def run_entry(entry: Entry, root: str | None, topic: str = TOPIC) -> dict[str, Any]:
    """Run one job (on a worker); its summary row. ``root``: batch folder or None."""
    _announce(topic, entry.index)
    t0 = time.perf_counter()
    try:
        from .. import pipeline
        from ..compilation_cache import enable_compilation_cache

        job = entry.job
        _scene_of(job)
        if isinstance(entry.target, str):
            target, saturated = pipeline.read_target(entry.target, job.scene,
                                                     job.fit.target_encoding)
            target_path = entry.target
        else:
            target, saturated, target_path = _array_target(entry.target, job.scene), None, ""
        enable_compilation_cache()
        if root is None:
            outcome = pipeline.run_job(job, target, saturated, target_path=target_path)
            result = outcome.to_dict()
        else:
            from ..outputs import write_outcome
            from ..outdir import staged_dir

            with staged_dir(os.path.join(root, entry.name)) as tmp:
                outcome = pipeline.run_job(job, target, saturated, target_path=target_path)
                result = outcome.to_dict()
                write_outcome(tmp, outcome, result)
                write_key(tmp, entry.key, time.perf_counter() - t0)
        row = result_row(entry, result, time.perf_counter() - t0)
        return row if root is not None else {**row, "out": ""}
    except (FitterError, OSError) as exc:
        return error_row(entry, one_line(exc), time.perf_counter() - t0)
    except Exception as exc:  # an internal fault of one job: reported, the batch goes on
        return error_row(entry, f"internal error: {type(exc).__name__}: {one_line(exc)}",
                         time.perf_counter() - t0)


#: The scene (and the folder its files resolve against) of this worker's last job.
_LAST_SCENE: list = [None]


def _scene_of(job) -> None:
    """Before a job of another scene than the worker's last, drop the last one's
    arrays (``fitter._keep.release``): kept for a later scene's fit, they were
    held beside its arrays (two large scenes at once, over a worker's memory
    limit sized for one job); a series of one scene keeps them."""
    scene = (job.scene, job.base_dir)
    if _LAST_SCENE[0] is not None and _LAST_SCENE[0] != scene:
        from .._keep import release

        release()
    _LAST_SCENE[0] = scene


def _array_target(target: np.ndarray, scene) -> np.ndarray:
    from ..imageio import ImageError

    if target.shape != (scene.height, scene.width, 3):
        raise ImageError(f"target array has shape {target.shape}; the scene needs "
                         f"({scene.height}, {scene.width}, 3)")
    if not np.isfinite(target).all() or (target < 0).any():
        raise ImageError("target array has NaN, Inf or negative values")
    return target


def _announce(topic: str, index: int) -> None:
    """Tell the client this job started (for its progress display); silent off a worker."""
    try:
        from distributed import get_worker

        get_worker().log_event(topic, {"start": index})
    except Exception:  # noqa: BLE001 -- not on a worker, or an old scheduler: no display
        pass


# --------------------------------------------------------------------------- rows


def _base(entry: Entry, out: str | None) -> dict[str, Any]:
    return {"config": entry.config, "out": out if out is not None else ""}


def error_row(entry: Entry, message: str, time_s: float = math.nan) -> dict[str, Any]:
    """The row of a job that did not run to a result (it has no output folder)."""
    row = _base(entry, "")
    row.update(status="error", resumed=False, time_s=time_s, error=message)
    return row


def result_row(entry: Entry, result: dict, time_s: float, resumed: bool = False) -> dict:
    """The row of a job with a result (``Outcome.to_dict()`` / result.json)."""
    row = _base(entry, entry.name)
    row.update(status=result["status"], resumed=resumed)
    for key, value in result["params"].items():
        if isinstance(value, str):  # lobe options (e.g. geometry = "smith")
            continue
        for coord, v in _coords(key, value):
            row[coord] = v
    for key, value in result.get("stderr", {}).items():
        for coord, v in _coords(key, value):
            row[f"stderr:{coord}"] = v
    for key, te in result.get("truth_error", {}).items():
        for coord, v in _coords(key, te["truth"]):
            row[f"truth:{coord}"] = v
    rmse = result.get("image_rmse")
    row["image_rmse"] = float(np.sqrt(np.mean(np.square(rmse)))) if rmse is not None \
        else math.nan
    v = result.get("validation")
    row["psnr_db"] = v["psnr_db"] if v else math.nan
    row["time_s"] = time_s
    row["error"] = ""
    return row


def _coords(key: str, value) -> list[tuple[str, float]]:
    """``[("lobe.p", v)]`` for a scalar, ``[("lobe.p[0]", v0), ...]`` for a vector
    (a JSON null, i.e. NaN, is NaN)."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return [(f"{key}[{i}]", _num(x)) for i, x in enumerate(np.ravel(np.asarray(
            value, dtype=object)))]
    return [(key, _num(value))]


def _num(x) -> float:
    return math.nan if x is None else float(x)

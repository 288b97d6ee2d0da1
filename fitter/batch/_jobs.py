"""What a batch runs: one ``Entry`` per job, its output folder name and resume key.

Configs are loaded here, on the client (no JAX): a config that does not load,
a missing target or an output folder fitter may not replace becomes an entry
with an ``error`` and is never sent to a worker. The resume key hashes the
job as it will run (``job_to_dict``: scene, material, ``[fit]`` with the
resolved target and the validation switch) and the target's bytes; a job
folder holding a complete result with the same key is not fitted again.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import json
import os
from typing import Any, Iterable

import numpy as np

from ..errors import FitterError

#: Written into each job folder beside fitter fit's files: the resume key and time.
KEY_FILE = ".fitter-batch.json"


class BatchError(FitterError):
    """A batch request that cannot start (no configs, bad --out, unreachable scheduler)."""


@dataclasses.dataclass(frozen=True)
class Entry:
    """One job of a batch.

    Attributes:
        index: position in the batch (rows keep this order).
        config: the config as given (path string, or a label for API jobs).
        job: the loaded ``fitter.config.Job`` (None when ``error``).
        target: the target image path, or an (H, W, 3) array (API jobs).
        name: output folder name under the batch folder.
        key: resume key (sha256 hex) of the job and its target.
        error: why the job cannot run (one sentence), or None.
        memory: the fit's estimated peak memory, bytes (``limits.scene_bytes``).
    """

    index: int
    config: str
    job: Any = None
    target: Any = None
    name: str = ""
    key: str = ""
    error: str | None = None
    memory: float = 0.0


def expand_configs(args: Iterable[str]) -> list[str]:
    """Config paths from files, folders (their ``*.toml``, sorted) and globs, in order.

    A path that names nothing is kept as given, so that it becomes an error
    row (``config file not found``) rather than vanishing from the table.
    Duplicates (same absolute path) are listed once.
    """
    out: list[str] = []
    seen: set[str] = set()
    for arg in args:
        if os.path.isdir(arg):
            found = sorted(glob.glob(os.path.join(glob.escape(arg), "*.toml")))
        elif glob.has_magic(arg):
            found = sorted(p for p in glob.glob(arg, recursive=True) if not os.path.isdir(p))
            if not found:
                raise BatchError(f"{arg}: no config matches this pattern")
        else:
            found = [arg]
        for path in found:
            if os.path.abspath(path) not in seen:
                seen.add(os.path.abspath(path))
                out.append(path)
    if not out:
        raise BatchError("no configs to run (the folders given hold no *.toml)")
    return out


def make_entries(items: Iterable[Any], validate: bool | None) -> list[Entry]:
    """Entries for configs (paths), ``Job`` objects or ``(target, scene, material)`` tuples.

    ``validate`` (None: each job's own) overrides ``fit.validate``.
    """
    entries = [_entry(i, item, validate) for i, item in enumerate(items)]
    names = _folder_names(entries)
    return [dataclasses.replace(e, name=n) for e, n in zip(entries, names)]


def _entry(index: int, item: Any, validate: bool | None) -> Entry:
    from ..config import Job, load_config

    label = str(item) if isinstance(item, (str, os.PathLike)) else f"job{index}"
    try:
        if isinstance(item, (str, os.PathLike)):
            job = load_config(os.fspath(item))
        elif isinstance(item, Job):
            job, label = item, item.path
        elif isinstance(item, tuple) and len(item) == 3:
            job = _job_from_tuple(index, *item)
        else:
            raise BatchError(f"job {index}: expected a config path, a Job or a "
                             f"(target, scene, material) tuple, not {type(item).__name__}")
        if validate is not None:
            job = job.replace(fit=job.fit.replace(validate=validate))
        target = item[0] if isinstance(item, tuple) else job.fit.target
        if target is None:
            raise BatchError(f"{job.path}: fit.target is not set; a batch job needs it "
                             "in [fit]")
        if isinstance(target, (str, os.PathLike)):
            target = os.path.abspath(os.fspath(target))
            if not os.path.isfile(target):
                raise BatchError(f"{target}: target image not found")
            job = job.replace(fit=job.fit.replace(target=target))  # config.toml records it
        else:
            target = np.asarray(target, dtype=np.float64)
        from ..limits import scene_bytes
        from ..pipeline import preflight

        preflight(job)
        return Entry(index, label, job=job, target=target, key=resume_key(job, target),
                     memory=scene_bytes("fit", job.scene, job.material, job.base_dir))
    except (FitterError, OSError) as exc:
        return Entry(index, label, error=one_line(exc))


def _job_from_tuple(index: int, target, scene, material):
    from ..config import FitOptions, Job

    path = os.path.abspath(os.fspath(target)) if isinstance(target, (str, os.PathLike)) else None
    return Job(path=f"<job{index}>", base_dir=os.getcwd(), scene=scene, material=material,
               truth={}, init={}, fixed={}, fit=FitOptions(target=path, validate=False))


def _folder_names(entries: list[Entry]) -> list[str]:
    """The config's stem; a stem shared by several jobs gets a short hash of the
    config's absolute path (stable from run to run, whatever the order)."""
    stems = [os.path.splitext(os.path.basename(e.config))[0] for e in entries]
    stems = [s if s and not s.startswith("<") else f"job{e.index}"
             for e, s in zip(entries, stems)]
    names = []
    for e, stem in zip(entries, stems):
        if stems.count(stem) > 1:
            tag = e.job.path if e.job is not None else os.path.abspath(e.config)
            stem = f"{stem}-{hashlib.sha256(tag.encode()).hexdigest()[:6]}"
        names.append(stem)
    for i, name in enumerate(names):  # the same config given twice (API): by position
        if names.count(name) > 1:
            names[i] = f"{name}-{entries[i].index}"
    return names


def resume_key(job, target) -> str:
    """sha256 of the job as it runs (``job_to_dict``), the target's bytes and fitter's version."""
    from .. import __version__
    from ..config import dumps_toml, job_to_dict

    h = hashlib.sha256(__version__.encode())
    h.update(dumps_toml(job_to_dict(job)).encode())
    if isinstance(target, str):
        with open(target, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    else:
        h.update(np.ascontiguousarray(target).tobytes())
    return h.hexdigest()


def finished(folder: str, key: str) -> dict | None:
    """The stored result of a complete job folder with resume key ``key``, else None.

    Returns ``{"result": result.json, "time_s": seconds of the original run}``.
    """
    from ..outdir import MARKER

    try:
        with open(os.path.join(folder, KEY_FILE), encoding="utf-8") as fh:
            stored = json.load(fh)
        if stored.get("key") != key or not os.path.isfile(os.path.join(folder, MARKER)):
            return None
        with open(os.path.join(folder, "result.json"), encoding="utf-8") as fh:
            result = json.load(fh)
    except (OSError, ValueError):
        return None
    return {"result": result, "time_s": stored.get("time_s", float("nan"))}


def write_key(folder: str, key: str, time_s: float) -> None:
    with open(os.path.join(folder, KEY_FILE), "w", encoding="utf-8") as fh:
        json.dump({"key": key, "time_s": time_s}, fh)
        fh.write("\n")


def one_line(exc: BaseException) -> str:
    """``exc`` as one line for a summary row: an OSError as "file: reason", else its
    text (its type's name when it has none), whitespace collapsed."""
    text = str(exc) or type(exc).__name__
    if isinstance(exc, OSError) and exc.strerror:
        text = f"{exc.filename + ': ' if exc.filename else ''}{exc.strerror}"
    return " ".join(text.split())

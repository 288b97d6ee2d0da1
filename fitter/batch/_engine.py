"""Running entries on Dask: an embedded ``LocalCluster`` or an existing scheduler.

Each job is one task (``_task.run_entry``). Dask does the scheduling, the
data movement and the fault handling: a worker process that dies takes its
task back to the scheduler, which gives it to another worker (up to
``distributed.scheduler.allowed-failures`` deaths, then the job is an error
row). On Ctrl-C the tasks not yet finished are cancelled, the embedded
cluster is closed (its processes end) and the staged folders of the jobs it
was writing are removed; every finished job's folder is whole (``outdir``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
import uuid
from typing import Any, Iterable, Sequence

from ._jobs import BatchError, Entry, one_line, finished, make_entries
from ._table import write_csv, write_figure
from ._task import STATUSES, TOPIC, error_row, result_row, run_entry

#: Seconds to wait for an existing scheduler to answer, and for it to have a worker.
CONNECT_TIMEOUT_S = 5
WORKER_WAIT_S = 30
#: The progress line's colour of each job status (``_task.STATUSES``).
COLOURS = {"converged": "green", "max_steps": "yellow", "failed": "yellow", "error": "red"}


def run_batch(jobs: Iterable[Any], out: str | None = None, *, scheduler: str | None = None,
              workers: int | None = None, validate: bool | None = None,
              progress: bool = False) -> list[dict[str, Any]]:
    """Fit many jobs on Dask; one row (a dict) per job, in the order given.

    Args:
        jobs: config paths, ``fitter.config.Job`` objects or ``(target, scene,
            material)`` tuples (target: an image path or an (H, W, 3) array;
            the material's defaults are the starting point).
        out: batch folder; each job's outputs go to ``out/<config stem>`` as
            ``fitter fit`` writes them, with ``summary.csv`` and ``summary.png``.
            Jobs whose folder holds a complete result of the same config and
            target are not run again. None: nothing is written.
        scheduler: address of an existing Dask scheduler (``tcp://host:port``);
            None starts a ``LocalCluster`` of ``workers`` processes.
        workers: processes of the embedded cluster (default: CPU cores, as
            many as the memory holds side by side, ``_local_size``).
        validate: override every job's ``fit.validate`` (None: keep it).
        progress: show a progress bar on stderr.

    Returns:
        Rows with the columns of ``summary.csv`` (``fitter.batch._table``):
        ``config``, ``out``, ``status``, ``resumed``, parameter coordinates,
        ``stderr:``/``truth:`` columns, ``image_rmse``, ``psnr_db``, ``time_s``,
        ``error``. A job that could not run has status ``"error"`` and a message.

    Raises:
        BatchError: ``out`` is not a usable folder, the scheduler does not answer,
            ``workers`` jobs side by side would not fit in the memory.
    """
    if workers is not None and workers < 1:
        raise BatchError(f"workers = {workers}: expected an integer >= 1")
    entries = make_entries(jobs, validate)
    root = _prepare_root(out) if out is not None else None
    rows: list[dict[str, Any] | None] = [None] * len(entries)
    todo: list[Entry] = []
    for e in entries:
        if e.error is None and root is not None:
            e = _check_folder(e, root)
        if e.error is not None:
            rows[e.index] = error_row(e, e.error)
            continue
        done = finished(os.path.join(root, e.name), e.key) if root is not None else None
        if done is not None:
            rows[e.index] = result_row(e, done["result"], done["time_s"], resumed=True)
        else:
            todo.append(e)
    if todo:
        try:
            with _client(scheduler, workers, todo) as client:
                if scheduler is not None:
                    todo = _held_by_workers(client, todo, rows)
                for e, row in _run(client, todo, root, progress):
                    rows[e.index] = row
        finally:  # after the embedded cluster's processes ended (Ctrl-C, a crash)
            if root is not None:
                _clean(root, todo)
    if root is not None:
        write_csv(os.path.join(root, "summary.csv"), rows)
        write_figure(os.path.join(root, "summary.png"), rows)
    return rows


def _prepare_root(out: str) -> str:
    root = os.path.abspath(out)
    if os.path.exists(root) and not os.path.isdir(root):
        raise BatchError(f"{root}: exists and is not a folder; choose another --out")
    try:
        os.makedirs(root, exist_ok=True)
    except OSError as exc:
        raise BatchError(f"{root}: cannot create the batch folder ({exc.strerror})") from None
    if not os.access(root, os.W_OK | os.X_OK):
        raise BatchError(f"{root}: cannot write in the batch folder (permission denied)")
    return root


def _check_folder(e: Entry, root: str) -> Entry:
    """The entry, or an error entry if its folder is one fitter may not replace."""
    import dataclasses

    from ..outdir import OutputError, check_out

    try:
        check_out(os.path.join(root, e.name))
    except OutputError as exc:
        return dataclasses.replace(e, error=one_line(exc))
    return e


def _clean(root: str, entries: Sequence[Entry]) -> None:
    from ..outdir import clean_stale

    for e in entries:
        clean_stale(root, e.name)


@contextlib.contextmanager
def _client(scheduler: str | None, workers: int | None, todo: Sequence[Entry]):
    """A ``distributed.Client`` on ``scheduler`` or on an embedded LocalCluster
    (``_local_size``)."""
    from distributed import Client

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as exc:
            raise BatchError(f"--scheduler {scheduler}: no Dask scheduler answers within "
                             f"{CONNECT_TIMEOUT_S} s ({one_line(exc)}); start one with "
                             "`dask scheduler` and workers with `dask worker ADDRESS`"
                             ) from None
        try:
            try:
                client.wait_for_workers(1, timeout=WORKER_WAIT_S)
            except TimeoutError:
                raise BatchError(f"--scheduler {scheduler}: the scheduler has no workers "
                                 f"after {WORKER_WAIT_S} s; start some with "
                                 f"`dask worker {scheduler}`") from None
            yield client
        finally:
            client.close()
        return
    from distributed import LocalCluster

    import dask

    n, memory_limit = _local_size(workers, todo)
    # One job at a time a worker: Dask's pause (at 80 % of its limit) would only keep a
    # worker whose RSS stays up after a job (the allocator keeps 80-93 % of a fit's
    # peak, measured) from taking the next; all paused, the batch would wait forever.
    # The nanny's stop at 95 % stays.
    with dask.config.set({"distributed.worker.memory.pause": False}), _started(
            LocalCluster, n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
            dashboard_address=None, env=_worker_env(n), memory_limit=memory_limit,
            silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
        client.register_plugin(_ignore_interrupt(), name="fitter-ignore-sigint")
        yield client


def _started(local_cluster, **kwargs):
    """``local_cluster(**kwargs)``; a ``BatchError`` saying why where its worker
    processes cannot start because they import the caller's script again: a
    script calling ``run_batch`` at its top level starts a cluster in each of
    them, which multiprocessing refuses (Dask says only "Nanny failed to start")."""
    try:
        return local_cluster(**kwargs)
    except RuntimeError as exc:
        script = getattr(sys.modules.get("__main__"), "__file__", None)
        if script is None or "failed to start" not in str(exc):
            raise
        raise BatchError(f"the embedded Dask cluster's worker processes did not start: each "
                         f"imports the script {script} again, so it must call run_batch "
                         'under `if __name__ == "__main__":`') from None


def _local_size(workers: int | None, todo: Sequence[Entry]) -> tuple[int, int | str]:
    """(worker processes, each one's memory limit) of the embedded cluster: one
    per core (or ``workers``) and job, fewer where the largest job's estimated
    memory (``Entry.memory``) times the workers is over ``limits.MEMORY_SHARE``
    of the memory available; that share split between them, or Dask's default
    if larger. That default, the machine's memory over its cores, alone
    stopped any job over it (a 256^2 env-lit fit, 4.2 GB, on a 16-core 32 GB
    machine), four times, before its row said so. ``workers`` too many for the
    memory is a ``BatchError``."""
    from .. import limits

    n = min(workers or os.cpu_count() or 1, len(todo))
    need = max((e.memory for e in todo), default=0.0)
    have = limits.available_bytes()
    if not have:
        return n, "auto"
    usable = limits.MEMORY_SHARE * have
    fits = max(1, int(usable // need)) if need > 0 else n
    if workers is not None and n > fits:
        raise BatchError(f"--workers {workers}: {n} jobs side by side need about "
                         f"{n * need / 1e9:.1f} GB ({need / 1e9:.1f} GB each, estimated) and "
                         f"this machine has {have / 1e9:.1f} GB available; use --workers "
                         f"{fits} or fewer, or leave it out")
    n = min(n, fits)
    return n, max(int(usable / n), _dask_default_limit())


def _dask_default_limit() -> int:
    """Dask's own memory limit of a one-thread worker (``memory_limit="auto"``)."""
    from distributed.worker_memory import parse_memory_limit

    return parse_memory_limit("auto", 1, logger=logging.getLogger(__name__)) or 0


def _held_by_workers(client, todo: Sequence[Entry], rows: list) -> list[Entry]:
    """The entries whose estimated memory some worker of an existing cluster
    holds (its ``memory_limit``); the others get an error row before any runs
    (Dask would stop each on every worker it tried). All of them where a
    worker has no limit or the limits cannot be read."""
    try:
        info = list(client.scheduler_info()["workers"].values())
        most = max(w["memory_limit"] for w in info) if info else 0
        if not all(w["memory_limit"] for w in info):
            return list(todo)
    except Exception:  # noqa: BLE001 (an older or newer scheduler: let Dask decide)
        return list(todo)
    keep = []
    for e in todo:
        if most and e.memory > most:
            rows[e.index] = error_row(e, (
                f"{e.config}: the fit needs about {e.memory / 1e9:.1f} GB of memory "
                f"(estimated) and the cluster's largest worker has a memory limit of "
                f"{most / 1e9:.1f} GB; start workers with a larger --memory-limit, or lower "
                "scene.supersampling or the image size"))
        else:
            keep.append(e)
    return keep


#: XLA's CPU thread pool off: with one worker process per core, each using every core
#: would oversubscribe them (measured ~10 % slower with 2 workers on 2 cores).
SINGLE_THREAD_XLA = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def _worker_env(n_workers: int) -> dict[str, str]:
    flags = os.environ.get("XLA_FLAGS", "")
    if n_workers < 2 or "intra_op_parallelism_threads" in flags:
        return {}
    return {"XLA_FLAGS": f"{flags} {SINGLE_THREAD_XLA}".strip()}


def _ignore_interrupt():
    """Worker plugin of the embedded cluster: Ctrl-C reaches the worker processes too
    (one process group), but only the client decides to stop; it then closes the
    cluster, which ends them. (Without it each prints a KeyboardInterrupt traceback.)"""
    from distributed.diagnostics.plugin import WorkerPlugin

    class IgnoreInterrupt(WorkerPlugin):
        def setup(self, worker):
            import signal
            import threading

            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, signal.SIG_IGN)

    return IgnoreInterrupt()


def _run(client, todo: Sequence[Entry], root: str | None, progress: bool):
    """Submit every entry; yield (entry, row) as jobs finish."""
    from distributed import as_completed

    started: set[int] = set()
    batch = uuid.uuid4().hex[:8]
    topic = f"{TOPIC}-{batch}"
    client.subscribe_topic(topic, lambda event: started.add(event[1]["start"]))
    futures = {client.submit(run_entry, e, root, topic, pure=False,
                             key=f"fitter-{batch}-{e.index}-{e.name}"): e for e in todo}
    counts = dict.fromkeys(STATUSES, 0)
    ended: set[int] = set()
    queue = as_completed(list(futures))
    try:
        with _Progress(progress, len(todo)) as bar:
            while not queue.is_empty():
                for fut in queue.next_batch(block=False):
                    e = futures[fut]
                    row = _row_of(fut, e)
                    fut.release()
                    ended.add(e.index)
                    counts[row["status"]] += 1
                    yield e, row
                bar.update(counts, len(started - ended))
                time.sleep(0.1)
    finally:
        client.unsubscribe_topic(topic)
        client.cancel([f for f in futures if not f.done()])


def _row_of(fut, e: Entry) -> dict[str, Any]:
    from distributed import KilledWorker

    try:
        return fut.result()
    except KilledWorker:
        import dask

        n = dask.config.get("distributed.scheduler.allowed-failures")
        return error_row(e, f"the worker processes running this job died {n + 1} times "
                            "(killed, crashed or out of memory); not retried again")
    except Exception as exc:  # noqa: BLE001 -- e.g. fitter missing on a remote worker
        return error_row(e, f"{type(exc).__name__}: {one_line(exc)}")


class _Progress:
    """A rich progress bar on stderr: jobs done, by status (``STATUSES``), running."""

    def __init__(self, enabled: bool, total: int):
        self.enabled, self.total = enabled, total

    def __enter__(self):
        if self.enabled:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, \
                TimeElapsedColumn

            self.bar = Progress(TextColumn("fitting"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("{task.fields[counts]}"), TimeElapsedColumn(),
                                console=Console(stderr=True), transient=False)
            self.bar.__enter__()
            self.task = self.bar.add_task("jobs", total=self.total, counts="")
        return self

    def update(self, counts: dict[str, int], running: int) -> None:
        if self.enabled:
            # The words of the summary line and summary.csv's status column.
            text = " ".join(f"[{COLOURS[s]}]{counts[s]} {s}[/]" for s in STATUSES
                            if counts[s] or s == "converged") + f" {running} running"
            self.bar.update(self.task, completed=sum(counts.values()), counts=text)

    def __exit__(self, *exc):
        if self.enabled:
            self.bar.__exit__(*exc)

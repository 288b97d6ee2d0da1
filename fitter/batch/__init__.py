"""Many fit jobs at once on Dask: ``fitter batch`` and ``run_batch``.

``run_batch(jobs, out)`` fits every job on a Dask cluster (an embedded
``distributed.LocalCluster`` of one-thread worker processes, or an existing
scheduler) and returns one row per job; with ``out`` each job's outputs are
written as ``fitter fit`` writes them, under ``out/<config stem>``, with
``summary.csv`` and ``summary.png`` beside them. Dask is imported only
when jobs are sent to a cluster (the CLI imports this package only inside
``fitter batch``).

Modules: ``_jobs`` (configs -> entries, folder names, resume keys),
``_task`` (what a worker runs, rows), ``_table`` (CSV and figure),
``_engine`` (clusters, submission, progress), ``_command`` (the CLI).
"""

from ._command import command as command
from ._engine import run_batch as run_batch
from ._jobs import BatchError as BatchError, expand_configs as expand_configs

__all__ = ["BatchError", "command", "expand_configs", "run_batch"]

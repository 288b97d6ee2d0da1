"""``fitter batch CONFIG... --out DIR``: parse-level checks, run, one summary line.

Exit codes: 0 every job converged; 3 some job did not converge or could not
run (its row in summary.csv says why); 2 a bad command line, an unusable
``--out`` or an unreachable scheduler (``BatchError``, raised to the CLI).
"""

from __future__ import annotations

import os

from ._engine import run_batch
from ._jobs import BatchError, expand_configs
from ._task import STATUSES

EXIT_OK, EXIT_SOME_FAILED = 0, 3


def command(args) -> int:
    if args.workers is not None and args.workers < 1:
        raise BatchError(f"--workers {args.workers}: expected an integer >= 1")
    if args.workers is not None and args.scheduler:
        raise BatchError("--workers sizes the embedded cluster; with --scheduler the "
                         "cluster's own workers run the jobs")
    configs = expand_configs(args.configs)
    if args.quiet:  # library warnings too (JAX's, Dask's): results go to --out
        import logging
        import warnings

        warnings.simplefilter("ignore")
        logging.disable(logging.WARNING)
    rows = run_batch(configs, args.out, scheduler=args.scheduler, workers=args.workers,
                     validate=args.validate, progress=not args.quiet)
    status = [r["status"] for r in rows]
    if not args.quiet:
        from rich.console import Console

        parts = [f"{status.count(s)} {s}" for s in STATUSES if status.count(s)]
        resumed = sum(bool(r["resumed"]) for r in rows)
        Console(stderr=True, highlight=False).print(
            f"{len(rows)} job(s): {', '.join(parts)}"
            + (f" ({resumed} kept from an earlier run)" if resumed else "")
            + f"; summary in {os.path.join(os.path.abspath(args.out), 'summary.csv')}")
        for r in rows:
            if r["status"] == "error":  # the message names the config or target
                Console(stderr=True, highlight=False, soft_wrap=True).print(
                    f"[red]error:[/] {r['error']}", markup=True)
    return EXIT_OK if all(s == "converged" for s in status) else EXIT_SOME_FAILED

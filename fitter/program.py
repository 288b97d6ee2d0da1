"""The ``fitter`` program (console script and ``python -m fitter``): the command
line of ``fitter.cli.main`` on ``sys.argv``, then a fast exit.

After a ``FAST_EXIT`` command every output is written, closed and moved into
place (``fitter.outdir``, ``fitter.imageio``) before ``main`` returns, and no
pool or server is left to shut down (``batch`` leaves Dask's), so the
interpreter's teardown -- 0.25-0.4 s of JAX's and drjit's runtimes -- is
skipped: JAX's pending effects are awaited, stdout and stderr flushed, then
``os._exit``. An exception out of ``main`` (exit code 1, a traceback) exits
normally. ``fitter.cli.main`` itself returns its code (tests call it in-process).
"""

from __future__ import annotations

import os
import sys

from .cli import EXIT_INTERNAL, main

#: Commands after which ``run`` ends the process with ``os._exit``.
FAST_EXIT = ("fit", "render", "validate")


def run() -> None:
    """Run the command line on ``sys.argv`` and exit with its code."""
    argv = sys.argv[1:]
    code = main(argv)
    if not (argv and argv[0] in FAST_EXIT):
        sys.exit(code)
    if "jax" in sys.modules:
        sys.modules["jax"].effects_barrier()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed or broken pipe: as Python's own exit would
            code = code or EXIT_INTERNAL
    os._exit(code)

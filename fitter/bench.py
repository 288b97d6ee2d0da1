"""``fitter bench``: the benchmarks of ``benchmarks/`` (error vs time, scaling, stiff cases).

The benchmark code lives in the source tree's ``benchmarks/`` folder (its
baselines are not part of the package); this module finds it next to the
package and runs ``benchmarks/run.py``. ``fitter bench --help`` lists the
options; ``benchmarks/README.md`` documents the runs.
"""

from __future__ import annotations

import os
import sys
from typing import Sequence

#: ``benchmarks/`` of a source checkout (the package is installed editable).
BENCH_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                         "benchmarks")


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``benchmarks/run.py`` with ``argv``; returns the exit code."""
    if not os.path.isfile(os.path.join(BENCH_DIR, "run.py")):
        print(f"fitter: error: the benchmarks need a source checkout ({BENCH_DIR}/run.py "
              "not found)", file=sys.stderr)
        return 2
    if BENCH_DIR not in sys.path:
        sys.path.insert(0, BENCH_DIR)
    import run

    return int(run.main(list(sys.argv[1:] if argv is None else argv)) or 0)

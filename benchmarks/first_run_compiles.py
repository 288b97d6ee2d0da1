"""Where a first fit's tracing, lowering and compiling go (issue 11 item 3:
the env first run is CPU-bound on them): one ``fitter.fit`` of a shipped case
in this process, without the persistent compilation cache, with
``jax_log_compiles`` on; per executable, the thread that made it and its
tracing, lowering and XLA compile seconds (summed over its compiles, whose
count is in brackets), largest first, then the totals per thread and the
fit's wall and CPU time.

    python benchmarks/first_run_compiles.py [--case env_plastic] [--top 25]

Tracing times nest (a function traced inside another counts in both), so
the per-thread trace totals overstate; lowering and compiling do not nest.
Compiles on other threads run beside the main one: their seconds are thread
time, slower when the two cores are shared.
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import re
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)
os.environ["FITTER_CACHE_DIR"] = ""  # a first run: nothing from disk

from _machine import host  # noqa: E402

#: (phase, pattern of jax's log line giving the name and seconds)
PHASES = (("trace", re.compile(r"^Finished tracing (\S+) for jit in ([\d.e-]+) sec")),
          ("lower", re.compile(r"^Finished jaxpr to MLIR module conversion jit\((.+?)\) in "
                               r"([\d.e-]+) sec")),
          ("compile", re.compile(r"^Finished XLA compilation of jit\((.+?)\) in ([\d.e-]+) sec")))


class _Log(logging.Handler):
    """Collects (thread, phase, name, seconds) from jax's compile log."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.rows: list = []

    def emit(self, record):
        msg = record.getMessage()
        for phase, pattern in PHASES:
            m = pattern.match(msg)
            if m:
                self.rows.append((threading.current_thread().name, phase, m.group(1),
                                  float(m.group(2))))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", default="env_plastic")
    ap.add_argument("--top", type=int, default=25, help="executables listed")
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_log_compiles", True)
    log = _Log()
    logger = logging.getLogger("jax")
    logger.addHandler(log)
    logger.setLevel(logging.DEBUG)
    logger.propagate = False  # the collector only, not the console

    import fitter
    from fitter import serialize
    from fitter.cases import CASES
    from fitter.imageio import read_image

    # The case as envlight.py's first fit loads it (its figures are the ones reported).
    spec = CASES[args.case]
    base = os.path.join(ROOT, "data_synthetic", args.case)
    scene = serialize.scene_from_dict(spec["scene"], args.case, base_dir=base)
    mat, _, _, fixed = serialize.material_from_dict(spec["material"], args.case)
    target = read_image(os.path.join(base, "target.exr"))
    t0, c0 = time.perf_counter(), time.process_time()
    res = fitter.fit(target, scene, mat, fixed=fixed or None, base_dir=base)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0

    per = collections.defaultdict(lambda: {"trace": 0.0, "lower": 0.0, "compile": 0.0, "n": 0})
    threads = collections.defaultdict(lambda: {"trace": 0.0, "lower": 0.0, "compile": 0.0})
    for thread, phase, name, seconds in log.rows:
        per[(thread, name)][phase] += seconds
        per[(thread, name)]["n"] += phase == "compile"
        threads[thread][phase] += seconds
    print(f"First fit of {args.case}: {wall:.2f} s wall, {cpu:.2f} s CPU ({res.status}); "
          f"{host()}\n")
    print("| thread | function (compiles) | trace s | lower s | compile s |")
    print("|---|---|---|---|---|")
    seconds = lambda s: s["trace"] + s["lower"] + s["compile"]  # noqa: E731
    ranked = sorted(per.items(), key=lambda kv: -seconds(kv[1]))
    for (thread, name), s in ranked[:args.top]:
        print(f"| {thread} | {name} ({s['n']}) | {s['trace']:.2f} | {s['lower']:.2f} "
              f"| {s['compile']:.2f} |")
    print(f"\n{sum(s['n'] for s in per.values())} compiles of {len(per)} functions by thread; "
          "a function traced on one thread and compiled on another has a row on each.\n")
    print("| thread | trace s (nested) | lower s | compile s |")
    print("|---|---|---|---|")
    for thread, s in sorted(threads.items()):
        print(f"| {thread} | {s['trace']:.2f} | {s['lower']:.2f} | {s['compile']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

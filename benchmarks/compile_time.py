"""First-run (cold compile) time of fits (issue 16: compile <= 1.5 s on a first
run; dielectric first run <= 5 s), this checkout against an older commit
(``--before REF``) in the same run, interleaved so both see the same load.

    python benchmarks/compile_time.py --before 8c59471 --repeat 3

Cases, each in a fresh process without the persistent compilation cache:

* ``plastic 256^2``: lambert + torrance_sparrow (Smith G), the benchmark's far
  start (``error_vs_time``), a JAX-rendered target with noise 1e-3 (the compile
  does not depend on the target's values); a coarse-to-fine fit.
* ``dielectric 128^2``: ``configs/dielectric.toml`` on its Mitsuba target.

Columns: ``compile`` is the fit's ``time_compile`` (tracing and compiling its
executables: the figure ``benchmarks/run.py`` reports), ``XLA`` the seconds XLA
itself spent compiling anything in the first fit (``jax_log_compiles``),
``first`` the wall time of the first ``fitter.fit`` call, ``compiled`` of the
second; the parameters and standard errors of both trees are compared.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import subprocess
import sys
import time

import _trees
from _machine import host

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CASES = ("plastic 256^2", "dielectric 128^2")
FAR = {"lambert.rho_d": [0.5, 0.5, 0.5], "torrance_sparrow.m": 0.3, "torrance_sparrow.eta": 1.3}


def _problem(case: str):
    import numpy as np

    import fitter

    if case.startswith("dielectric"):
        from fitter import config, pipeline

        job = config.load_config("configs/dielectric.toml")
        target, _ = pipeline.read_target(job.fit.target, job.scene)
        return job.scene, job.material, target, {"init": job.init, "fixed": job.fixed,
                                                      "base_dir": job.base_dir}
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    from error_vs_time import load_job

    job, base = load_job("plastic", 256)
    clean = np.asarray(fitter.render(job.truth, job.scene, job.material, base_dir=base))
    target = clean + np.random.default_rng(0).normal(0.0, 1e-3, clean.shape)
    return job.scene, job.material, target, {"init": FAR, "fixed": job.fixed, "base_dir": base}


def worker(case: str) -> dict:
    import jax
    import numpy as np

    import fitter

    xla = []

    class _Log(logging.Handler):
        def emit(self, rec):
            m = re.search(r"Finished XLA compilation of .* in ([0-9.e-]+) sec", rec.getMessage())
            if m:
                xla.append(float(m.group(1)))

    jax.config.update("jax_log_compiles", True)
    logging.getLogger("jax").addHandler(_Log())
    logging.getLogger("jax").propagate = False
    scene, material, target, kw = _problem(case)
    xla.clear()
    t = time.perf_counter()
    res = fitter.fit(target, scene, material, **kw)
    first = time.perf_counter() - t
    t_xla = sum(xla)
    t = time.perf_counter()
    fitter.fit(target, scene, material, **kw)
    return {"compile": res.time_compile, "xla": t_xla, "first": first,
            "compiled": time.perf_counter() - t, "status": res.status,
            "params": {k: np.asarray(v).tolist() for k, v in res.params.items()},
            "stderr": {k: np.asarray(v).tolist() for k, v in res.stderr.items()}}


def run(tree: str, case: str) -> dict:
    env = {**os.environ, "PYTHONPATH": tree, "FITTER_CACHE_DIR": ""}
    proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker", case],
                          cwd=tree, env=env, capture_output=True, text=True, check=False)
    if proc.returncode:
        return {"failed": proc.stderr.strip().splitlines()[-1:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _max_rel(a: dict, b: dict) -> float:
    import numpy as np

    out = 0.0
    for k, v in a.items():
        x, y = np.asarray(v, float), np.asarray(b.get(k, np.nan), float)
        out = max(out, float(np.max(np.abs(x - y) / np.maximum(np.abs(y), 1e-300))))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", help="git ref to compare with (extracted by git archive)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds of interleaved runs")
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=CASES)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker)))
        return 0
    trees = _trees.trees(args.before, "fitter-compile-")
    records = _trees.interleaved(trees, args.cases, args.repeat,
                                 lambda tree, case, _: run(tree, case))
    print(f"First-run compile, {args.repeat} fresh processes per (tree, case), interleaved; "
          f"least times; {host()}\n")
    print("| case | tree | compile (s) | XLA (s) | first run (s) | compiled (s) | status |")
    print("|---|---|---|---|---|---|---|")
    best = {}
    for case in args.cases:
        for name, _ in trees:
            rs = _trees.succeeded(records, name, case)
            if not rs:
                continue
            best[(name, case)] = {k: min(r[k] for r in rs) for k in
                                  ("compile", "xla", "first", "compiled")}
            b = best[(name, case)]
            print(f"| {case} | {name} | {b['compile']:.2f} | {b['xla']:.2f} | {b['first']:.2f} "
                  f"| {b['compiled']:.2f} | {rs[0]['status']} |")
    if len(trees) == 2:
        print("\nBefore / after (same run), and the largest relative change of a fitted value "
              "or standard error:")
        for case in args.cases:
            b, a = best.get((trees[0][0], case)), best.get(("after", case))
            if a and b:
                rb = next(r for r in records[(trees[0][0], case)] if "failed" not in r)
                ra = next(r for r in records[("after", case)] if "failed" not in r)
                print(f"- {case}: compile {b['compile'] / a['compile']:.1f}x, XLA "
                      f"{b['xla'] / a['xla']:.1f}x, first run {b['first'] / a['first']:.1f}x, "
                      f"compiled {b['compiled'] / a['compiled']:.2f}x; values "
                      f"{_max_rel(ra['params'], rb['params']):.1e}, errors "
                      f"{_max_rel(ra['stderr'], rb['stderr']):.1e}")
    print("\nTargets: compile <= 1.5 s (plastic 256^2), dielectric first run <= 5 s.")
    return 0


if __name__ == "__main__":
    sys.exit(main())

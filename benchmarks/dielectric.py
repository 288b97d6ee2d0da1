"""Dielectric fits at 128^2 (issue 16, item 4): first-run and compiled time and
accuracy, this checkout against an older commit (``--before REF``) in the same
run, interleaved so both see the same machine load.

    python benchmarks/dielectric.py --before a6b37ca            # all cases
    python benchmarks/dielectric.py --before a6b37ca --mitsuba  # + Mitsuba validation

Cases (128^2, 4x4 sub-pixel samples, the shipped envmap, absorbing interior):

* ``shipped``: ``configs/dielectric.toml`` on its Mitsuba target
  (``data_synthetic/dielectric``, eta 1.5, attenuation (0.9, 0.7, 0.5)),
  from the config's start (eta 1.3, attenuation 0.8);
* ``shipped, default start``: the same target from the lobe defaults (eta 1.5,
  attenuation 1), as ``tests/test_mitsuba_recovery.py`` fits it;
* ``eta=1.02`` / ``eta=1.001``: targets made by the JAX model (same scene and
  attenuation, Gaussian noise sigma 1e-3, seed 0), from the lobe defaults.

Each (tree, case) runs in a fresh process without the persistent compilation
cache: "first" is the wall time of its first ``fitter.fit`` call (tracing,
compiling and solving; not the imports), "compiled" the least of ``--fits``
further calls. ``--mitsuba`` re-renders the shipped fit with Mitsuba (1024 spp,
the config's validation) and gives the RMSE against the target.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import _trees
from _machine import host

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = "configs/dielectric.toml"
CASES = ("shipped", "shipped, default start", "eta=1.02", "eta=1.001")
NOISE = 1e-3


def _job_and_target(tree: str, case: str):
    import numpy as np

    from fitter import config, pipeline

    job = config.load_config(os.path.join(tree, CONFIG))
    target, saturated = pipeline.read_target(job.fit.target, job.scene)
    init = job.init if case == "shipped" else {}
    truth = dict(job.truth)
    if case.startswith("eta="):
        import fitter

        truth["dielectric.eta"] = float(case[4:])
        clean = np.asarray(fitter.render(truth, job.scene, job.material, base_dir=job.base_dir))
        target = clean + np.random.default_rng(0).normal(0.0, NOISE, clean.shape)
    return job, target, saturated, init, truth


def worker(tree: str, case: str, fits: int, mitsuba: bool) -> dict:
    t0 = time.perf_counter()
    import numpy as np

    import fitter
    from fitter import pipeline

    job, target, saturated, init, truth = _job_and_target(tree, case)
    t_setup = time.perf_counter() - t0
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from _stages import Stages

    timer = Stages()

    def one():
        return timer.run(lambda: fitter.fit(target, job.scene, job.material, init=init,
                                            fixed=job.fixed, base_dir=job.base_dir))

    res, first, first_stages = one()
    runs = [one() for _ in range(fits)]
    compiled, compiled_stages = min((t, s) for _, t, s in runs)
    out = {"setup": t_setup, "first": first, "compiled": compiled, "status": res.status,
           "stages_first": first_stages, "stages_compiled": compiled_stages,
           "iterations": res.iterations,
           "params": {k: np.asarray(v).tolist() for k, v in res.params.items()},
           "error": {k: np.abs(np.asarray(res.params[k]) - np.asarray(v)).max().item()
                     for k, v in truth.items()},
           "sigmas": {k: (np.abs(np.asarray(res.params[k]) - np.asarray(v))
                          / np.asarray(res.stderr[k])).max().item()
                      for k, v in truth.items() if k in res.stderr}}
    if mitsuba and case == "shipped":
        val = pipeline.validate(job, res.params, target, saturated, job.fit.validate_spp)
        out["mitsuba_rmse"] = val.rmse
    return out


def run(tree: str, case: str, fits: int, mitsuba: bool) -> dict:
    env = {**os.environ, "PYTHONPATH": tree, "FITTER_CACHE_DIR": ""}
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", tree, case, "--fits", str(fits)]
    if mitsuba:
        cmd.append("--mitsuba")
    proc = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if proc.returncode:
        return {"failed": proc.stderr.strip().splitlines()[-1:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", help="git ref to compare with (extracted by git archive)")
    ap.add_argument("--repeat", type=int, default=2, help="rounds of interleaved runs")
    ap.add_argument("--fits", type=int, default=3, help="compiled fits per process")
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=CASES)
    ap.add_argument("--mitsuba", action="store_true", help="validate the shipped fit")
    ap.add_argument("--worker", nargs=2, metavar=("TREE", "CASE"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(*args.worker, args.fits, args.mitsuba)))
        return 0

    trees = _trees.trees(args.before, "fitter-dielectric-")
    records = _trees.interleaved(
        trees, args.cases, args.repeat,
        lambda tree, case, rnd: run(tree, case, args.fits, args.mitsuba and rnd == 0))

    print(f"Dielectric fits at 128^2, 4x4 samples; {args.repeat} fresh processes per (tree, case), "
          f"interleaved; least times; {host()}\n")
    print("| case | tree | first run (s) | compiled (s) | steps | status | max error eta "
          "| max error attenuation | error / stderr | Mitsuba RMSE |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    best = {}
    for case in args.cases:
        for name, _ in trees:
            rs = _trees.succeeded(records, name, case)
            if not rs:
                continue
            first = min(r["first"] for r in rs)
            comp = min(r["compiled"] for r in rs)
            best[(name, case)] = (first, comp)
            r = rs[0]
            mi = next((f"{x['mitsuba_rmse']:.5f}" for x in rs if "mitsuba_rmse" in x), "")
            sig = max(r["sigmas"].values()) if r["sigmas"] else float("nan")
            print(f"| {case} | {name} | {first:.2f} | {comp:.2f} | {r['iterations']} | "
                  f"{r['status']} | {r['error']['dielectric.eta']:.2e} | "
                  f"{r['error']['dielectric.attenuation']:.2e} | {sig:.2f} | {mi} |")
    if len(trees) == 2:
        print("\nSpeed-up (before / after, same run):")
        for case in args.cases:
            b, a = best.get((trees[0][0], case)), best.get(("after", case))
            if a and b:
                print(f"- {case}: first run {b[0] / a[0]:.1f}x, compiled {b[1] / a[1]:.1f}x")
    for name, _ in trees:
        rs = [r for r in records.get((name, args.cases[0]), []) if "failed" not in r]
        if not rs:
            continue
        r = min(rs, key=lambda x: x["first"])
        c = min(rs, key=lambda x: x["compiled"])
        print(f"\nWhere the time goes ({name}, {args.cases[0]}; the fastest first run and "
              "compiled call; XLA = tracing, lowering and compiling inside the stage):\n")
        print("| stage | first run s | of which XLA s | compiled s |")
        print("|---|---|---|---|")
        for k, (t, x) in r["stages_first"].items():
            print(f"| {k} | {t:.2f} | {x:.2f} | {c['stages_compiled'].get(k, (0.0, 0.0))[0]:.2f} |")
        print(f"| **whole call** | {r['first']:.2f} | "
              f"{sum(x for _, x in r['stages_first'].values()):.2f} | {c['compiled']:.2f} |")
    print("\nTargets: compiled <= 2 s, first run <= 5 s, accuracy unchanged (shipped case).")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The memory model of ``fitter.limits`` against measurement: peak RSS of one
``fitter.render`` or ``fitter.fit`` per fresh process, for the shipped scenes
"plastic" (lambert + torrance_sparrow, 2 point lights), "env_plastic" (the
same lobes lit by the shipped probe), "dielectric" and "mirror" (specular
lobes under an envmap: the point-lit model), at several film sizes and
sub-pixel samples, beside ``limits.job_bytes``' estimate for it. ``MEMORY_MODEL`` is
chosen so that every row's estimate / measured is >= 1.

    python benchmarks/memory_model.py                      # the rows of the model's docs
    python benchmarks/memory_model.py --rows env_plastic:fit:128:4 plastic:render:1024:4
    python benchmarks/memory_model.py --many 5             # 5 scenes fitted in one process

``--many N``: N different env_plastic scenes (256^2, the sphere's radius
1.0, 0.98, ...) rendered and fitted one after the other in one process, its
RSS after each and its peak: what the scene caches keep (``fitter._keep``).

A fit's target is rendered first in a process of its own (the JAX model at
the truth plus Gaussian noise of sigma 2e-3), so the fit's peak is its own;
the persistent compilation cache is off (a first run).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from _machine import host

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
#: case:task:resolution:supersampling of a default run.
ROWS = ("plastic:render:256:4", "plastic:render:1024:4", "plastic:fit:256:4",
        "plastic:fit:1024:4", "env_plastic:render:128:4", "env_plastic:render:512:4",
        "env_plastic:fit:128:2", "env_plastic:fit:128:4", "env_plastic:fit:128:8",
        "env_plastic:fit:256:2", "env_plastic:fit:256:4", "env_plastic:fit:512:4",
        "dielectric:render:512:4", "dielectric:fit:256:4", "mirror:render:1024:4",
        "mirror:fit:512:4")


def _job(case: str, res: int, k: int | None = None):
    """(job, base_dir) of a shipped case at res x res (and k x k samples)."""
    from error_vs_time import load_job

    job, base = load_job(case, res)
    return (job if k is None else job.replace(scene=job.scene.replace(supersampling=k))), base


def _truth_image(job, base, scene, seed: int):
    import numpy as np

    import fitter

    img = np.asarray(fitter.render(job.material.full_params({**job.fixed, **job.truth}), scene,
                                   job.material, base_dir=base))
    return img + np.random.default_rng(seed).normal(0.0, 2e-3, img.shape)


def worker(case: str, task: str, res: int, k: int, folder: str) -> dict:
    import resource
    import time

    import numpy as np

    import fitter

    job, base = _job(case, res, k)
    path = os.path.join(folder, f"{case}-{res}-{k}.npy")
    t0 = time.perf_counter()
    if task == "render" or not os.path.exists(path):
        np.save(path, _truth_image(job, base, job.scene, 0))
    else:
        fitter.fit(np.load(path), job.scene, job.material, fixed=job.fixed or None,
                   base_dir=base)
    return {"seconds": time.perf_counter() - t0,
            "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0}


def many(n: int, res: int = 256) -> None:
    import gc
    import resource

    import fitter
    from fitter.scene import Sphere

    job, base = _job("env_plastic", res)
    print(f"{n} env_plastic scenes at {res}² in one process; {host()}\n")
    print("| scene | sphere radius | status | RSS after GB | peak RSS so far GB |")
    print("|---|---|---|---|---|")
    for i in range(n):
        radius = 1.0 - 0.02 * i
        s = job.scene.replace(sphere=Sphere(center=job.scene.sphere.center, radius=radius))
        r = fitter.fit(_truth_image(job, base, s, i), s, job.material, fixed=job.fixed or None,
                       base_dir=base)
        gc.collect()
        with open("/proc/self/statm") as fh:
            rss = int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0
        print(f"| {i} | {radius:.2f} | {r.status} | {rss / 1e9:.2f} | {peak / 1e9:.2f} |",
              flush=True)


def run(row: str, folder: str) -> dict:
    env = {**os.environ, "FITTER_CACHE_DIR": "", "PYTHONPATH": ROOT}
    case, task, res, k = row.split(":")
    steps = ([] if task == "render" or os.path.exists(
        os.path.join(folder, f"{case}-{res}-{k}.npy")) else ["render"]) + [task]
    for step in steps:
        proc = subprocess.run([sys.executable, __file__, "--worker", case, step, res, k, folder],
                              capture_output=True, text=True, env=env)
        if proc.returncode:
            raise SystemExit(f"{row}: {proc.stderr.strip().splitlines()[-1:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", nargs="+", default=list(ROWS), help="case:task:resolution:k")
    ap.add_argument("--many", type=int, help="fit this many scenes in one process")
    ap.add_argument("--worker", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.many:
        os.environ["FITTER_CACHE_DIR"] = ""
        sys.path.insert(0, ROOT)
        many(args.many)
        return 0
    if args.worker:
        case, task, res, k, folder = args.worker
        print(json.dumps(worker(case, task, int(res), int(k), folder)))
        return 0
    sys.path.insert(0, ROOT)
    from fitter import limits

    print(f"Peak RSS against fitter.limits' estimate; {host()}\n")
    print("| scene | task | film | samples | seconds | peak RSS GB | estimate GB | "
          "estimate / peak |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for row in args.rows:
            case, task, res, k = row.split(":")
            job, base = _job(case, int(res), int(k))
            est = limits.scene_bytes(task, job.scene, job.material, base)
            got = run(row, folder)
            print(f"| {case} | {task} | {res}² | {k}x{k} | {got['seconds']:.1f} | "
                  f"{got['peak'] / 1e9:.2f} | {est / 1e9:.2f} | {est / got['peak']:.2f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

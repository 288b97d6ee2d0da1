"""Peak memory and time of one `fitter.fit` at a resolution (the shipped
"plastic" case: lambert + torrance_sparrow, 2 point lights, 4x4 supersampling),
each in its own process so that ``ru_maxrss`` is that fit's peak.

    python benchmarks/memory.py 256 1024

The target is the JAX model at the truth plus Gaussian noise of sigma 2e-3
(as ``coarse_to_fine.py``'s: a noise-free target's stated errors are zero, which
skips their discretisation term, 12 s of a compiled 1024^2 fit until it was
capped); the start is the benchmark's far start. The
persistent compilation cache is off (a first run): ``compile s`` is the
compile, ``run s`` the solve and the diagnostics after it, ``warm s`` a
second fit in the same process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

from _machine import host

HERE = os.path.dirname(os.path.abspath(__file__))


def worker(res: int) -> dict:
    sys.path.insert(0, HERE)
    import numpy as np

    import fitter
    from error_vs_time import CASES, load_job

    job, base = load_job("plastic", res)
    target = np.asarray(fitter.render(job.material.full_params({**job.fixed, **job.truth}),
                                      job.scene, job.material, base_dir=base))
    target = target + np.random.default_rng(0).normal(0.0, 2e-3, target.shape)
    t0 = time.perf_counter()
    r = fitter.fit(target, job.scene, job.material, init=CASES["plastic"]["init"],
                   fixed=job.fixed, base_dir=base)
    t1 = time.perf_counter()
    fitter.fit(target, job.scene, job.material, init=CASES["plastic"]["init"],  # timed only
               fixed=job.fixed, base_dir=base)
    t2 = time.perf_counter()
    err = max(float(np.max(np.abs(np.asarray(r.params[k]) - np.asarray(v)) / np.abs(v)))
              for k, v in job.truth.items())
    return {"res": res, "first_s": t1 - t0, "compile_s": r.time_compile, "run_s": r.time_run,
            "warm_s": t2 - t1, "status": r.status, "max_rel_err": err}


def main(argv) -> int:
    if argv and argv[0] == "--worker":
        print(json.dumps(worker(int(argv[1]))))
        return 0
    env = {**os.environ, "FITTER_CACHE_DIR": ""}
    print("| resolution | first fit s (compile + run) | compiled fit s | status | "
          "max rel. error | peak RSS MB |")
    print("|---|---|---|---|---|---|")
    for res in (int(a) for a in (argv or ["256"])):
        proc = subprocess.Popen([sys.executable, __file__, "--worker", str(res)], env=env,
                                stdout=subprocess.PIPE, text=True)
        out = proc.stdout.read()
        _, status, usage = os.wait4(proc.pid, 0)
        if status:
            print(f"| {res}² | failed ({status}) | | | | {usage.ru_maxrss / 1024:.0f} |")
            continue
        r = json.loads(out.strip().splitlines()[-1])
        print(f"| {res}² | {r['first_s']:.2f} ({r['compile_s']:.2f} + {r['run_s']:.2f}) | "
              f"{r['warm_s']:.2f} | {r['status']} | {r['max_rel_err']:.1e} | "
              f"{usage.ru_maxrss / 1024:.0f} |")
    print(f"\n{host()} (1 / 5 min) at the end")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

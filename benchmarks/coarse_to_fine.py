"""Coarse-to-fine measured against a direct fit (issue 16, item 4): 256² plastic
(lambert + torrance_sparrow, 4x4 samples) from the benchmark's far start
(rho_d 0.5, m 0.3, eta 1.3), target from the JAX model at the truth.

Coarse: the target averaged 2x2 to 128², fitted with 2x2 samples per pixel;
fine: the full image from the coarse solution. Both compiled beforehand;
medians of 5 interleaved repetitions.

    python benchmarks/coarse_to_fine.py
"""

import statistics
import sys
import time

import numpy as np
import os
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import fitter
from error_vs_time import CASES, load_job
job, base = load_job("plastic", 256)
truth = job.material.full_params({**job.fixed, **job.truth})
target = np.asarray(fitter.render(truth, job.scene, job.material, base_dir=base))
coarse_scene = job.scene.replace(width=128, height=128, supersampling=2)
coarse_t = target.reshape(128, 2, 128, 2, 3).mean(axis=(1, 3))
init = CASES["plastic"]["init"]
def direct():
    return fitter.fit(target, job.scene, job.material, init=init, fixed=job.fixed, base_dir=base)
def c2f():
    r = fitter.fit(coarse_t, coarse_scene, job.material, init=init, fixed=job.fixed, base_dir=base)
    start = {k: v for k, v in r.params.items() if k in init}
    return fitter.fit(target, job.scene, job.material, init=start, fixed=job.fixed, base_dir=base), r
def err(r):
    return max(float(np.max(np.abs(np.asarray(r.params[k]) - np.asarray(v)) / np.abs(v))) for k, v in job.truth.items())
direct(); c2f()  # compile
td, tc = [], []
for i in range(5):
    t0 = time.perf_counter(); rd = direct(); t1 = time.perf_counter(); rc, rcoarse = c2f(); t2 = time.perf_counter()
    td.append(t1 - t0); tc.append(t2 - t1)
print(f"direct median {statistics.median(td):.3f} s  (iters {rd.iterations}, err {err(rd):.1e}, solve {rd.time_run:.3f})")
print(f"coarse-to-fine median {statistics.median(tc):.3f} s  (coarse iters {rcoarse.iterations} err {err(rcoarse):.1e} run {rcoarse.time_run:.3f}; fine iters {rc.iterations}, err {err(rc):.1e}, run {rc.time_run:.3f})")
print("stderr direct", {k: np.round(np.asarray(v),8) for k,v in rd.stderr.items()})
print("stderr c2f   ", {k: np.round(np.asarray(v),8) for k,v in rc.stderr.items()})

"""Scaling of one LM fit with the number of lights, and batched vs sequential fits.

Targets here are rendered by the project's own forward model (truth of the
``plastic`` case; timing does not depend on where the target came from).
Times are ``fitter.fit``'s own: compile and run reported separately, run
measured on a second, warm call. Pixel-count scaling comes from the
error-vs-time runs at several resolutions.
"""

from __future__ import annotations

import time

import numpy as np

RING_RADIUS, RING_HEIGHT = 5.0, 3.0


def lights(n: int):
    """``n`` point lights on a ring in front of the sphere (total intensity 70 W/sr)."""
    import fitter

    out = []
    for i in range(n):
        a = 2.0 * np.pi * i / n + 0.3
        pos = (RING_RADIUS * np.cos(a), RING_RADIUS * np.sin(a), RING_HEIGHT)
        out.append(fitter.PointLight(tuple(float(v) for v in pos), (70.0 / n,) * 3))
    return tuple(out)


def run(spec: dict) -> dict:
    import fitter

    from error_vs_time import CASES, load_job

    job, base = load_job("plastic", int(spec["res"]))
    init = CASES["plastic"]["init"]
    out = {"lights": [], "batch": None}
    for n in spec["lights"]:
        scene = job.scene.replace(lights=lights(n))
        target = np.asarray(fitter.render(job.truth, scene, job.material))
        cold = fitter.fit(target, scene, job.material, init=init, fixed=job.fixed)
        warm = fitter.fit(target, scene, job.material, init=init, fixed=job.fixed)
        out["lights"].append({"n_lights": n, "res": int(spec["res"]),
                              "compile_s": cold.time_compile, "fit_warm_s": warm.time_run,
                              "iterations": warm.iterations, "status": warm.status})
    nb = int(spec["batch"])
    rng = np.random.default_rng(0)
    scene = job.scene
    truths = [{"lambert.rho_d": rng.uniform(0.2, 0.8, 3),
               "torrance_sparrow.m": rng.uniform(0.1, 0.4),
               "torrance_sparrow.eta": rng.uniform(1.3, 1.8)} for _ in range(nb)]
    targets = np.stack([np.asarray(fitter.render(t, scene, job.material)) for t in truths])
    fitter.fit(targets[0], scene, job.material, init=init, fixed=job.fixed)  # compile
    t0 = time.perf_counter()
    seq = [fitter.fit(t, scene, job.material, init=init, fixed=job.fixed) for t in targets]
    t_seq = time.perf_counter() - t0
    b = {"n": nb, "res": int(spec["res"]), "sequential_s": t_seq,
         "sequential_converged": sum(r.converged for r in seq), "batch_s": None}
    # "map": one compiled loop over the targets (the default on CPU);
    # "vmap": every target's solver vectorised, run for the slowest one's steps.
    for mode, key in (("map", "batch"), ("vmap", "vmap")):
        kw = dict(init=init, fixed=job.fixed, batch=mode)
        fitter.fit_batch(targets, scene, job.material, **kw)  # compile
        t0 = time.perf_counter()
        res = fitter.fit_batch(targets, scene, job.material, **kw)
        b[f"{key}_s"] = time.perf_counter() - t0
        b[f"{key}_converged"] = sum(r.converged for r in res)
    out["batch"] = b
    return out

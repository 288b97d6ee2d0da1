"""Cost of the discretisation part of the stated error (issue 12, "k vs 2k").

At the fitted parameters the fit is rendered once more with 2k x 2k samples
per pixel (``fitter.fit._discretisation``) and the difference is taken
through the fit's linearisation. This prints, per image size, the whole fit's
wall time and the time of that step (minimum of ``--repeat`` warm runs,
after one cold run that compiles), as a ratio in the same run.

    python benchmarks/discretisation_cost.py [--sizes 128,256] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import fitter  # noqa: E402

LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
          fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0)))
TRUTH = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
         "torrance_sparrow.eta": 1.5}


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="128,256")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    mat = fitter.Material.make("lambert+torrance_sparrow", {"torrance_sparrow.geometry": "smith"})
    print("size  k->2k   fit s (warm)   discretisation s   share")
    for size in (int(s) for s in args.sizes.split(",")):
        scene = fitter.Scene(width=size, height=size, supersampling=4, lights=LIGHTS)
        clean = np.asarray(fitter.render(TRUTH, scene, mat))
        target = clean + np.random.default_rng(0).normal(0.0, 0.01, clean.shape)
        fitter.fit(target, scene, mat)  # cold: compiles
        best_fit, best_disc, info = np.inf, np.inf, None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            r = fitter.fit(target, scene, mat)
            best_fit = min(best_fit, time.perf_counter() - t0)
            info = r.adequacy["blocks"]["discretisation"]
            best_disc = min(best_disc, info["seconds"])
        k = info["supersampling"]
        print(f"{size:4d}  {k[0]}->{k[1]}   {best_fit:10.3f}   {best_disc:14.3f}   "
              f"{best_disc / best_fit:6.1%}", flush=True)


if __name__ == "__main__":
    main()

"""A conductor's fit along its valley of equal F0: ``fitter.fit`` against
Levenberg-Marquardt alone in Gulbrandsen's (F0, edge tint) coordinates.

Gold (m = 0.05, Smith, conductor Fresnel) under the tests' sky with a
one-texel sun (``tests/skies.py``, sun at row 28, column 64), 64^2, target by
the JAX model with Gaussian noise 0.01 (seed 0). Two solves of the same
problem:

* ``fitter.fit`` as shipped: Levenberg-Marquardt in (log m, F0, the angle on
  the circle of equal F0) per channel (``fit._valley``; before it, in (log m,
  log eta, log k): 278 and 114 steps for the two sun positions below), with
  its corner re-solve (``fit._corner``) and checks;
* Levenberg-Marquardt alone (the product's solver and tolerances) in (log m,
  logit F0, logit g) per channel, where (F0 = r, g) is Gulbrandsen's
  "artist friendly metallic Fresnel" (JCGT 3(4), 2014): n = g n_min + (1 - g)
  n_max with n_min = (1 - r) / (1 + r), n_max = (1 + sqrt r) / (1 - sqrt r),
  k^2 = (r (n + 1)^2 - (n - 1)^2) / (1 - r). It maps the box [0, 1)^2 onto
  the curve of equal F0 = r (g = 0: k = 0, the dielectric-like end; g = 1: n =
  n_min, the metal end), so the valley is a coordinate line.

Printed per solve: Levenberg-Marquardt steps, seconds (compiled), final cost,
F0 per channel against the truth's, eta and k.

    python benchmarks/conductor_coordinates.py [ROW COL]   # the sun's texel (28 64)
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, os.pardir))
sys.path.insert(0, os.path.join(HERE, os.pardir, "tests"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from skies import one_texel_sun  # noqa: E402

import fitter  # noqa: E402
from fitter.bsdf.fresnel import conductor_f0  # noqa: E402
from fitter.fit import _setup  # noqa: E402
from fitter.fit._solvers import ATOL, RTOL, make_solver  # noqa: E402
from fitter.render import render_active  # noqa: E402

TRUTH = {"torrance_sparrow.m": 0.05, "torrance_sparrow.eta": [0.18, 0.42, 1.37],
         "torrance_sparrow.k": [3.4, 2.35, 1.77]}
FIXED = {"torrance_sparrow.geometry": "smith", "torrance_sparrow.fresnel": "conductor"}
#: F0's upper end in the (F0, g) coordinates (n_max and k^2 divide by 1 - sqrt F0).
F0_MAX = 0.999


def gulbrandsen(r, g):
    """(n, k) of normal-incidence reflectance ``r`` and edge tint ``g`` (Gulbrandsen 2014)."""
    s = jnp.sqrt(r)
    n = g * (1 - r) / (1 + r) + (1 - g) * (1 + s) / (1 - s)
    k2 = (r * (n + 1) ** 2 - (n - 1) ** 2) / (1 - r)
    return n, jnp.sqrt(jnp.maximum(k2, 1e-12))


def _logit(u):
    return np.log(u) - np.log1p(-u)


def main():
    row, col = (int(a) for a in sys.argv[1:3]) if len(sys.argv) > 2 else (28, 64)
    with tempfile.TemporaryDirectory() as tmp:
        scene = one_texel_sun(os.path.join(tmp, "sky.exr"), row, col, [0.3, 0.4, 0.6],
                              [0.5, 0.5, 0.6], [0.15, 0.12, 0.1], [2000.0, 1900.0, 1700.0])
        clean = np.asarray(fitter.render({**TRUTH, **FIXED}, scene, "torrance_sparrow"))
        target = clean + np.random.default_rng(0).normal(0.0, 0.01, clean.shape)
        f0_truth = conductor_f0(np.array(TRUTH["torrance_sparrow.eta"]),
                                np.array(TRUTH["torrance_sparrow.k"]))
        print(f"sun at texel ({row}, {col}); truth F0 {np.round(f0_truth, 4)}")

        steps = []
        fitter.fit(target, scene, "torrance_sparrow", fixed=FIXED)  # compiled
        t0 = time.perf_counter()
        r = fitter.fit(target, scene, "torrance_sparrow", fixed=FIXED,
                       progress=lambda s: steps.append(s))
        t = time.perf_counter() - t0
        done = [s for s in steps if " done: " in s]
        f0 = conductor_f0(np.asarray(r.params["torrance_sparrow.eta"]),
                          np.asarray(r.params["torrance_sparrow.k"]))
        print(f"fitter.fit: {'; '.join(done)}; {t:.1f} s, cost {r.cost:.4f}, "
              f"F0 {np.round(f0, 4)}, eta {np.round(r.params['torrance_sparrow.eta'], 4)}, "
              f"k {np.round(r.params['torrance_sparrow.k'], 4)}, {r.status}")

        problem = _setup.Problem.make(target[None], scene, "torrance_sparrow", fixed=FIXED)
        data, spec = problem.data(0), problem.spec
        lo, hi = np.log(1e-3), np.log(1.0)

        def params(w):
            m = jnp.exp(lo + (hi - lo) * jax.nn.sigmoid(w[0]))
            n, k = gulbrandsen(F0_MAX * jax.nn.sigmoid(w[1:4]), jax.nn.sigmoid(w[4:7]))
            return {**data.fixed, "torrance_sparrow.m": m, "torrance_sparrow.eta": n,
                    "torrance_sparrow.k": k}

        def residuals(w, data):
            model = render_active(params(w), data.geometry, data.env, data.sphere,
                                  material=spec.material, env_type=spec.env_type)
            return ((model - data.target) * data.weights).reshape(-1)

        def solve(w0, data):
            import optimistix as optx

            sol = optx.least_squares(residuals, make_solver("levenberg_marquardt", RTOL, ATOL),
                                     w0, args=data, max_steps=500, throw=False)
            return sol.value, sol.stats["num_steps"]

        init = problem.init_full  # the same start: m 0.2, eta 1, k 3 (F0 9/13), g 1/2
        f00 = conductor_f0(np.asarray(init["torrance_sparrow.eta"]) * np.ones(3),
                           np.asarray(init["torrance_sparrow.k"]) * np.ones(3))
        w0 = jnp.asarray(np.concatenate([
            [_logit((np.log(init["torrance_sparrow.m"]) - lo) / (hi - lo))],
            _logit(f00 / F0_MAX), np.zeros(3)]))
        run = jax.jit(solve)
        jax.block_until_ready(run(w0, data))  # compiled
        t0 = time.perf_counter()
        w, n_steps = jax.block_until_ready(run(w0, data))
        t = time.perf_counter() - t0
        res = np.asarray(residuals(w, data))
        p = params(w)
        print(f"LM in (log m, logit F0, logit g): {int(n_steps)} steps, {t:.1f} s, "
              f"cost {0.5 * float(res @ res):.4f}, "
              f"F0 {np.round(F0_MAX * np.asarray(jax.nn.sigmoid(w[1:4])), 4)}, "
              f"eta {np.round(np.asarray(p['torrance_sparrow.eta']), 4)}, "
              f"k {np.round(np.asarray(p['torrance_sparrow.k']), 4)}, "
              f"g {np.round(np.asarray(jax.nn.sigmoid(w[4:7])), 4)}")


if __name__ == "__main__":
    main()

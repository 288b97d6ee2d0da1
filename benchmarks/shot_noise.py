"""Stated errors under shot noise (noise growing with the signal): a table.

A camera's noise is Poisson-Gaussian: photons = value / gain (Poisson), plus
read noise. For a shipped case's scene and material, the truth is rendered by
the model (so there is no model error), ``--draws`` noise draws are fitted
with the product's defaults and, per parameter, the spread (standard
deviation) of z = (fit - truth) / stated error over the draws is printed (1
for honest errors; sd of n unit normals ~ 1 +- 1/sqrt(2n)), its largest |z|,
the draws that are DISHONEST (|z| > 3 and beyond the practical tolerance
while "converged") and how many carried the "spatially structured" warning.

    python benchmarks/shot_noise.py [--case bright_phong] [--gain 0.01]
        [--read 1e-3] [--draws 12] [--seed 1]

Reference: the truth the target was rendered with; the fitter's stated
errors assume one noise level for the image (``fitter.fit._covariance``),
with a spatial-block sandwich for structured residuals (``_adequacy``).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))

from _machine import host  # noqa: E402
from honesty import TOL  # noqa: E402 (the practical tolerances, issue 12)

import fitter  # noqa: E402
from fitter import serialize  # noqa: E402
from fitter.cases import CASES  # noqa: E402

def _beyond(key: str, err, truth) -> np.ndarray:
    """Where ``err`` is beyond the practical tolerance of ``key`` (``honesty.TOL``)."""
    if key.split(".")[-1] not in TOL:
        return np.zeros(np.shape(err), bool)
    a, rel = TOL[key.split(".")[-1]]
    return np.abs(err) > a + rel * np.abs(truth)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", default="bright_phong")
    ap.add_argument("--gain", type=float, default=0.01, help="value of one photon")
    ap.add_argument("--read", type=float, default=1e-3, help="read noise (standard deviation)")
    ap.add_argument("--draws", type=int, default=12)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    spec = CASES[a.case]
    base = os.path.join(os.path.dirname(HERE), "data_synthetic", a.case)
    scene = serialize.scene_from_dict(spec["scene"], a.case, base_dir=base)
    mat, truth, _, fixed = serialize.material_from_dict(spec["material"], a.case)
    clean = np.asarray(fitter.render(mat.full_params(truth), scene, mat, base_dir=base))
    rng = np.random.default_rng(a.seed)
    z: dict = {}
    dishonest, warned = 0, 0
    for _ in range(a.draws):
        img = rng.poisson(np.maximum(clean, 0.0) / a.gain) * a.gain + rng.normal(
            0.0, a.read, clean.shape)
        res = fitter.fit(img, scene, mat, fixed=fixed or None, base_dir=base)
        warned += any("spatially structured" in w for w in res.warnings)
        bad = False
        for k in res.free:
            if k not in res.stderr:
                continue
            err = np.atleast_1d(res.params[k]) - np.atleast_1d(truth[k])
            zk = err / np.atleast_1d(res.stderr[k])
            z.setdefault(k, []).append(zk)
            bad |= bool(np.any((np.abs(zk) > 3) & _beyond(k, err, np.atleast_1d(truth[k]))
                               & (res.status == "converged")))
        dishonest += bad
    print(f"\n{host()}\n")
    print(f"{a.case}, Poisson-Gaussian noise: gain {a.gain:g}, read {a.read:g}, image max "
          f"{clean.max():.3g}; {a.draws} draws (seed {a.seed})\n")
    print("| parameter | sd of z (per channel) | max abs z |")
    print("|---|---|---|")
    for k, zk in z.items():
        zk = np.array(zk)
        print(f"| {k} | {', '.join(f'{s:.2f}' for s in np.std(zk, axis=0))} | "
              f"{np.abs(zk).max():.2f} |")
    print(f"\nDISHONEST draws (some parameter > 3 stated errors and beyond tolerance, "
          f"converged): {dishonest} of {a.draws}; 'spatially structured' warned: "
          f"{warned} of {a.draws}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

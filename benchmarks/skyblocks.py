"""The sky sum's block layout: time and padding per (block B, window S) (issue 11 item 3).

Usage: ``.venv/bin/python benchmarks/skyblocks.py [--case env_plastic] [--rounds 3]
[--layouts 16x2,256x4,...]``.

Takes the env samples' theta_o nodes of the case's scene (its geometry, built once),
lays them out with ``skystencil.blocks`` per (B, S) -- 16x2 is the former layout, 16
samples of one node per block -- and times ``sky_sum`` on a random table c and lobe h of
those shapes for 1, 3 and 6 lobe columns (a render, env_plastic's Jacobian, the cost
profile's six points), printing the padding rows' fraction and the minimum over
``--rounds`` interleaved rounds (the machine is shared: times are upper bounds; the
ratio to 16x2 in the same run is the figure). Equality of the layouts' sums is tested
in ``tests/test_skystencil.py``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir)
sys.path.insert(0, ROOT)

import jax.numpy as jnp
from envlight import best_ms  # the sibling benchmark's timer

from fitter import serialize, skystencil
from fitter.cases import CASES

R = importlib.import_module("fitter.render")


def _nodes(case):
    """(node, frac) per env sample of the case's geometry, and the node count."""
    spec = CASES[case]
    base = os.path.join(ROOT, "data_synthetic", case)
    scene = serialize.scene_from_dict(spec["scene"], case, base_dir=base)
    mat = serialize.material_from_dict(spec["material"], case)[0]
    geo = R.cached_renderer(scene, mat, jnp.dtype(jnp.float64), base).geometry
    win, pos = np.asarray(geo.env_node), np.asarray(geo.env_frac)
    real = np.asarray(geo.env_index) >= 0
    at = np.repeat(win[:, 0], pos.size // win.shape[0]) + pos
    node = np.minimum(np.floor(at).astype(np.int32), geo.env_cosines.cos_i.shape[0] - 2)
    return node[real], (at - node)[real], geo.env_cosines.cos_i.shape


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", default="env_plastic")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--layouts", default="16x2,256x4,256x3,256x5,512x4,128x3")
    a = ap.parse_args()
    node, frac, (t, n, _) = _nodes(a.case)
    rng = np.random.default_rng(0)
    cols = (1, 3, 6)
    hs = {k: jnp.asarray(rng.random((k, t, n))) for k in cols}
    setups = {}
    for lay in a.layouts.split(","):
        b, s = (int(x) for x in lay.split("x"))
        order, win, pos = skystencil.blocks(node, frac, t, block=b, window=s)
        c = jnp.asarray(rng.random((win.shape[0], 3 * b, n)))
        setups[lay] = (jnp.asarray(win), jnp.asarray(pos), c, 1 - node.size / order.size)
    best = {}
    for _ in range(a.rounds):  # interleaved: every layout sees the same load
        for lay, (win, pos, c, _) in setups.items():
            for k in cols:
                ms = best_ms(skystencil.sky_sum, hs[k], win, pos, c, repeat=4)
                best[lay, k] = min(best.get((lay, k), np.inf), ms)
    ref = next(iter(setups))
    print(f"{node.size} env samples, {t} nodes, {n} cells ({a.case})")
    print("| B x S | padding rows | " + " | ".join(f"{k} col ms" for k in cols)
          + f" | ratio to {ref} |")
    print("|---|---|" + "---|" * len(cols) + "---|")
    for lay, (*_, pad) in setups.items():
        ratio = " / ".join(f"{best[lay, k] / best[ref, k]:.2f}" for k in cols)
        print(f"| {lay} | {pad:.3f} | " + " | ".join(f"{best[lay, k]:.1f}" for k in cols)
              + f" | {ratio} |")


if __name__ == "__main__":
    main()

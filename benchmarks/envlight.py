"""Environment light on opaque lobes: model error vs Mitsuba, and cost, per discretisation.

Usage: ``.venv/bin/python benchmarks/envlight.py [--spp 4096] [--case env_plastic]``.

For the shipped HDR probe (``data_synthetic/probe.exr``) and a case's scene,
renders each lobe of the case alone with Mitsuba (path, MIS, max_depth 2) at
``--spp`` (two seeds: the noise floor) and with the model under several
discretisations of ``fitter.envlight`` (ring density of the sky stencil, sun
cell size), printing the interior relative RMSE and mean relative error, the
number of stencil cells, tabulation time and geometry memory. Then times the
compiled and first fit of the case with the defaults.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax.numpy as jnp
import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir)
sys.path.insert(0, ROOT)

from fitter import envlight, mitsuba, serialize  # noqa: E402
from fitter.cases import CASES  # noqa: E402
from fitter.material import Material  # noqa: E402
import importlib  # noqa: E402

R = importlib.import_module("fitter.render")


def _lobes(mat: Material, truth):
    for lobe in mat.lobe_objects:
        sub = {k: v for k, v in truth.items() if k.startswith(lobe.name + ".")}
        opts = {k: v for k, v in mat.options_of(lobe.name).items()}
        yield lobe.name, Material.from_params({**sub, **{f"{lobe.name}.{k}": v
                                                         for k, v in opts.items()}}), sub


_DEFAULT = (envlight.RING_EDGES, envlight.SUN_CELL)


def _variants():
    full, cell = _DEFAULT
    half = np.concatenate([full[:-1:2], full[-1:]])
    return {"default": (full, cell), "coarse rings": (half, cell), "sun cells halved": (full, 2 * cell)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=4096)
    ap.add_argument("--case", default="env_plastic")
    ap.add_argument("--variants", default="all", help="comma-separated labels, or all")
    a = ap.parse_args()
    spec = CASES[a.case]
    base = os.path.join(ROOT, "data_synthetic", a.case)
    scene = serialize.scene_from_dict(spec["scene"], a.case, base_dir=base)
    mat, truth, _, _ = serialize.material_from_dict(spec["material"], a.case)
    truth = mat.full_params(truth)
    for name, m, p in _lobes(mat, truth):
        ref = np.asarray(mitsuba.render(scene, m, m.full_params(p), spp=a.spp, seed=1))
        ref2 = np.asarray(mitsuba.render(scene, m, m.full_params(p), spp=a.spp, seed=2))
        for label, (edges, cell) in _variants().items():
            if a.variants != "all" and label not in a.variants.split(","):
                continue
            envlight.RING_EDGES, envlight.SUN_CELL = edges, cell
            envlight._tables.cache_clear()
            R._prepare.cache_clear()
            R.cached_renderer.cache_clear()
            t0 = time.perf_counter()
            r = R.cached_renderer(scene, m, jnp.dtype(jnp.float64), None)
            t_prep = time.perf_counter() - t0
            img = np.asarray(r.image({k: v for k, v in p.items()}))
            full = np.zeros(scene.width * scene.height, bool)
            full[np.asarray(r.pixel_index)[np.asarray(r.geometry.hit).all(1)]] = True
            full = full.reshape(scene.height, scene.width)
            d, n = (img - ref)[full], (ref - ref2)[full]
            scale = ref[full].mean()
            mem = sum(np.asarray(x).nbytes for x in (r.geometry.env_color, *r.geometry.env_cosines,
                                                      r.geometry.light_weight, *r.geometry.cosines))
            print(f"{name:18s} {label:15s} cells {r.geometry.env_color.shape[1]:4d} "
                  f"sun lights {r.geometry.light_color.shape[0]:3d}  rel RMSE {np.sqrt(np.mean(d**2)) / scale:.4f}"
                  f" (noise {np.sqrt(np.mean(n**2) / 2) / scale:.4f})  mean {d.mean() / scale:+.4f}"
                  f"  prepare {t_prep:.2f} s  geometry {mem / 2**20:.0f} MiB", flush=True)
        envlight.RING_EDGES, envlight.SUN_CELL = _variants()["default"]
        envlight._tables.cache_clear()


if __name__ == "__main__":
    main()

"""Environment light on opaque lobes: model error vs Mitsuba per discretisation, and cost.

Usage: ``.venv/bin/python benchmarks/envlight.py [--spp 4096] [--case env_plastic]
[--variants all|default,...] [--no-fit]``.

1. Accuracy. For the shipped HDR probe and a case's scene, renders each lobe of
   the case alone with Mitsuba (path, MIS, max_depth 2) at ``--spp`` with two
   seeds (their difference is the noise floor; cached under
   ``benchmarks/results/tmp/``) and with the model under several
   discretisations of the sky term (``envlight.Detail``: theta_o nodes, lobe
   points per cell; the stencil's ring density; the sun's sample sets; the
   limb pixels' env samples, ``geometry.LIMB_NODES`` and ``ENV_LIMB_COS``),
   printing over the pixels wholly on the sphere the relative RMSE, the mean
   relative error, the mean and RMS relative error of the limb pixels (cos_o <
   0.35 at a sub-sample) with the latter's noise floor, the per-step render and
   Jacobian time of that lobe alone and the geometry's memory.
2. Cost of the case's fit with the defaults, each in a fresh process: the first
   fit (tabulation + compilation + solve; no compilation cache) and its CPU
   time (all threads: steadier than wall time on a loaded machine) and the compiled
   fit (the same fit again in that process), with per-step render and Jacobian
   time of the whole material and peak RSS; the same for the case's material
   under two point lights (the ``plastic`` scene) as the baseline of the same run.
   ``--before REF`` runs the same fits on that commit's tree too (``_trees``),
   interleaved with this one's, and ``--repeat N`` keeps each figure's minimum
   over N runs (the machine is shared: times are upper bounds) and, with
   ``--before``, prints the paired median of the first fit's after - before
   differences (``paired``: the verdict to trust for a small change); the
   first fit's median over the runs is printed beside its minimum.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _trees  # noqa: E402
from _machine import host  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir)
sys.path.insert(0, ROOT)

import importlib  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from fitter import geometry, mitsuba, serialize, skystencil, suncells  # noqa: E402
from fitter.cases import CASES  # noqa: E402
from fitter.material import Material  # noqa: E402

R = importlib.import_module("fitter.render")
CACHE = os.path.join(ROOT, "benchmarks", "results", "tmp")


def _lobes(mat: Material, truth):
    for lobe in mat.lobe_objects:
        sub = {k: v for k, v in truth.items() if k.startswith(lobe.name + ".")}
        opts = dict(mat.options_of(lobe.name))
        yield lobe.name, Material.from_params({**sub, **{f"{lobe.name}.{k}": v
                                                         for k, v in opts.items()}}), sub


@contextlib.contextmanager
def _variant(label):
    """Module settings of a discretisation variant (restored afterwards)."""
    saved = (skystencil.Detail.__new__.__defaults__, suncells.SUN_CONE, suncells.SUN_EDGE,
             geometry.ENV_LIMB_COS, geometry.LIMB_NODES)
    nodes, sub, rings = skystencil.Detail()
    change = {"default": {}, "nodes 49": {"nodes": 49}, "nodes 65": {"nodes": 65},
              "nodes 193": {"nodes": 193},
              "sub 1x1": {"sub": (1, 1)}, "sub 1x2": {"sub": (1, 2)}, "sub 4x8": {"sub": (4, 8)},
              "coarse rings": {"rings": 2},
              "sun everywhere": {"cone": 4.0}, "limb 0.2": {"limb": 0.2},
              "limb 0.1": {"limb": 0.1}, "limb grid": {"limb_nodes": 0},
              "limb 3 points": {"limb_nodes": 3}, "limb 2 points": {"limb_nodes": 2},
              "limb 6 points": {"limb_nodes": 6}}[label]
    skystencil.Detail.__new__.__defaults__ = (change.get("nodes", nodes), change.get("sub", sub),
                                              change.get("rings", rings))
    suncells.SUN_CONE = change.get("cone", suncells.SUN_CONE)
    geometry.ENV_LIMB_COS = change.get("limb", geometry.ENV_LIMB_COS)
    geometry.LIMB_NODES = change.get("limb_nodes", geometry.LIMB_NODES)
    _clear()
    try:
        yield
    finally:
        (skystencil.Detail.__new__.__defaults__, suncells.SUN_CONE, suncells.SUN_EDGE,
         geometry.ENV_LIMB_COS, geometry.LIMB_NODES) = saved
        _clear()


def _clear():
    skystencil._cached_tables.cache_clear()
    skystencil.node_geometry.cache_clear()
    R._prepare.cache_clear()
    R.cached_renderer.cache_clear()


def _reference(scene, m, p, spp, seed, tag):
    os.makedirs(CACHE, exist_ok=True)
    path = os.path.join(CACHE, f"envlight_{tag}_{spp}_{seed}.npy")
    if os.path.exists(path):
        return np.load(path)
    img = np.asarray(mitsuba.render(scene, m, m.full_params(p), spp=spp, seed=seed))
    np.save(path, img)
    return img


def best_ms(fn, *args, repeat=3):
    """Least wall time (ms) of ``jax.jit(fn)(*args)`` over ``repeat`` calls, compiled first."""
    fj = jax.jit(fn)
    jax.block_until_ready(fj(*args))
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fj(*args))
        best = min(best, time.perf_counter() - t0)
    return 1e3 * best


def step_times(r, params, free):
    """(render ms, Jacobian ms) of ``render_active`` on r's geometry; Jacobian: forward
    mode in the ``free`` parameters (as the fit's)."""
    p = r.params(params)

    def f(p, geo):
        return R.render_active(p, geo, r.env, r.sphere, material=r.material, env_type=r.env_type)

    def jac(p, geo):
        sub = {k: p[k] for k in free}
        return jax.jacfwd(lambda s: f({**p, **s}, geo))(sub)

    return best_ms(f, p, r.geometry), best_ms(jac, p, r.geometry)


def accuracy(a):
    spec = CASES[a.case]
    base = os.path.join(ROOT, "data_synthetic", a.case)
    scene = serialize.scene_from_dict(spec["scene"], a.case, base_dir=base)
    mat, truth, _, _ = serialize.material_from_dict(spec["material"], a.case)
    truth = mat.full_params(truth)
    labels = ["default", "nodes 49", "nodes 65", "nodes 193", "sub 1x1", "sub 1x2", "sub 4x8",
              "coarse rings", "sun everywhere", "limb 0.2", "limb 0.1", "limb grid",
              "limb 2 points", "limb 3 points", "limb 6 points"]
    if a.variants != "all":
        labels = [v for v in labels if v in a.variants.split(",")]
    print("| lobe | variant | rel RMSE | noise | mean | limb mean | limb rel RMSE | its noise "
          "| render ms | jac ms | prepare s | geometry MiB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, m, p in _lobes(mat, truth):
        ref = _reference(scene, m, p, a.spp, 1, f"{a.case}_{name}")
        ref2 = _reference(scene, m, p, a.spp, 2, f"{a.case}_{name}")
        for label in labels:
            with _variant(label):
                t0 = time.perf_counter()
                r = R.cached_renderer(scene, m, jnp.dtype(jnp.float64), None)
                t_prep = time.perf_counter() - t0
                img = np.asarray(r.image(dict(p)))
                free = [k for k in r.params(dict(p)) if k.split(".", 1)[1] != "rho_s"]
                t_r, t_j = step_times(r, dict(p), free)
            geo = r.geometry
            hit = np.asarray(geo.hit)
            full = np.zeros(scene.width * scene.height, bool)
            full[np.asarray(r.pixel_index)[hit.all(1)]] = True
            cos_c = -np.sum(np.asarray(geo.normal) * np.asarray(geo.ray_dir), -1).min(1)
            limb = np.zeros_like(full)
            limb[np.asarray(r.pixel_index)[hit.all(1) & (cos_c < 0.35)]] = True
            full, limb = full.reshape(scene.height, -1), limb.reshape(scene.height, -1)
            d, n = (img - ref)[full], (ref - ref2)[full]
            scale = ref[full].mean()
            rel = (img - ref)[limb] / np.maximum(ref[limb], 1e-9)
            rel_noise = (ref - ref2)[limb] / np.maximum(ref[limb], 1e-9)
            rel_limb = rel.mean()
            mem = sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(geo))
            print(f"| {name} | {label} | {np.sqrt(np.mean(d**2)) / scale:.4f} | "
                  f"{np.sqrt(np.mean(n**2) / 2) / scale:.4f} | {d.mean() / scale:+.4f} | "
                  f"{rel_limb:+.4f} | {np.sqrt(np.mean(rel**2)):.4f} | "
                  f"{np.sqrt(np.mean(rel_noise**2) / 2):.4f} | {t_r:.1f} | {t_j:.1f} | "
                  f"{t_prep:.2f} | "
                  f"{mem / 2**20:.0f} |", flush=True)


_FIT = r"""
import json, os, resource, sys, time
t0 = time.perf_counter()
import numpy as np, fitter
from fitter import serialize
from fitter.cases import CASES
from fitter.imageio import read_image
sys.path.insert(0, os.path.join(%(root)r, "benchmarks"))
import envlight as B
case, scene_of = %(case)r, %(scene_of)r
spec = CASES[case]
base = os.path.join(%(root)r, "data_synthetic", case)
scene = serialize.scene_from_dict(CASES[scene_of]["scene"], case, base_dir=base)
mat, truth, _, fixed = serialize.material_from_dict(spec["material"], case)
target = np.asarray(fitter.render(mat.full_params(truth), scene, mat, base_dir=base)) \
    if scene_of != case else read_image(os.path.join(base, "target.exr"))
t1, c1 = time.perf_counter(), time.process_time()
res = fitter.fit(target, scene, mat, fixed=fixed or None, base_dir=base)
t_first, t_compile = time.perf_counter() - t1, res.time_compile
cpu_first = time.process_time() - c1
t1 = time.perf_counter()
res = fitter.fit(target, scene, mat, fixed=fixed or None, base_dir=base)
t_again = time.perf_counter() - t1
import importlib, jax.numpy as jnp
R = importlib.import_module("fitter.render")
r = R.cached_renderer(scene, mat, jnp.dtype(jnp.float64), base)
t_r, t_j = B.step_times(r, mat.full_params(truth), list(res.free))
print(json.dumps({"first": t_first, "cpu_first": cpu_first, "again": t_again,
                  "steps": res.iterations,
                  "render_ms": t_r, "jac_ms": t_j, "status": res.status,
                  "compile": t_compile,
                  "params": {k: np.asarray(v).tolist() for k, v in res.params.items()},
                  "rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}))
"""


def _fit_once(root, case, scene_of):
    env = dict(os.environ, FITTER_CACHE_DIR="", PYTHONPATH=root)
    code = _FIT % {"root": root, "case": case, "scene_of": scene_of}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=False, cwd=root)
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if not line:
        print(out.stderr[-2000:])
        return None
    return json.loads(line[-1])


def paired(runs: dict, case: str) -> str:
    """Median and spread of the after - before differences of the env case's first
    fit, run by run (both trees ran in each round, one after the other): single
    runs here vary by +-0.3 s, so a minimum of 5 hides differences of 0.1-0.3 s;
    the paired median of 10 rounds resolves ~0.1 s."""
    lines = []
    for field in ("first", "cpu_first"):
        a, b = (runs.get((name, case), []) for name in ("after", "before"))
        d = np.array([x.get(field, np.nan) - y.get(field, np.nan) for x, y in zip(a, b)
                      if x is not None and y is not None])
        if d.size:
            lines.append(f"{field}: after - before, paired median {np.median(d):+.2f} s, "
                         f"mean {d.mean():+.2f}, sd {d.std():.2f} ({d.size} rounds)")
    return "\n".join(lines)


def cost(a):
    trees = _trees.trees(a.before, "fitter-envlight-")
    best = {}
    runs: dict = {}  # (tree, scene) -> [record or None] per round
    for _ in range(a.repeat):  # interleaved: every tree and scene sees the same load
        for name, root in trees:
            for scene_of in ("plastic", a.case):
                d = _fit_once(root, a.case, scene_of)
                # (a copy: the minima below update d in place)
                runs.setdefault((name.split(" ")[0], scene_of), []).append(d and dict(d))
                if d is None:
                    continue
                key = (name, scene_of)
                if key in best:
                    d.update({k: min(d[k], best[key][k]) for k in
                              ("first", "cpu_first", "again", "render_ms", "jac_ms", "compile",
                               "rss_gb")
                              if k in best[key]})
                best[key] = d
    print(f"\n{host()} (1 / 5 min) at the end\n")
    print("| tree | scene | first fit s | its median | its CPU s | of it compile s | "
          "compiled fit s | steps | render ms | Jacobian ms | peak RSS GB | status |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (name, scene_of), d in best.items():
        label = "point lights (baseline)" if scene_of == "plastic" else f"{a.case} (envmap)"
        firsts = [r["first"] for r in runs[(name.split(" ")[0], scene_of)] if r]
        print(f"| {name} | {label} | {d['first']:.2f} | {np.median(firsts):.2f} | "
              f"{d.get('cpu_first', float('nan')):.2f} | "
              f"{d.get('compile', float('nan')):.2f} | "
              f"{d['again']:.2f} | {d['steps']} | {d['render_ms']:.1f} | {d['jac_ms']:.1f} | "
              f"{d['rss_gb']:.2f} | {d['status']} |", flush=True)
    for (name, scene_of), d in best.items():
        if scene_of == a.case:
            print(f"fitted ({name}):", {k: np.round(v, 5).tolist() for k, v in d["params"].items()})
    if a.before:
        print(paired(runs, a.case))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=4096)
    ap.add_argument("--case", default="env_plastic")
    ap.add_argument("--variants", default="all", help="comma-separated labels, or all")
    ap.add_argument("--no-fit", action="store_true")
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--before", help="git ref whose tree's fits to run too (git archive)")
    ap.add_argument("--repeat", type=int, default=1, help="runs per fit; each figure's minimum")
    a = ap.parse_args()
    if not a.no_accuracy:
        accuracy(a)
    if not a.no_fit:
        cost(a)


if __name__ == "__main__":
    main()

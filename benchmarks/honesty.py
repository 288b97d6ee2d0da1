"""Honest answers on images the model did not make (issue 12): a table.

For each shipped Mitsuba case (``data_synthetic/``) and for mismatch cases
rendered here with Mitsuba (``MISMATCH``: a ``roughplastic`` sphere fitted
with lambert + torrance_sparrow, eta near 1 with one start, gold fitted with
a dielectric Fresnel, a sub-pixel highlight), fit with the product's defaults
and print per parameter the error / stated standard error, whether the error
is beyond the practical tolerance (rho 0.005, sigma 0.02, m 2 %, e 3 %, eta
0.005), and the verdict (status, warnings). A row is DISHONEST when the error
is both > 3 stated errors and beyond tolerance while the status is
"converged" and the parameter is listed identifiable.

    python benchmarks/honesty.py [--out results/honesty.json] [--cases a,b]

The "before" column of ``benchmarks/README.md`` is this script run with the
package of commit 1af5b24 first on the path (a ``git worktree``):

    git worktree add /tmp/before 1af5b24
    PYTHONPATH=/tmp/before python benchmarks/honesty.py --out /tmp/before.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import fitter  # noqa: E402
from fitter import config  # noqa: E402
from fitter.imageio import read_image  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir, "data_synthetic")
#: (absolute, relative) practical tolerance per parameter name (issue 12).
TOL = {"rho_d": (0.005, 0), "rho_s": (0.005, 0), "rho_m": (0.005, 0), "sigma": (0.02, 0),
       "m": (0, 0.02), "e": (0, 0.03), "eta": (0.005, 0), "attenuation": (0.01, 0),
       "k": (0.005, 0)}
SPP = 1024


def _shipped():
    from fitter.cases import CASES

    for name in CASES:
        folder = os.path.join(ROOT, name)
        case = json.load(open(os.path.join(folder, "case.json")))
        job = config.job_from_dict({"scene": case["scene"], "material": case["material"]},
                                   base_dir=folder)
        target = read_image(os.path.join(folder, "target.exr"))
        yield name, target, job.scene, job.material, case["truth"], {"base_dir": folder}


def _render(scene, bsdf, spp=SPP):
    """Mitsuba render of ``scene`` with the sphere's BSDF replaced by ``bsdf``."""
    import mitsuba as mi

    import fitter.mitsuba as fm
    from fitter.mitsuba import plugins

    material = fitter.Material.make("lambert")
    d = fm.scene_dict(scene, material, {}, spp=spp, seed=7)
    plugins.register(mi)
    d["sphere"]["bsdf"] = bsdf
    img = mi.render(mi.load_dict(d), spp=fm.stratified_spp(spp), seed=7)
    return np.array(img, dtype=np.float64)[..., :3]


def _mismatch():
    """Targets the model did not make, or one it makes but a single start misses."""
    import fitter.mitsuba as fm

    lights = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
              fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0)))
    scene = fitter.Scene(width=128, height=128, supersampling=4, lights=lights)
    rgb = lambda v: {"type": "rgb", "value": list(v)}  # noqa: E731
    plastic = {"type": "roughplastic", "distribution": "beckmann", "alpha": 0.2,
               "int_ior": 1.5, "ext_ior": 1.0, "diffuse_reflectance": rgb((0.2, 0.5, 0.7))}
    mat = fitter.Material.make("lambert+torrance_sparrow",
                               {"torrance_sparrow.geometry": "smith"})
    yield ("roughplastic", _render(scene, plastic, 4096), scene, mat,
           {"lambert.rho_d": [0.2, 0.5, 0.7], "torrance_sparrow.m": 0.2,
            "torrance_sparrow.eta": 1.5}, {})
    truth = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.2,
             "torrance_sparrow.eta": 1.02, "torrance_sparrow.rho_s": 1.0}
    yield ("low_eta_m0.2", fm.render(scene, mat, truth, spp=SPP, seed=3), scene, mat, truth, {})
    weak = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.3,
            "torrance_sparrow.eta": 1.1, "torrance_sparrow.rho_s": 1.0}
    yield ("weak_specular", fm.render(scene, mat, weak, spp=SPP, seed=4), scene, mat, weak, {})
    small = scene.replace(width=64, height=64)
    sharp = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.01,
             "torrance_sparrow.eta": 1.5, "torrance_sparrow.rho_s": 1.0}
    yield ("subpixel_highlight", fm.render(small, mat, sharp, spp=SPP, seed=5), small, mat,
           sharp, {})
    gold = {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.25,
            "material": "Au"}
    ts = fitter.Material.make("torrance_sparrow", {"torrance_sparrow.geometry": "smith"})
    g64 = scene.replace(width=64, height=64)
    yield ("gold_dielectric_fresnel", _render(g64, gold), g64, ts,
           {"torrance_sparrow.m": 0.25}, {"n_starts": 4})


def verdict_rows(name, res, truth):
    rows = []
    identifiable = [k for k in res.free if k not in res.unidentifiable]
    for key, t in truth.items():
        short = key.split(".")[1]
        if short not in TOL:
            continue
        a, rel = TOL[short]
        err = np.abs(np.asarray(res.params[key], float) - np.asarray(t, float))
        if key in res.unidentifiable and key in res.free:  # reported, no error stated
            rows.append({"case": name, "param": key, "err_over_stderr": None,
                         "sys_over_stat": None, "disc_over_stat": None,
                         "err": float(np.max(err)),
                         "beyond_tol": bool(np.any(err > a + rel * np.abs(np.asarray(t, float)))),
                         "dishonest": False, "unidentifiable": True})
            continue
        if key not in res.stderr or key not in identifiable:
            continue
        se = np.maximum(np.asarray(res.stderr[key], float), 1e-300)
        beyond = err > a + rel * np.abs(np.asarray(t, float))
        ratio = err / se
        bad = bool(np.any(beyond & (ratio > 3)) and res.status == "converged")
        sys_ratio = disc_ratio = None
        if key in getattr(res, "stderr_sys", {}):
            stat = np.maximum(np.asarray(res.stderr_stat[key], float), 1e-300)
            sys_ratio = float(np.max(np.asarray(res.stderr_sys[key], float) / stat))
            if key in getattr(res, "stderr_disc", {}):
                disc_ratio = float(np.max(np.asarray(res.stderr_disc[key], float) / stat))
        rows.append({"case": name, "param": key, "err_over_stderr": float(np.max(ratio)),
                     "sys_over_stat": sys_ratio, "disc_over_stat": disc_ratio,
                     "err": float(np.max(err)), "beyond_tol": bool(np.any(beyond)),
                     "dishonest": bad})
    return rows


def table(before: list, after: list) -> str:
    """Markdown: per case and parameter, error / stated error and the verdict,
    before and after (``*`` marks a dishonest row)."""
    b = {(r["case"], x["param"]): (r, x) for r in before for x in r["rows"]}
    bs = {r["case"]: r for r in before}
    lines = ["| case | parameter | beyond tolerance | before: err/σ, status | "
             "after: err/σ (σ_sys/σ_stat; σ_disc/σ_stat), status |", "|---|---|---|---|---|"]
    for r in after:
        for x in r["rows"]:
            old = b.get((r["case"], x["param"]))
            if old:
                o = f"{old[1]['err_over_stderr']:.3g}{'*' if old[1]['dishonest'] else ''}, " \
                    f"{old[0]['status']}"
            else:
                o = f"–, {bs[r['case']]['status']}" if r["case"] in bs else "n/a"
            sys_ratio, disc = x.get("sys_over_stat"), x.get("disc_over_stat")
            if x.get("unidentifiable"):
                new = f"unidentifiable, {r['status']}"
            else:
                new = f"{x['err_over_stderr']:.3g}{'*' if x['dishonest'] else ''}" + (
                    f" ({sys_ratio:.2g}; {disc:.2g})" if disc is not None else
                    f" ({sys_ratio:.2g})" if sys_ratio is not None else "") + f", {r['status']}"
            lines.append(f"| {r['case']} | {x['param'].split('.', 1)[1]} | "
                         f"{'yes' if x['beyond_tol'] else 'no'} | {o} | {new} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=None)
    ap.add_argument("--table", nargs=2, metavar=("BEFORE", "AFTER"),
                    help="print the markdown table of two --out files and exit")
    ap.add_argument("--cases", default=None, help="comma-separated names")
    ap.add_argument("--no-shipped", action="store_true")
    args = ap.parse_args(argv)
    if args.table:
        print(table(*(json.load(open(f)) for f in args.table)))
        return []
    want = set(args.cases.split(",")) if args.cases else None
    out = []
    sources = ([] if args.no_shipped else [_shipped()]) + [_mismatch()]
    for src in sources:
        while True:
            try:  # a case an older fitter cannot read or render is recorded, not fatal
                name, target, scene, mat, truth, kw = next(src)
            except StopIteration:
                break
            except Exception as exc:  # noqa: BLE001
                print(f"(a case could not be set up: {type(exc).__name__}: {exc})", flush=True)
                continue
            if want and name not in want:
                continue
            t0 = time.perf_counter()
            try:
                res = fitter.fit(target, scene, mat, **kw)
            except Exception as exc:  # noqa: BLE001
                out.append({"case": name, "status": f"error: {type(exc).__name__}", "rows": []})
                print(f"{name:26s} error {exc}", flush=True)
                continue
            rows = verdict_rows(name, res, truth)
            rec = {"case": name, "status": res.status, "message": res.message,
                   "warnings": res.warnings, "rows": rows, "seconds": time.perf_counter() - t0,
                   "stderr_sys": {k: np.asarray(v).tolist() for k, v in
                                  getattr(res, "stderr_sys", {}).items()},
                   "stderr_disc": {k: np.asarray(v).tolist() for k, v in
                                   getattr(res, "stderr_disc", {}).items()},
                   "discretisation": res.adequacy.get("blocks", {}).get("discretisation"),
                   "unidentifiable": list(res.unidentifiable),
                   "derived": getattr(res, "derived", {})}
            out.append(rec)
            rated = [r for r in rows if r["err_over_stderr"] is not None]
            worst = max(rated, key=lambda r: r["err_over_stderr"]) if rated else None
            print(f"{name:26s} {res.status:10s} "
                  + (f"worst {worst['param']:26s} err/se {worst['err_over_stderr']:9.2f} "
                     f"beyond {worst['beyond_tol']!s:5s}" if worst else "")
                  + (" DISHONEST" if any(r["dishonest"] for r in rows) else ""), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    sys.exit(0 if main() is not None else 1)

"""The benchmarks: error against run time, baselines, scaling, stiff cases.

A script of the source checkout, not part of the package:
``python benchmarks/run.py [--quick] [--out DIR] [--skip PART]`` (see
README.md here). Every measurement runs in its own subprocess (this script
again, with ``--worker``), so the peak resident memory of each method is that process's own
(``os.wait4``'s ``ru_maxrss``) and no method warms another's caches. Targets
are Mitsuba renders: the shipped ``data_synthetic/<case>/target.exr`` at
128 x 128, rendered here with the case's settings at other resolutions.

Writes to ``--out`` (default ``benchmarks/results``): ``samples.csv`` (one row
per recorded iteration and parameter coordinate), ``results.json``
(everything), ``results.md`` (the tables) and ``error_vs_time.png``.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
#: The speed targets of the project (lambert + torrance_sparrow, 256^2, 2 point lights).
TARGET_CASE, TARGET_RES = "plastic", 256
TARGET_FIT_S, TARGET_COMPILE_S, TARGET_VS_SCIPY, TARGET_VS_MITSUBA = 0.1, 1.5, 30.0, 100.0
LEVELS = (1e-2, 1e-3)

#: (case, resolution, method, options) of each run.
QUICK = {
    "evt": [("plastic", 256, m, {}) for m in ("lm", "scipy")]
    # 4 spp, the fastest setting, long enough to reach 0.1 % (a verdict, not a bound)
    + [("plastic", 256, "mitsuba", {"spp": 4, "iters": 200}),
       ("plastic", 256, "mitsuba", {"spp": 16, "iters": 60})]
    + [("plastic", 128, m, {}) for m in ("lm", "dogleg", "bfgs", "scipy")]
    + [("plastic", 128, "adam", {"max_steps": 300}),
       ("plastic", 128, "mitsuba", {"spp": 16, "iters": 100})],
    "scaling": {"res": 64, "lights": [1, 2, 4], "batch": 8},
    "stiff": {"size": 24, "dtypes": ["float64", "float32"], "fast_only": True},
}
FULL = {
    "evt": [(c, 128, m, {}) for c in ("lambert", "oren_nayar", "phong", "torrance_sparrow",
                                      "mirror", "oren_nayar_phong", "dielectric")
            for m in ("lm", "dogleg", "bfgs", "adam")]
    + [("plastic", r, m, {}) for r in (64, 128, 256)
       for m in ("lm", "dogleg", "bfgs", "adam", "scipy")]
    + [("plastic", r, "mitsuba", {"spp": spp, "iters": 300}) for r in (64, 128, 256)
       for spp in (4, 16, 64)]
    + [("plastic", r, "mitsuba", {"spp": 16, "iters": 300, "lr": 0.05}) for r in (128, 256)],
    "scaling": {"res": 128, "lights": [1, 2, 4, 8], "batch": 16},
    "stiff": {"size": 32, "dtypes": ["float64", "float32"], "fast_only": False},
}


# --------------------------------------------------------------------------- workers


def worker(kind: str, spec_path: str, out_path: str) -> int:
    sys.path.insert(0, HERE)  # the sibling modules, also when imported as benchmarks.run
    with open(spec_path) as fh:
        spec = json.load(fh)
    if kind == "evt":
        import error_vs_time as mod
    elif kind == "scaling":
        import scaling as mod
    else:
        import stiff as mod
    out = mod.run(spec)
    with open(out_path, "w") as fh:
        json.dump(out, fh)
    return 0


def spawn(kind: str, spec: dict, tmp: str, log, cache: str = "") -> dict:
    """Run one worker subprocess; returns its result with ``peak_rss_mb`` and ``process_s``.

    ``cache``: the worker's persistent XLA compilation cache folder
    (``FITTER_CACHE_DIR``); empty (default) turns it off, so compile times
    are those of a first run.
    """
    n = len(os.listdir(tmp))
    spec_path, out_path = os.path.join(tmp, f"spec{n}.json"), os.path.join(tmp, f"out{n}.json")
    with open(spec_path, "w") as fh:
        json.dump(spec, fh)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--worker", kind,
                             spec_path, out_path], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "FITTER_CACHE_DIR": cache})
    output = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    secs = time.perf_counter() - t0
    if proc.returncode != 0 or not os.path.exists(out_path):
        log(f"  worker failed (exit {proc.returncode}):\n{output[-3000:]}")
        return {"error": output[-3000:], "process_s": secs, **spec}
    with open(out_path) as fh:
        out = json.load(fh)
    out["peak_rss_mb"] = usage.ru_maxrss / 1024.0  # Linux: kilobytes
    out["process_s"] = secs
    return out


def make_target(case: str, res: int, tmp: str) -> str:
    """Path of a .npy Mitsuba target of ``case`` at ``res`` x ``res``."""
    path = os.path.join(tmp, f"target_{case}_{res}.npy")
    if os.path.exists(path):
        return path
    sys.path.insert(0, HERE)
    from error_vs_time import load_job

    job, base = load_job(case, res)
    shipped = os.path.join(base, "target.exr")
    if res == 128 and os.path.exists(shipped):
        from fitter.imageio import read_image

        img = read_image(shipped)
    else:
        import fitter.mitsuba as fm
        from fitter.cases import CASES

        spp = min(int(CASES[case]["synth"]["spp"]), 1024)
        img = fm.render(job.scene, job.material, job.truth, spp=spp, seed=0, base_dir=base)
    np.save(path, np.asarray(img, dtype=np.float64))
    return path


# --------------------------------------------------------------------------- analysis


def label(r: dict) -> str:
    """Method name with the Mitsuba baseline's settings."""
    if r.get("method") == "mitsuba":
        return f"mitsuba spp{r.get('spp')} lr{r.get('lr', 0.02):g}"
    return r.get("method", "?")


def time_to(trace, level):
    """Seconds until the max relative error drops below ``level`` and stays there."""
    t = None
    for row in trace:
        if row["max_rel_err"] <= level:
            if t is None:
                t = row["time_s"]
        else:
            t = None
    return t


def final_err(trace):
    return trace[-1]["max_rel_err"] if trace else float("nan")


def machine() -> str:
    from _machine import cpu

    import jax

    return (f"{cpu()}, nproc {os.cpu_count()}, {platform.system()} {platform.release()}, "
            f"Python {platform.python_version()}, jax {jax.__version__}")


def _fmt(x, unit=""):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "—"
    return f"{x:.3g}{unit}"


def summarize(evt: list[dict]) -> list[dict]:
    rows = []
    for r in evt:
        if "error" in r:
            rows.append({k: r.get(k) for k in ("case", "res", "method")} | {"error": True})
            continue
        tr = r["trace"]
        rows.append({
            "case": r["case"], "res": r["res"], "method": label(r),
            "n_pixels": r["n_pixels"], "compile_s": r["compile_s"],
            "t_1pct": time_to(tr, 1e-2), "t_01pct": time_to(tr, 1e-3),
            "final_err": final_err(tr), "best_err": min(x["max_rel_err"] for x in tr),
            "steps": tr[-1]["step"], "trace_s": tr[-1]["time_s"],
            "image_rmse": tr[-1].get("image_rmse"), "peak_rss_mb": r.get("peak_rss_mb"),
            "fit_warm_s": r.get("fit_warm_s"), "fit_cold_s": r.get("fit_cold_s"),
            "fit_warm_defaults_s": r.get("fit_warm_defaults_s"),
            "product_compile_s": r.get("compile_s") if r["method"] not in ("scipy", "mitsuba")
            else None,
        })
    return rows


def speed_ratios(evt: list[dict], case: str, res: int) -> list[dict]:
    """Time of each baseline / time of LM to reach the same error (same run)."""
    by = {label(r): r for r in evt
          if r.get("case") == case and r.get("res") == res and "error" not in r}
    lm = by.get("lm")
    out = []
    if lm is None:
        return out
    for name, r in by.items():
        if r["method"] not in ("scipy", "mitsuba"):
            continue
        # The baseline's own level: the error it stays below over its last fifth
        # (Adam with Monte Carlo gradients fluctuates around its plateau).
        tail = r["trace"][-max(1, len(r["trace"]) // 5):]
        best = 1.05 * max(x["max_rel_err"] for x in tail)  # 5 % slack: both may sit on one floor
        levels = sorted({*LEVELS, best}, reverse=True)
        for level in levels:
            tb, tl = time_to(r["trace"], level), time_to(lm["trace"], level)
            out.append({"baseline": name, "level": level,
                        "baseline_s": tb, "lm_s": tl,
                        "ratio": (tb / tl) if (tb is not None and tl) else None,
                        "baseline_total_s": r["trace"][-1]["time_s"] if r["trace"] else None,
                        "baseline_best": level == best})
    return out


# --------------------------------------------------------------------------- outputs


def write_csv(path, evt):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["case", "res", "method", "spp", "step", "time_s", "max_rel_err",
                    "image_rmse", "coordinate", "value", "truth", "abs_err", "rel_err"])
        for r in evt:
            if "error" in r:
                continue
            for row in r["trace"]:
                for coord, (v, t, a, rel) in row["errors"].items():
                    w.writerow([r["case"], r["res"], r["method"], r.get("spp", ""), row["step"],
                                f"{row['time_s']:.6g}", f"{row['max_rel_err']:.6g}",
                                "" if row.get("image_rmse") is None
                                else f"{row['image_rmse']:.6g}",
                                coord, f"{v:.10g}", f"{t:.10g}", f"{a:.4g}", f"{rel:.4g}"])


def plot(path, evt, case, resolutions):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res_list = [r for r in resolutions if any(e.get("res") == r and e.get("case") == case
                                              for e in evt)]
    fig, axes = plt.subplots(1, len(res_list), figsize=(6 * len(res_list), 4.5), squeeze=False)
    for ax, res in zip(axes[0], res_list):
        for r in evt:
            if r.get("case") != case or r.get("res") != res or "error" in r:
                continue
            tr = [x for x in r["trace"] if x["time_s"] > 0]
            if not tr:
                continue
            ax.loglog([x["time_s"] for x in tr], [max(x["max_rel_err"], 1e-9) for x in tr],
                      label=label(r), marker="." if len(tr) < 40 else None)
        for level in LEVELS:
            ax.axhline(level, color="grey", lw=0.5, ls=":")
        ax.set_xlabel("run time, s (compile excluded)")
        ax.set_ylabel("max relative parameter error")
        ax.set_title(f"{case}, {res}x{res}, Mitsuba target")
        ax.legend(fontsize=8)
        ax.grid(True, which="both", lw=0.2)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def markdown(res: dict) -> str:
    L = []
    L.append(f"# benchmarks/run.py{' --quick' if res['quick'] else ''}: results")
    L.append("")
    L.append(f"Machine: {res['machine']}. Date: {res['date']}. Total {res['total_s']:.0f} s.")
    L.append("The CPU was shared with other jobs while this ran: absolute times are noisy; "
             "ratios measured in the same run are the robust figures.")
    L.append("")
    L.append("Relative error = max over parameter coordinates of |x - truth| / |truth| "
             "(truth from the Mitsuba case). Times exclude compilation (reported separately); "
             "time to an error level = first time after which the error stays below it. "
             "Image RMSE: JAX model at the method's parameters vs the target, fitted pixels.")
    L.append("")
    L.append("## Error vs time")
    L.append("")
    L.append("| case | res | method | compile s | to 1 % s | to 0.1 % s | final rel err | "
             "image RMSE | steps | peak RSS MB | fitter.fit warm s |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in res["summary"]:
        if r.get("error"):
            L.append(f"| {r['case']} | {r['res']} | {r['method']} | worker failed |||||||| ")
            continue
        L.append(f"| {r['case']} | {r['res']}² | {r['method']} | {_fmt(r['compile_s'])} | "
                 f"{_fmt(r['t_1pct'])} | {_fmt(r['t_01pct'])} | {_fmt(r['final_err'])} | "
                 f"{_fmt(r['image_rmse'])} | {r['steps']} | {_fmt(r['peak_rss_mb'])} | "
                 f"{_fmt(r['fit_warm_s'])} |")
    L.append("")
    L.append(f"## Speed ratio at equal error ({TARGET_CASE}, {TARGET_RES}²): "
             "baseline time / LM time")
    L.append("")
    L.append("| baseline | error level | baseline s | LM s | ratio |")
    L.append("|---|---|---|---|---|")
    for s in res["ratios"]:
        lvl = _fmt(s["level"]) + (" (baseline's final)" if s["baseline_best"] else "")
        L.append(f"| {s['baseline']} | {lvl} | {_fmt(s['baseline_s'])} | {_fmt(s['lm_s'])} | "
                 f"{_fmt(s['ratio'], '×')} |")
    L.append("")
    L.append("## Speed targets")
    L.append("")
    for line in res["targets"]:
        L.append(f"- {line}")
    sc = res.get("scaling") or {}
    if sc.get("lights"):
        L.append("")
        L.append("## Scaling")
        L.append("")
        L.append("LM fit (`fitter.fit`) vs pixel count (Mitsuba targets, from the runs above):")
        L.append("")
        L.append("| res | fitted pixels | compile s | fit warm s |")
        L.append("|---|---|---|---|")
        for r in res["summary"]:
            if r.get("method") == "lm" and r.get("case") == TARGET_CASE and not r.get("error"):
                L.append(f"| {r['res']}² | {r['n_pixels']} | {_fmt(r['product_compile_s'])} | "
                         f"{_fmt(r['fit_warm_s'])} |")
        L.append("")
        L.append(f"LM fit vs number of point lights ({sc['lights'][0]['res']}², target from the "
                 "JAX model):")
        L.append("")
        L.append("| lights | compile s | fit warm s | iterations | status |")
        L.append("|---|---|---|---|---|")
        for r in sc["lights"]:
            L.append(f"| {r['n_lights']} | {_fmt(r['compile_s'])} | {_fmt(r['fit_warm_s'])} | "
                     f"{r['iterations']} | {r['status']} |")
        b = sc.get("batch")
        if b:
            L.append("")
            batch = (f"`fit_batch`: {_fmt(b['batch_s'])} s ({b.get('batch_converged')} converged)"
                     if b.get("batch_s") is not None else "`fit_batch` not available")
            if b.get("vmap_s") is not None:
                batch += (f"; `fit_batch(batch=\"vmap\")`: {_fmt(b['vmap_s'])} s "
                          f"({b.get('vmap_converged')} converged)")
            L.append(f"Batch of {b['n']} targets at {b['res']}² (compiled): sequential "
                     f"`fit` {_fmt(b['sequential_s'])} s ({b['sequential_converged']} converged); "
                     f"{batch}.")
    st = res.get("stiff")
    if st:
        L.append("")
        L.append("## Stiff and extreme cases")
        L.append("")
        L.append("Outcomes (see benchmarks/stiff.py): recovered = converged, every parameter "
                 "identifiable and within tolerance "
                 "(5 % relative; for reflectances, sigma, eta at least 0.02 absolute); "
                 "reported = not converged / unidentifiable / error within "
                 "the stated uncertainty; confident_wrong = converged, |err| > 5 stderr and > tol; "
                 "nonfinite = NaN/Inf in parameters, gradients or covariance; "
                 "error = the fit raised "
                 "an exception.")
        L.append("")
        L.append("| dtype | recovered | reported | confident_wrong | nonfinite | error |")
        L.append("|---|---|---|---|---|---|")
        for dt, c in st["counts"].items():
            L.append(f"| {dt} | {c['recovered']} | {c['reported']} | {c['confident_wrong']} | "
                     f"{c['nonfinite']} | {c['error']} |")
        L.append("")
        dtypes = list(st["counts"])
        L.append("| case | " + " | ".join(f"{dt}: outcome (status; unidentifiable)"
                                          for dt in dtypes) + " |")
        L.append("|---|" + "---|" * len(dtypes))
        cells: dict = {}
        for r in st["rows"]:
            unid = ", ".join(r.get("unidentifiable") or [])
            cells.setdefault(r["case"], {})[r["dtype"]] = (
                f"**{r['outcome']}** ({r.get('status') or r.get('message', '')[:60]}"
                + (f"; {unid}" if unid else "") + ")")
        for case, by in cells.items():
            L.append(f"| {case} | " + " | ".join(by.get(dt, "") for dt in dtypes) + " |")
    L.append("")
    return "\n".join(L)


def speed_targets(summary, ratios) -> list[str]:
    out = []
    lm = next((r for r in summary if r.get("case") == TARGET_CASE and r.get("res") == TARGET_RES
               and r.get("method") == "lm" and not r.get("error")), None)
    if lm is None:
        return ["(no LM run at the target case)"]
    fw, pc = lm["fit_warm_s"], lm["product_compile_s"]
    out.append(f"fit once compiled, from the benchmark's start: {_fmt(fw)} s (target ≤ "
               f"{TARGET_FIT_S} s: {'met' if fw is not None and fw <= TARGET_FIT_S else 'NOT met'}; "
               f"ratio {_fmt(fw / TARGET_FIT_S if fw else None)} of the target)")
    fd = lm.get("fit_warm_defaults_s")
    if fd is not None:
        out.append(f"fit once compiled, from the lobe defaults (no start given): {_fmt(fd)} s "
                   f"(target ≤ {TARGET_FIT_S} s: {'met' if fd <= TARGET_FIT_S else 'NOT met'})")
    out.append(f"compile (first run, no persistent XLA cache): {_fmt(pc)} s (target ≤ "
               f"{TARGET_COMPILE_S} s: "
               f"{'met' if pc is not None and pc <= TARGET_COMPILE_S else 'NOT met'})")
    warm = next((r for r in summary if r.get("method") == "lm (warm XLA cache)"
                 and r.get("res") == TARGET_RES and not r.get("error")), None)
    if warm is not None:
        wc = warm["product_compile_s"]
        out.append(f"compile with a warm persistent XLA cache (a repeated run of the CLI): "
                   f"{_fmt(wc)} s (target ≤ {TARGET_COMPILE_S} s: "
                   f"{'met' if wc is not None and wc <= TARGET_COMPILE_S else 'NOT met'})")
    # Every Mitsuba setting at 1 % and 0.1 %; a level the baseline never reaches
    # gives a lower bound (its whole run / LM's time to that level).
    for base in sorted({s["baseline"] for s in ratios if s["baseline"].startswith("mitsuba")}):
        for level in LEVELS:
            s = next((s for s in ratios if s["baseline"] == base and s["level"] == level), None)
            if s is None or s["lm_s"] is None:
                continue
            if s["ratio"] is not None:
                txt = f"{_fmt(s['ratio'])}×"
                ok = s["ratio"] >= TARGET_VS_MITSUBA
            else:
                total = s.get("baseline_total_s")
                bound = total / s["lm_s"] if total else None
                txt = (f"> {_fmt(bound)}× (never reached in its run)" if bound
                       else "never reached")
                ok = bound is not None and bound >= TARGET_VS_MITSUBA
            verdict = ("met" if ok else "NOT met" if s["ratio"] is not None
                       else "not shown: a lower bound only, the run is too short")
            out.append(f"vs {base} at rel. error {_fmt(level)}: {txt} "
                       f"(target ≥ {TARGET_VS_MITSUBA:g}×: {verdict})")
            if s["ratio"] is not None and fw:  # what a user waits for: the whole call
                out.append(f"the whole compiled fitter.fit call ({_fmt(fw)} s, checks "
                           f"included) vs {base} at rel. error {_fmt(level)}: "
                           f"{_fmt(s['baseline_s'] / fw)}×")
    for name, goal in (("scipy", TARGET_VS_SCIPY), ("mitsuba", TARGET_VS_MITSUBA)):
        rs = [s for s in ratios if s["baseline"].startswith(name) and s["ratio"] is not None]
        if not rs:
            out.append(f"vs {name}: no common error level reached")
            continue
        s = min(rs, key=lambda s: s["level"])
        out.append(f"vs {s['baseline']} at rel. error {_fmt(s['level'])}: {_fmt(s['ratio'])}× "
                   f"faster (target ≥ {goal:g}×: {'met' if s['ratio'] >= goal else 'NOT met'})")
    return out


# --------------------------------------------------------------------------- main


def main(argv) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/run.py",
                                description=__doc__.split("\n\n")[0].replace("``", ""))
    p.add_argument("--quick", action="store_true", help="the small run (< 5 min on 2 cores)")
    p.add_argument("--out", default=os.path.join(HERE, "results"), help="output folder")
    p.add_argument("--skip", action="append", default=[], choices=["evt", "scaling", "stiff"],
                   help="skip a part (repeatable)")
    p.add_argument("--worker", nargs=3, metavar=("KIND", "SPEC", "OUT"), help=argparse.SUPPRESS)
    try:
        args = p.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2), already printed
        return 0 if exc.code == 0 else 2
    if args.worker:
        return worker(*args.worker)
    plan = QUICK if args.quick else FULL
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    t_all = time.perf_counter()
    results = {"quick": bool(args.quick), "machine": machine(),
               "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
               "evt": [], "scaling": None, "stiff": None}
    with tempfile.TemporaryDirectory(prefix="fitter-bench-") as tmp:
        if "evt" not in args.skip:
            for case, res, method, opts in plan["evt"]:
                log(f"[bench] {case} {res}x{res} {method} {opts or ''}")
                spec = {"case": case, "res": res, "method": method,
                        "target": make_target(case, res, tmp), **opts}
                target_lm = (case, res, method) == (TARGET_CASE, TARGET_RES, "lm")
                xla = os.path.join(tmp, "xla") if target_lm else ""
                r = spawn("evt", spec, tmp, log, cache=xla)
                results["evt"].append(r)
                if "trace" in r:
                    log(f"  final rel err {final_err(r['trace']):.3g} after "
                        f"{r['trace'][-1]['time_s']:.3g} s, compile {r['compile_s']:.3g} s, "
                        f"peak RSS {r['peak_rss_mb']:.0f} MB")
                if target_lm:  # the same fit again, with the persistent cache now filled
                    log("[bench] ... again with a warm persistent XLA cache")
                    again = spawn("evt", spec, tmp, log, cache=xla)
                    if "trace" in again:
                        again["method"] = "lm (warm XLA cache)"
                        results["evt"].append(again)
        if "scaling" not in args.skip:
            log(f"[bench] scaling {plan['scaling']}")
            results["scaling"] = spawn("scaling", plan["scaling"], tmp, log)
        if "stiff" not in args.skip:
            log(f"[bench] stiff cases {plan['stiff']}")
            results["stiff"] = spawn("stiff", plan["stiff"], tmp, log)
            if "counts" in results["stiff"]:
                log(f"  {results['stiff']['counts']}")
    results["summary"] = summarize(results["evt"])
    results["ratios"] = speed_ratios(results["evt"], TARGET_CASE, TARGET_RES)
    results["targets"] = speed_targets(results["summary"], results["ratios"])
    results["total_s"] = time.perf_counter() - t_all
    os.makedirs(args.out, exist_ok=True)
    write_csv(os.path.join(args.out, "samples.csv"), results["evt"])
    with open(os.path.join(args.out, "results.json"), "w") as fh:
        json.dump(results, fh, indent=1, default=float)
    with open(os.path.join(args.out, "results.md"), "w") as fh:
        fh.write(markdown(results))
    if results["evt"]:
        plot(os.path.join(args.out, "error_vs_time.png"), results["evt"], TARGET_CASE,
             sorted({r["res"] for r in results["evt"]}))
    for line in results["targets"]:
        print(line)
    print(f"wrote {args.out}/results.md, results.json, samples.csv, error_vs_time.png "
          f"({results['total_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

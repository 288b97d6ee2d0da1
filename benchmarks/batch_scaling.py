"""``fitter batch`` vs sequential ``fitter fit``, and batch throughput vs workers.

Sixteen jobs (by default) made from ``configs/quickstart.toml`` (128², 4x4
supersampling, two point lights, lambert + torrance_sparrow): each has its own
``[material.truth]`` (drawn with a fixed seed) and a target rendered from it
by ``fitter render``. Timed, each as the user runs it, with validation off:

* ``sequential``: one ``fitter fit CONFIG --no-validate`` process per job;
* ``batch``: one ``fitter batch CONFIGS --no-validate --workers N`` for each N
  in ``--workers`` (a new batch folder each time, so nothing is resumed),
  ``--repeat`` rounds, the median reported (the machine may be shared).

Everything uses one persistent compilation cache (``FITTER_CACHE_DIR``),
warmed by an untimed ``fitter fit`` first: the case of a user who has run
this scene before. The batch results are checked against the sequential ones
(largest relative difference of any parameter coordinate).

    python benchmarks/batch_scaling.py                 # 16 jobs, workers 1 and 2
    python benchmarks/batch_scaling.py --jobs 4 --workers 1 2 4 --repeat 1 --out /tmp/bs

Writes ``batch_scaling.json`` and ``batch_scaling.png`` (jobs/s against
workers, the sequential rate as a line) to ``--out`` (default
``benchmarks/results/``).
"""

from __future__ import annotations

import argparse
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
FITTER = [sys.executable, "-m", "fitter"]


def make_jobs(folder: str, n: int, seed: int = 0) -> list[str]:
    """``n`` configs from quickstart with their own truths; targets by ``fitter render``."""
    import tomllib

    from fitter.config import dumps_toml

    with open(os.path.join(ROOT, "configs", "quickstart.toml"), "rb") as fh:
        base = tomllib.load(fh)
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(n):
        data = json.loads(json.dumps(base))
        data["material"]["truth"] = {
            "lambert.rho_d": [round(float(x), 4) for x in rng.uniform(0.2, 0.8, 3)],
            "torrance_sparrow.m": round(float(rng.uniform(0.1, 0.3)), 4),
            "torrance_sparrow.eta": round(float(rng.uniform(1.3, 1.7)), 4)}
        data["fit"]["target"] = f"job{i:02d}.exr"
        path = os.path.join(folder, f"job{i:02d}.toml")
        with open(path, "w") as fh:
            fh.write(dumps_toml(data))
        subprocess.run([*FITTER, "render", path, "--out", os.path.join(folder, f"job{i:02d}.exr"),
                        "--quiet"], check=True)
        paths.append(path)
    return paths


def params_of(result_json: str) -> dict[str, np.ndarray]:
    with open(result_json) as fh:
        p = json.load(fh)["params"]
    return {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in p.items()
            if not isinstance(v, str)}


def max_rel_diff(a: dict, b: dict) -> float:
    worst = 0.0
    for k in a:
        d = np.abs(a[k] - b[k]) / np.maximum(np.abs(a[k]), 1e-300)
        worst = max(worst, float(d.max()))
    return worst


def timed(cmd: list[str]) -> tuple[float, int]:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if proc.returncode not in (0, 3):
        print(f"{' '.join(cmd[2:4])}: exit {proc.returncode}\n{proc.stderr[-3000:]}",
              file=sys.stderr)
    return time.perf_counter() - t0, proc.returncode


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=16)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3, help="batch runs per worker count "
                                                          "(the median is reported)")
    ap.add_argument("--out", default=os.path.join(HERE, "results"))
    args = ap.parse_args(argv)
    work = tempfile.mkdtemp(prefix="batch_scaling-")
    os.environ["FITTER_CACHE_DIR"] = os.path.join(work, "cache")
    cfg = os.path.join(work, "configs")
    os.makedirs(cfg)
    paths = make_jobs(cfg, args.jobs)
    timed([*FITTER, "fit", paths[0], "--no-validate", "--quiet",  # warm the cache
           "--out", os.path.join(work, "warm")])

    t_seq = 0.0
    for p in paths:
        t, rc = timed([*FITTER, "fit", p, "--no-validate", "--quiet",
                       "--out", os.path.join(work, "seq", os.path.basename(p)[:-5])])
        t_seq += t
        assert rc in (0, 3), f"fitter fit {p}: exit {rc}"
    print(f"sequential: {args.jobs} x fitter fit: {t_seq:.1f} s", flush=True)

    walls: dict[int, list[float]] = {n: [] for n in args.workers}
    diff = 0.0
    for r in range(args.repeat):  # rounds interleave the worker counts (a shared machine)
        for n in args.workers:
            out = os.path.join(work, f"batch-{n}-{r}")  # new folder: nothing is resumed
            t, rc = timed([*FITTER, "batch", *paths, "--no-validate", "--quiet",
                           "--workers", str(n), "--out", out])
            assert rc in (0, 3), f"fitter batch: exit {rc}"
            walls[n].append(t)
            diff = max(diff, *(max_rel_diff(
                params_of(os.path.join(work, "seq", f"job{i:02d}", "result.json")),
                params_of(os.path.join(out, f"job{i:02d}", "result.json")))
                for i in range(args.jobs)))
            print(f"round {r}: batch --workers {n}: {t:.1f} s", flush=True)
    runs = []
    for n in args.workers:
        t = float(np.median(walls[n]))
        runs.append({"workers": n, "wall_s": t, "wall_s_all": walls[n],
                     "jobs_per_s": args.jobs / t, "vs_sequential": t / t_seq})
        print(f"batch --workers {n}: median {t:.1f} s ({args.jobs / t:.2f} jobs/s, "
              f"{t / t_seq:.2f} x sequential)", flush=True)
    print(f"largest relative difference batch vs fitter fit: {diff:.1e}")

    record = {"machine": f"{platform.processor() or platform.machine()}, "
                         f"{os.cpu_count()} cores", "date": time.strftime("%Y-%m-%d"),
              "jobs": args.jobs, "case": "quickstart 128^2, 4x4 supersampling, --no-validate",
              "sequential_s": t_seq, "sequential_jobs_per_s": args.jobs / t_seq, "batch": runs,
              "max_rel_diff_vs_fit": diff,
              "load_average": os.getloadavg()}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "batch_scaling.json"), "w") as fh:
        json.dump(record, fh, indent=2)
        fh.write("\n")
    plot(record, os.path.join(args.out, "batch_scaling.png"))
    return 0


def plot(record: dict, path: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 3.6), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    w = [r["workers"] for r in record["batch"]]
    ax.plot(w, [r["jobs_per_s"] for r in record["batch"]], "o-", label="fitter batch")
    ax.axhline(record["sequential_jobs_per_s"], color="0.5", ls="--",
               label="sequential fitter fit")
    ax.set_xticks(w)
    ax.set_xlabel("workers (processes, 1 thread each)")
    ax.set_ylabel("jobs / s")
    ax.set_ylim(bottom=0)
    for r in record["batch"]:
        ax.plot([r["workers"]] * len(r["wall_s_all"]),
                [record["jobs"] / t for t in r["wall_s_all"]], ".", color="C0", alpha=0.4)
    load = record.get("load_average", [float("nan")])[0]
    ax.set_title(f"{record['jobs']} jobs, {record['case']}\n{record['machine']}, "
                 f"load average {load:.1f} at the end", fontsize=8)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())

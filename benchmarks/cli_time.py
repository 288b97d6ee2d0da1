"""Wall time of a warm, repeated `fitter fit` (what a user waits for), with the
CLI's stage times, side by side for this checkout and (``--before REF``) an
older commit, interleaved run by run so that both see the same machine load.

    python benchmarks/cli_time.py                      # quickstart, --no-validate and validated
    python benchmarks/cli_time.py --before 6321d3c --repeat 7
    python benchmarks/cli_time.py --config configs/dielectric.toml --no-validated

Each tree's ``fitter`` sources are byte-compiled first (``compileall``: what an
installed package or any earlier run has; an environment with
``PYTHONDONTWRITEBYTECODE`` set would otherwise compile them on every run,
~0.08 s), each (tree, mode) is run once untimed (fills the persistent
compilation cache and the exported traces), then ``--repeat`` times; the table gives the
median and the minimum of the wall time (process start to exit, `os.wait4`),
the median of each stage the CLI prints, and the peak RSS. ``--before`` checks
the commit out with ``git worktree`` in a temporary folder and runs it with
the same interpreter (``PYTHONPATH``); each tree has its own cache folder
(``FITTER_CACHE_DIR``, filled by the untimed run).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

from _machine import host

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STAGES = (("fit", r"^fitting .*?: ([\d.]+) s"), ("render", r"^rendering the fit: ([\d.]+) s"),
          ("validate", r"^validating .*?: ([\d.]+) s"), ("outputs", r"^writing outputs: ([\d.]+) s"))


def run_once(tree: str, config: str, validate: bool, out: str, cache: str) -> dict:
    cmd = [sys.executable, "-m", "fitter", "fit", os.path.join(tree, config), "--out", out]
    if not validate:
        cmd.append("--no-validate")
    env = {**os.environ, "PYTHONPATH": tree, "FITTER_CACHE_DIR": cache}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    text = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) not in (0, 3):
        raise SystemExit(f"{' '.join(cmd)} failed:\n{text[-2000:]}")
    rec = {"wall": wall, "rss_mb": usage.ru_maxrss / 1024.0}
    for key, pat in STAGES:
        m = re.search(pat, text, re.M)
        if m:
            rec[key] = float(m.group(1))
    return rec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="configs/quickstart.toml")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--before", help="git ref to compare with (run from a worktree)")
    ap.add_argument("--no-validated", action="store_true", help="skip the validated runs")
    args = ap.parse_args(argv)

    trees = [("this checkout", ROOT)]
    tmp = tempfile.mkdtemp(prefix="fitter-cli-time-")
    if args.before:
        wt = os.path.join(tmp, "before")
        subprocess.run(["git", "-C", ROOT, "worktree", "add", "--detach", "-q", wt, args.before],
                       check=True)
        trees.append((f"before ({args.before})", wt))
    for _, tree in trees:
        subprocess.run([sys.executable, "-m", "compileall", "-q", os.path.join(tree, "fitter")],
                       check=True)
    # Each tree its own cache folder: a tree removes the files other sources
    # made (``compilation_cache.remove_stale``), so sharing one, each run of
    # one tree would find the other's and none of its own.
    cache = {name: os.path.join(tmp, f"cache-{i}") for i, (name, _) in enumerate(trees)}
    modes = [False] + ([] if args.no_validated else [True])
    records: dict = {}
    try:
        for validate in modes:
            for name, tree in trees:  # untimed: warm caches
                run_once(tree, args.config, validate, os.path.join(tmp, "out"), cache[name])
            for _ in range(args.repeat):
                for name, tree in trees:
                    records.setdefault((name, validate), []).append(
                        run_once(tree, args.config, validate, os.path.join(tmp, "out"),
                                 cache[name]))
    finally:
        if args.before:
            subprocess.run(["git", "-C", ROOT, "worktree", "remove", "--force", wt], check=False)
    print(f"`fitter fit {args.config}`, warm (second and later runs), {args.repeat} runs each, "
          f"interleaved; {host()} (1 / 5 min) at the end\n")
    print("| tree | validation | wall median s | wall min s | fit s | render s | validate s "
          "| outputs s | other s | peak RSS MB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (name, validate), recs in records.items():
        med = lambda k: statistics.median(r.get(k, 0.0) for r in recs)  # noqa: E731
        wall = med("wall")
        other = wall - sum(med(k) for k, _ in STAGES)
        print(f"| {name} | {'yes' if validate else 'no'} | {wall:.2f} | "
              f"{min(r['wall'] for r in recs):.2f} | {med('fit'):.2f} | {med('render'):.2f} | "
              f"{med('validate'):.2f} | {med('outputs'):.2f} | {other:.2f} | "
              f"{med('rss_mb'):.0f} |")
    print("\n`other`: interpreter start, imports before the fit (jax), config and target "
          "reading, the summary table.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

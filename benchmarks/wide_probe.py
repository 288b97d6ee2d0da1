"""Probes wider than the shipped one: accuracy and cost per light-map width.

The shipped probe's scene (``fitter.mitsuba.synth.make_probe``: sky, ground,
window, a ~3 deg sun at ~300x the sky) made ``--width`` wide, a shipped env
case's scene and material under it, rendered by Mitsuba from the whole map
(path, MIS, max_depth 2, ``--spp``; cached under ``benchmarks/results/tmp/``),
then fitted in a fresh process per ``envlight.LIGHT_WIDTH`` (the width of the
map's pyramid level the opaque lobes are lit from; 0: the map itself). Prints,
per case and light width, each fitted parameter against the truth in stated
errors, the first fit's wall time and the process's peak RSS.

    python benchmarks/wide_probe.py [--width 2048] [--light-widths 256,512,0]
        [--cases env_phong,env_plastic] [--spp 4096]

``envlight.LIGHT_WIDTH`` (512) and its sun cells were picked from this
(``benchmarks/README.md``, "Wide probes").
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)
CACHE = os.path.join(ROOT, "benchmarks", "results", "tmp")

from _machine import host  # noqa: E402

#: The child's fit: the job from JSON, LIGHT_WIDTH set, one fitter.fit.
CHILD = """
import json, os, resource, sys, time
sys.path.insert(0, {root!r})
os.environ["FITTER_CACHE_DIR"] = ""
from fitter import config, envlight
from fitter.imageio import read_image
import fitter
spec = json.loads({spec!r})
if {light_width}:
    envlight.LIGHT_WIDTH = {light_width}
else:  # the map itself: wider than any map
    envlight.LIGHT_WIDTH = 1 << 30
job = config.job_from_dict(spec, base_dir={folder!r})
target = read_image({target!r})
t0 = time.perf_counter()
res = fitter.fit(target, job.scene, job.material, fixed=job.fixed)
seconds = time.perf_counter() - t0
plain = lambda v: getattr(v, "tolist", lambda: v)()
print(json.dumps({{"seconds": seconds, "status": res.status,
                   "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
                   "params": {{k: plain(res.params[k]) for k in res.free}},
                   "stderr": {{k: plain(res.stderr[k]) for k in res.free}}}}))
"""


def _target(case: str, width: int, spp: int) -> tuple[dict, str, dict]:
    """(the job as a dict, the Mitsuba target's path, the truth) of ``case`` under
    the probe ``width`` wide, made once and cached."""
    from fitter import config
    from fitter.cases import CASES
    from fitter.mitsuba.synth import make_probe, write_case
    from fitter.pipeline import truth_params

    os.makedirs(CACHE, exist_ok=True)
    probe = os.path.join(CACHE, f"probe_{width}.exr")
    if not os.path.exists(probe):  # (one point a texel beyond 1024: 8 x 8 took 3 GB at 2048)
        make_probe(probe, width, width // 2, sub=8 if width <= 1024 else 1)
    spec = json.loads(json.dumps(CASES[case]))
    spec["scene"]["environment"]["file"] = probe
    spec = {"scene": spec["scene"], "material": spec["material"]}
    job = config.job_from_dict(spec, base_dir=CACHE)
    truth = truth_params(job)
    folder = os.path.join(CACHE, f"wide_{case}_{width}_{spp}")
    if not os.path.exists(os.path.join(folder, "target.exr")):
        write_case(folder, job.scene, job.material, truth, spp=spp, seed=0)
    return spec, os.path.join(folder, "target.exr"), truth


def _fit(spec: dict, target: str, light_width: int) -> dict:
    code = CHILD.format(root=ROOT, spec=json.dumps(spec), light_width=light_width,
                        folder=CACHE, target=target)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"the fit at light width {light_width} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=2048)
    ap.add_argument("--light-widths", default="256,512,0", help="0: the map itself")
    ap.add_argument("--cases", default="env_phong,env_plastic")
    ap.add_argument("--spp", type=int, default=4096)
    args = ap.parse_args(argv)
    print(f"Probe {args.width} x {args.width // 2}, Mitsuba {args.spp} spp; {host()}\n")
    print("| case | light width | parameter | fitted | truth | off / stated | first fit s "
          "| peak RSS GB |")
    print("|---|---|---|---|---|---|---|---|")
    for case in args.cases.split(","):
        spec, target, truth = _target(case, args.width, args.spp)
        for lw in (int(w) for w in args.light_widths.split(",")):
            got = _fit(spec, target, lw)
            for key, value in got["params"].items():
                v, t = np.asarray(value, float), np.asarray(truth[key], float)
                z = np.max(np.abs(v - t) / np.asarray(got["stderr"][key], float))
                print(f"| {case} | {lw or 'the map'} | {key} | {np.round(v, 5).tolist()} | "
                      f"{t.tolist()} | {z:.2f} | {got['seconds']:.1f} | "
                      f"{got['peak'] / 1e9:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The on-disk trace cache (``fitter.fit._cache``) repairs itself: a corrupt
entry is replaced by the next run, not re-traced by every later one."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

from jax import export

from fitter.fit import _cache  # noqa: F401 (registers fitter's pytrees for deserialize)

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: One small fit with the compilation cache (and so the trace cache) in argv[1].
FIT = """
import sys
import jax
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
import numpy as np
import fitter
scene = fitter.Scene(width=16, height=16, supersampling=1,
                     lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),))
target = np.asarray(fitter.render({"lambert.rho_d": 0.5}, scene))
assert fitter.fit(target, scene, "lambert").status == "converged"
print("loaded:", " ".join(m for m in ("optimistix", "lineax", "equinox", "optax")
                          if m in sys.modules))
"""


def run_fit(folder) -> set[str]:
    """Run ``FIT``; the solver libraries it imported."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", FIT, str(folder)], check=True, env=env,
                          cwd=ROOT, timeout=300, capture_output=True, text=True)
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("loaded:")][-1]
    return set(line.split()[1:])


def test_a_corrupt_cache_entry_is_rewritten_by_the_next_run(tmp_path):
    run_fit(tmp_path)
    entries = sorted(tmp_path.glob("fitter-*.jaxexport"))
    assert entries  # the solve and the Jacobian check were exported
    for path in entries:
        path.write_bytes(b"not a flatbuffer")  # e.g. a disk that filled up mid-write
    run_fit(tmp_path)
    for path in entries:
        data = path.read_bytes()
        assert data != b"not a flatbuffer", f"{path.name} was not rewritten"
        export.deserialize(bytearray(data))  # whole and readable again


def test_a_repeated_fit_loads_its_trace_without_the_solver_libraries(tmp_path):
    # optimistix, lineax, equinox and jaxtyping take ~0.5 s to import; a fit
    # whose trace and outcome table are on disk must not need them.
    first = run_fit(tmp_path)
    assert "optimistix" in first  # traced: the solver library was needed
    assert sorted(tmp_path.glob("fitter-outcomes-*.json"))
    assert run_fit(tmp_path) == set()
    for path in tmp_path.glob("fitter-outcomes-*.json"):
        path.write_text("{not json")  # a broken table: read from optimistix again
    assert "optimistix" in run_fit(tmp_path)
    assert run_fit(tmp_path) == set()

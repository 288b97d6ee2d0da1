"""The on-disk trace cache (``fitter.fit._cache``) repairs itself: a corrupt
entry is replaced by the next run, not re-traced by every later one."""

from __future__ import annotations

import json
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
import json
import numpy as np
import fitter
from fitter.fit import _cache
traced = []
_export = _cache.export.export
def counted(*args, **kwargs):
    traced.append(1)
    return _export(*args, **kwargs)
_cache.export.export = counted
scene = fitter.Scene(width=16, height=16, supersampling=1,
                     lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),))
target = np.asarray(fitter.render({"lambert.rho_d": 0.5}, scene))
target = target + np.random.default_rng(0).normal(0.0, 0.01, target.shape)  # stderr > 0
res = fitter.fit(target, scene, "lambert")
assert res.status == "converged"
print("loaded:", " ".join(m for m in ("optimistix", "lineax", "equinox", "optax")
                          if m in sys.modules))
print("traced:", len(traced))
print("result:", json.dumps({k: res.to_dict()[k] for k in ("params", "stderr", "stderr_disc")}))
"""


def run_fit_lines(folder) -> dict[str, str]:
    """Run ``FIT``; its ``name: value`` lines."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", FIT, str(folder)], check=True, env=env,
                          cwd=ROOT, timeout=300, capture_output=True, text=True)
    return dict(ln.split(": ", 1) if ": " in ln else (ln.rstrip(":"), "")
                for ln in proc.stdout.splitlines() if ln.split(":")[0] in
                ("loaded", "traced", "result"))


def run_fit(folder) -> set[str]:
    """Run ``FIT``; the solver libraries it imported."""
    return set(run_fit_lines(folder)["loaded"].split())


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


def test_a_repeated_fit_traces_nothing_and_states_the_same_errors(tmp_path):
    # Every compiled step of a fit -- the solve, the cost profile and the
    # discretisation's finer render (no start check: the solution shows no zero
    # column, ``_drivers._checked_after``) -- is exported on the first run and
    # loaded by the next, which must give the same values and errors.
    first = run_fit_lines(tmp_path)
    assert int(first["traced"]) >= 3
    again = run_fit_lines(tmp_path)
    assert int(again["traced"]) == 0
    assert json.loads(again["result"]) == json.loads(first["result"])
    disc = json.loads(first["result"])["stderr_disc"]["lambert.rho_d"]
    assert min(disc) > 0  # the finer render ran (16^2, 1 sample: its error is stated)


def test_a_new_trace_removes_the_traces_other_sources_left(tmp_path):
    """Traces tagged by other sources but the ones that wrote last, and those of
    the names before the tag, are removed when this run stores its own; a file
    fitter did not write stays. Reference: the folder's listing."""
    import os

    stale = [tmp_path / f"fitter-trace-{'0' * 16}-{'a' * 32}.jaxexport",
             tmp_path / f"fitter-{'b' * 32}.jaxexport"]
    kept = [tmp_path / "fitter-notes.jaxexport",
            tmp_path / f"fitter-trace-{'1' * 16}-{'a' * 32}.jaxexport"]  # wrote last
    for path in stale + kept:
        path.write_bytes(b"x")
    os.utime(stale[0], (1000, 1000))
    os.utime(kept[1], (2000, 2000))
    run_fit(tmp_path)
    assert not any(path.exists() for path in stale) and all(path.exists() for path in kept)
    assert sorted(tmp_path.glob("fitter-trace-*.jaxexport"))  # this run's own


#: ``FIT`` under a sky with a one-texel sun (an env-lit fit: sun cells in its data).
FIT_SUN = FIT.replace(
    """scene = fitter.Scene(width=16, height=16, supersampling=1,
                     lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),))""",
    f"""sys.path.insert(0, {str(ROOT / "tests")!r})
from skies import one_texel_sun
scene = one_texel_sun(sys.argv[1] + "/../sky.exr", 20, 40, [0.3, 0.4, 0.6], [0.5, 0.5, 0.6],
                      [0.15, 0.12, 0.1], [2000.0, 1900.0, 1700.0], size=24)""")


def test_an_env_lit_fit_with_a_sun_traces_nothing_when_repeated(tmp_path):
    # The sun's cells (``SunCells``) are part of the solve's data: its trace must
    # serialise them too, or every repeated env-lit fit traces its solve again (~1 s).
    assert FIT_SUN != FIT
    cache = tmp_path / "cache"
    cache.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def lines():
        proc = subprocess.run([sys.executable, "-c", FIT_SUN, str(cache)], check=True,
                              env=env, cwd=ROOT, timeout=300, capture_output=True, text=True)
        return dict(ln.split(": ", 1) for ln in proc.stdout.splitlines() if ": " in ln)

    first = lines()
    assert int(first["traced"]) >= 3
    again = lines()
    assert int(again["traced"]) == 0
    assert json.loads(again["result"]) == json.loads(first["result"])

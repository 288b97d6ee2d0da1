"""Scene caches bounded by bytes (``fitter._keep``): fits of many scenes in one
process do not pile up their arrays (five 256^2 env-lit scenes held 12.5 GB
with ``functools.lru_cache(8)``; benchmarks/memory_model.py --many)."""

from __future__ import annotations

import importlib

import numpy as np

import fitter
from fitter._keep import hold, nbytes, recent
from fitter.fit import _setup

render_mod = importlib.import_module("fitter.render")


def _cache(max_bytes=100):
    made = []

    @recent(max_items=4, max_bytes=max_bytes)
    def make(name, size):
        made.append(name)
        return {"a": np.zeros(size, np.uint8), "b": (np.zeros(size, np.uint8),)}

    return make, made


def test_nbytes_counts_every_array_once():
    a = np.zeros(10)
    assert nbytes({"x": a, "y": [a, np.zeros(3, np.float32)], "z": "text"}) == 80 + 12


def test_hold_keeps_insertion_order_and_its_bounds():
    kept: dict = {}
    for name in "abc":
        hold(kept, name, np.zeros(10, np.uint8), most=2)
    assert list(kept) == ["b", "c"]  # the oldest went
    hold(kept, "b", kept["b"], most=2)
    assert list(kept) == ["c", "b"]  # held again: the newest
    hold(kept, "d", np.zeros(100, np.uint8), most=5, max_bytes=50)
    assert list(kept) == ["d"]  # over the bytes: all but the newest
    hold(kept, "e", np.zeros(100, np.uint8), most=5, max_bytes=50, protect=0)
    assert kept == {}  # protect=0: the newest too (the finer geometries' rule)


def test_the_newest_value_stays_and_older_ones_only_within_the_bytes():
    make, made = _cache()
    make("A", 500)
    make("Ac", 5)  # small: A, the one before it, stays (a fit's coarse problem)
    assert make.cache_info() == (2, 1010)
    make("A", 500), make("Ac", 5)
    assert made == ["A", "Ac"]  # both were hits
    make("B", 500)  # large: A went before B was made, Ac after
    assert make.cache_info() == (1, 1000)
    make("Bc", 5)
    assert make.cache_info() == (2, 1010) and made == ["A", "Ac", "B", "Bc"]
    for i in range(6):  # small ones: the count bounds them
        make(f"s{i}", 1)
    assert make.cache_info() == (4, 8)
    make.cache_clear()
    assert make.cache_info() == (0, 0)


def test_rendering_many_scenes_keeps_only_the_newest_large_one(monkeypatch):
    # With a bound of one byte every scene is large: after three scenes only the
    # last one's arrays are kept (with lru_cache all three were).
    for f in (render_mod._prepare, render_mod.cached_renderer, _setup._fitted_geometry):
        monkeypatch.setattr(f, "max_bytes", 1)
        f.cache_clear()
    light = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),)
    images = [fitter.render({"lambert.rho_d": 0.5},
                            fitter.Scene(width=w, height=w, supersampling=1, lights=light))
              for w in (8, 10, 12)]
    assert [np.shape(i)[0] for i in images] == [8, 10, 12]
    assert render_mod._prepare.cache_info()[0] == 1
    assert render_mod.cached_renderer.cache_info()[0] == 1
    built = []
    build = render_mod.build_geometry
    monkeypatch.setattr(render_mod, "build_geometry", lambda *a, **k: built.append(1)
                        or build(*a, **k))
    scene = fitter.Scene(width=12, height=12, supersampling=1, lights=light)
    again = fitter.render({"lambert.rho_d": 0.5}, scene)  # the newest: reused
    np.testing.assert_array_equal(np.asarray(again), np.asarray(images[-1]))
    assert not built and render_mod._prepare.cache_info()[0] == 1
    fitter.render({"lambert.rho_d": 0.5}, scene.replace(width=8, height=8))  # dropped: made
    assert built == [1]


def test_a_batch_worker_drops_the_last_scene_before_a_job_of_another(monkeypatch):
    # One job's arrays held beside the next job's (another scene) could exceed a
    # worker's memory limit sized for one job; a series of one scene keeps them.
    from fitter import _keep
    from fitter.batch import _task
    from fitter.config import FitOptions, Job

    light = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),)
    fitter.render({"lambert.rho_d": 0.5}, fitter.Scene(width=8, height=8, lights=light))
    assert render_mod._prepare.cache_info()[0] >= 1
    released, real = [], _keep.release
    monkeypatch.setattr(_keep, "release", lambda: released.append(1) or real())
    monkeypatch.setattr(_task, "_LAST_SCENE", [None])

    def job(width):
        return Job(path="j.toml", base_dir="/tmp", scene=fitter.Scene(width=width, lights=light),
                   material=None, truth={}, init={}, fixed={}, fit=FitOptions())

    for width in (8, 8, 16, 16):
        _task._scene_of(job(width))
    assert released == [1]  # once: before the first job of the 16-wide scene
    assert render_mod._prepare.cache_info()[0] == 0  # every scene cache emptied


def test_derived_values_kept_per_owner_without_keeping_it(monkeypatch):
    """``derived``: a value made once per owner (its anchor array) and name,
    read-only, for the last ``KEEP_DERIVED`` owners; an owner that is gone is
    not kept alive by it (a weak reference) and its values go with it."""
    import gc
    import weakref

    from fitter import _keep

    monkeypatch.setattr(_keep, "_DERIVED", [])
    made = []

    def value(tag):
        made.append(tag)
        return np.full(3, float(len(made)))

    owners = [np.zeros(2) for _ in range(_keep.KEEP_DERIVED + 1)]
    first = _keep.derived(owners[0], "v", lambda: value(0))
    assert _keep.derived(owners[0], "v", lambda: value(1)) is first and made == [0]
    assert not first.flags.writeable
    _keep.derived(owners[0], "w", lambda: value(2))  # another name: made
    for k, owner in enumerate(owners[1:], 1):
        _keep.derived(owner, "v", lambda k=k: value(10 + k))
    assert len(_keep._DERIVED) == _keep.KEEP_DERIVED  # the oldest owner's values went
    _keep.derived(owners[0], "v", lambda: value(99))
    assert made[-1] == 99
    gone = weakref.ref(owners[-1])
    del owners[-1], owner
    gc.collect()
    assert gone() is None  # not kept alive
    _keep.release()
    assert _keep._DERIVED == []

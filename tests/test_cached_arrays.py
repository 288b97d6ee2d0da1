"""``fitter.compilation_cache.cached_arrays``: the sky stencil's scene-independent
tables (``skystencil._tables``, ``skystencil.node_geometry``) kept beside the
compilation cache. A later process loads exactly what an earlier one made; a
corrupt file is made again and replaced; without a cache folder nothing is
written. The reference is the computation itself (``make``), run in the test."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import fitter
from fitter import compilation_cache, skystencil


@pytest.fixture
def cache_folder(tmp_path):
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    yield tmp_path
    jax.config.update("jax_compilation_cache_dir", before)


@pytest.fixture
def no_cache_folder():
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", None)
    yield
    jax.config.update("jax_compilation_cache_dir", before)


def test_a_later_call_loads_the_same_arrays_without_making_them(cache_folder):
    made = []

    def make():
        made.append(1)
        return np.arange(6.0).reshape(2, 3), np.array([1, 2], np.int32)

    first = compilation_cache.cached_arrays("probe", "k", make)
    again = compilation_cache.cached_arrays("probe", "k", make)
    assert len(made) == 1
    assert len(list(cache_folder.glob("fitter-probe-*.npz"))) == 1
    for a, b in zip(first, again):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    compilation_cache.cached_arrays("probe", "other key", make)
    assert len(made) == 2  # another key is another file


def test_a_corrupt_file_is_made_again_and_replaced(cache_folder):
    make = lambda: (np.linspace(0.0, 1.0, 5),)  # noqa: E731
    compilation_cache.cached_arrays("probe", "k", make)
    (path,) = cache_folder.glob("fitter-probe-*.npz")
    path.write_bytes(b"not an npz file")
    (got,) = compilation_cache.cached_arrays("probe", "k", make)
    assert np.array_equal(got, make()[0])
    (again,) = compilation_cache.cached_arrays("probe", "k", lambda: pytest.fail("made again"))
    assert np.array_equal(again, make()[0])


def test_without_a_cache_folder_nothing_is_written(monkeypatch, no_cache_folder):
    monkeypatch.setattr(compilation_cache, "store_atomically",
                        lambda *a: pytest.fail("a file was written"))
    made = []
    for _ in range(2):
        compilation_cache.cached_arrays("probe", "k", lambda: made.append(1) or (np.ones(2),))
    assert len(made) == 2  # made each time, never loaded


def test_the_stencil_tables_from_disk_equal_the_computed_ones(cache_folder, monkeypatch):
    nodes, sub = 9, (2, 4)  # a small node count: a file of its own
    fresh_cos, fresh_w = skystencil._node_geometry(nodes, sub)
    fresh_tables = skystencil._tables()
    clear = lambda: (skystencil.node_geometry.cache_clear(),  # noqa: E731
                     skystencil._cached_tables.cache_clear())
    clear()
    try:
        skystencil.node_geometry(nodes, sub)  # made and stored
        skystencil._cached_tables()
        assert len(list(cache_folder.glob("fitter-sky-*.npz"))) == 2
        clear()
        monkeypatch.setattr(skystencil, "_node_geometry", lambda *a: pytest.fail("made again"))
        monkeypatch.setattr(skystencil, "_tables", lambda: pytest.fail("made again"))
        cos, w = skystencil.node_geometry(nodes, sub)
        tables = skystencil._cached_tables()
    finally:
        clear()  # later tests make their own
    assert type(cos) is type(fresh_cos)
    for a, b in zip((*cos, w, *tables), (*fresh_cos, fresh_w, *fresh_tables)):
        assert a.dtype == b.dtype and np.array_equal(a, b)


def test_storing_removes_only_this_kinds_files_of_other_sources(cache_folder, monkeypatch):
    """A table stored by these sources removes the same kind's tables that other
    sources made (tagged, or named before the tag) but those of the other
    sources that wrote last, and nothing else: another kind's, these sources'
    other keys, JAX's entries and files fitter did not write stay. Reference:
    the folder's listing, made by hand."""
    import os

    monkeypatch.setattr(compilation_cache, "_SWEPT", set())
    older, last, untagged = "0123456789abcdef", "fedcba9876543210", "f" * 32
    stale = [f"fitter-probe-{older}-{'a' * 32}.npz", f"fitter-probe-{older}-{'d' * 32}.npz",
             f"fitter-probe-{untagged}.npz"]
    kept = [f"fitter-probe-{last}-{'a' * 32}.npz",  # the other sources that wrote last
            f"fitter-sky-nodes-{older}-{'b' * 32}.npz",  # another kind
            f"jit_solve-{'c' * 64}-cache",  # JAX's
            "fitter-probe-notes.npz", "results.npz", "fitter-probe-1234.txt"]  # not ours
    for name in stale + kept:
        (cache_folder / name).write_bytes(b"x")
    for name, when in ((stale[0], 1000), (stale[1], 2000), (kept[0], 3000)):
        os.utime(cache_folder / name, (when, when))
    compilation_cache.cached_arrays("probe", "k1", lambda: (np.ones(2),))
    compilation_cache.cached_arrays("probe", "k2", lambda: (np.zeros(2),))
    names = {p.name for p in cache_folder.iterdir()}
    assert not names & set(stale)
    assert set(kept) <= names
    assert len([n for n in names if n.startswith("fitter-probe-") and n.endswith(".npz")
                and n not in kept]) == 2  # both of these sources' keys


def test_a_sky_lit_fit_makes_the_stencil_tables_on_its_import_thread(no_cache_folder,
                                                                      monkeypatch):
    """``fit._ahead.import_ahead``: where the environment lights an opaque lobe, the
    tables the set-up asks for (``geometry.build_geometry``'s calls) are made (or,
    with a cache folder, loaded) on the thread; a mirror under the same sky, or a
    material not yet parsed, starts no such work."""
    from fitter import Environment, Material, Scene
    from fitter.fit import _ahead

    made = []
    monkeypatch.setattr(skystencil, "warm", lambda: made.append(1))
    scene = Scene(width=8, height=8, environment=Environment("constant", radiance=(1.0, 1.0, 1.0)))

    def run(material):
        made.clear()
        _ahead.import_ahead(scene, material)
        _ahead.settled(lambda: None)()  # joins the thread
        return len(made)

    assert run(Material.make(["lambert"])) == 1
    assert run(Material.make(["mirror"])) == 0
    assert run({"lobes": ["lambert"]}) == 0  # not parsed yet: no guess
    jax.config.update("jax_compilation_cache_dir", "/nonexistent-cache")
    try:
        assert run(Material.make(["lambert"])) == 1
        assert run(Material.make(["mirror"])) == 0
    finally:
        jax.config.update("jax_compilation_cache_dir", None)


def test_warm_makes_the_tables_build_geometry_asks_for(monkeypatch):
    """``skystencil.warm`` fills the caches under the arguments the set-up passes
    (a cache keyed on other arguments would be made twice)."""
    skystencil.node_geometry.cache_clear()
    skystencil._cached_tables.cache_clear()
    skystencil.warm()
    det = skystencil.Detail()
    monkeypatch.setattr(skystencil, "_node_geometry", lambda *a: pytest.fail("made again"))
    monkeypatch.setattr(skystencil, "_tables", lambda *a: pytest.fail("made again"))
    skystencil.node_geometry(det.nodes, tuple(det.sub), det.rings)
    skystencil._cached_tables(det.rings)


def test_a_fit_given_a_lobe_string_warms_the_tables_too(no_cache_folder, monkeypatch):
    """``fitter.fit`` parses the material before ``import_ahead`` reads it: a
    "lambert" string under a sky gets the tables made on the import thread, as a
    ``Material`` does."""
    from fitter import Environment, Scene

    made = []
    warm = skystencil.warm
    monkeypatch.setattr(skystencil, "warm", lambda: made.append(1) or warm())
    scene = Scene(width=16, height=16,
                  environment=Environment("constant", radiance=(1.0, 1.0, 1.0)))
    target = np.asarray(fitter.render({"lambert.rho_d": [0.5, 0.4, 0.3]}, scene, "lambert"))
    fitter.fit(target, scene, "lambert")
    assert made == [1]

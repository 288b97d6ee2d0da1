"""Executables compiled on a thread ahead of their use (``fit._compile.compile_ahead``:
the solve beside the start check; ``fit._discretisation.prefetch``: the finer
render beside the solve) give the fit the same result as compiled in line, a
failure on the thread falls back to compiling in line, and no thread outlives
``fit``."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import fitter
from fitter.fit import _compile, _discretisation, _drivers, _renders

LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),)
SCENE = fitter.Scene(width=40, height=40, supersampling=2, lights=LIGHTS)
GLOSSY = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
          "torrance_sparrow.eta": 1.5}
THREADS = ("fitter-compile-ahead", "fitter-finer-geometry")
PARTS = ("params", "stderr", "stderr_stat", "stderr_sys", "stderr_disc")


@pytest.fixture(scope="module")
def target():
    # 16 x 16 samples, fitted with 2 x 2: a discretisation error to state too.
    return np.asarray(fitter.render(GLOSSY, SCENE.replace(supersampling=16)))


def _fresh(monkeypatch):
    """No executable or finer geometry kept from another fit."""
    for mod, name in ((_compile, "_COMPILED"), (_compile, "_PENDING"),
                      (_renders, "EXECUTABLES"), (_discretisation, "_GEOMETRIES"),
                      (_discretisation, "_AHEAD")):
        monkeypatch.setattr(mod, name, {})


def _fit(target, monkeypatch):
    """The fit, and the threads on which the solve and the finer render were compiled."""
    _fresh(monkeypatch)
    where = []
    build, lowered, render = (_compile._build, _compile._compile_lowered,
                              _renders.compile_render)

    def build_rec(kind, *args):
        where.append((kind, threading.current_thread().name))
        return build(kind, *args)

    def lowered_rec(*args):  # only compile_ahead's, only the solve's here
        where.append(("solve", threading.current_thread().name))
        return lowered(*args)

    def render_rec(*args):
        where.append(("finer render", threading.current_thread().name))
        return render(*args)

    monkeypatch.setattr(_compile, "_build", build_rec)
    monkeypatch.setattr(_compile, "_compile_lowered", lowered_rec)
    monkeypatch.setattr(_renders, "compile_render", render_rec)
    res = fitter.fit(target, SCENE, "lambert+torrance_sparrow")
    assert not [t.name for t in threading.enumerate() if t.name in THREADS]  # joined
    return res, [w for w in where if w[0] in ("solve", "finer render")]


def _untimed(x):
    """``x`` (the adequacy verdict) without its timings."""
    if isinstance(x, dict):
        return {k: _untimed(v) for k, v in x.items() if k != "seconds"}
    return repr(x)


def _same(a, b, keys=GLOSSY):
    assert a.status == b.status
    assert (a.message, a.warnings, a.unidentifiable, a.free, a.iterations, a.cost) == \
        (b.message, b.warnings, b.unidentifiable, b.free, b.iterations, b.cost)
    assert _untimed(a.adequacy) == _untimed(b.adequacy)
    np.testing.assert_array_equal(a.correlation, b.correlation)
    np.testing.assert_array_equal(a.image_rmse, b.image_rmse)
    for part in PARTS:
        for key in keys:
            np.testing.assert_array_equal(getattr(a, part)[key], getattr(b, part)[key])


@pytest.fixture(scope="module")
def in_line(target):
    """The fit with every executable compiled where it is used (no thread)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_drivers, "compile_ahead", lambda *a, **k: None)
        mp.setattr(_discretisation, "prefetch", lambda problem: None)
        res, where = _fit(target, mp)
    assert where == [("solve", "MainThread"), ("finer render", "MainThread")]
    return res


def test_compiled_ahead_gives_the_same_fit(target, in_line, monkeypatch):
    ahead, where = _fit(target, monkeypatch)
    assert where == [("solve", "fitter-compile-ahead"), ("finer render", "fitter-finer-geometry")]
    _same(ahead, in_line)
    assert np.all(np.asarray(ahead.stderr_disc["lambert.rho_d"]) > 0)


def test_a_failure_on_the_thread_compiles_in_line(target, in_line, monkeypatch):
    lowered, render = _compile._compile_lowered, _renders.compile_render

    def fails_on_threads(f):
        def g(*args):
            if threading.current_thread() is not threading.main_thread():
                raise RuntimeError("injected")
            return f(*args)
        return g

    monkeypatch.setattr(_compile, "_compile_lowered", fails_on_threads(lowered))
    monkeypatch.setattr(_renders, "compile_render", fails_on_threads(render))
    res, where = _fit(target, monkeypatch)
    # Tried on the threads (and failed there), then compiled where used.
    assert sorted(where) == [("finer render", "MainThread"),
                             ("finer render", "fitter-finer-geometry"),
                             ("solve", "MainThread"), ("solve", "fitter-compile-ahead")]
    _same(res, in_line)


@pytest.fixture(scope="module")
def sun_probe(tmp_path_factory):
    """A 32 x 16 map with a sun far smaller than one texel (as test_envlight's)."""
    from fitter.imageio import write_image

    img = np.full((16, 32, 3), 0.3)
    img[5, 9] = [3000.0, 2900.0, 2500.0]
    path = str(tmp_path_factory.mktemp("probe") / "sun.exr")
    write_image(path, img)
    return path


def test_sun_lit_finer_geometries_made_ahead_give_the_same_fit(sun_probe, finer_builds,
                                                               monkeypatch):
    # An environment map lighting opaque lobes: prefetch makes both finer
    # geometries (2k samples with the default sun cells, k with FINER_SUN), then
    # the half-ring sky of the stated errors (``ring_error``, k).
    scene = fitter.Scene(width=32, height=32, supersampling=2,
                         environment=fitter.Environment(type="envmap", file=sun_probe))
    material = fitter.Material.make(["lambert", "torrance_sparrow"],
                                    {"torrance_sparrow.geometry": "smith"})
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3], "torrance_sparrow.m": 0.15,
             "torrance_sparrow.eta": 1.5}
    target = np.asarray(fitter.render(truth, scene.replace(supersampling=6), material))
    made_on = finer_builds
    _fresh(monkeypatch)
    ahead = fitter.fit(target, scene, material, init=truth)
    assert made_on == [(4, "fitter-finer-geometry"), (2, "fitter-finer-geometry"),
                       (2, "fitter-finer-geometry")]
    made_on.clear()
    _fresh(monkeypatch)
    monkeypatch.setattr(_discretisation, "prefetch", lambda problem: None)
    here = fitter.fit(target, scene, material, init=truth)
    assert made_on == [(4, "MainThread"), (2, "MainThread"), (2, "MainThread")]
    _same(ahead, here, truth)
    assert np.all(np.asarray(ahead.stderr_disc["torrance_sparrow.m"]) > 0)


def test_a_compile_started_behind_waits_for_those_started_before(monkeypatch):
    """``compile_ahead(behind=True)`` (the cost profile's, ``_profile.ahead``)
    compiles only after the compiles already started ahead (the solve's, which
    the fit needs first) have ended."""
    order = []
    gate = threading.Event()
    earlier = threading.Thread(target=lambda: (gate.wait(10), order.append("earlier")))
    monkeypatch.setattr(_compile, "_PENDING", {"earlier": (earlier, [])})
    monkeypatch.setattr(_compile, "_COMPILED", {})
    monkeypatch.setattr(_compile, "_function", lambda kind, spec, static: None)
    monkeypatch.setattr(_compile, "lower_cached", lambda f, args, key: "lowered")
    monkeypatch.setattr(_compile, "_options", lambda kind, once, spec: {})
    monkeypatch.setattr(_compile, "_compile_lowered",
                        lambda lowered, options, x64: order.append("behind") or "exe")
    earlier.start()
    _compile.compile_ahead("residuals", "spec", (np.zeros(2),), behind=True)
    behind = [t for k, (t, _) in _compile._PENDING.items() if k != "earlier"]
    assert len(behind) == 1
    behind[0].join(0.3)
    assert order == []  # still waiting
    gate.set()
    earlier.join()
    behind[0].join()
    assert order == ["earlier", "behind"]


def test_a_process_keeps_only_the_most_recently_used_executables(monkeypatch):
    # A batch worker fitting images of ever new shapes kept every executable it
    # compiled; now the KEEP_COMPILED most recently used (a hit counts as a use).
    monkeypatch.setattr(_compile, "_COMPILED", {})
    monkeypatch.setattr(_compile, "_PENDING", {})
    monkeypatch.setattr(_compile, "KEEP_COMPILED", 3)
    monkeypatch.setattr(_compile, "_key", lambda kind, spec, args, once, static: kind)
    built = []
    monkeypatch.setattr(_compile, "_build", lambda kind, *a: built.append(kind) or kind)
    for kind in ("a", "b", "c", "a", "d"):  # "a" used again: "b" is the oldest
        assert _compile.compiled(kind, None, ())[0] == kind
    assert list(_compile._COMPILED) == ["c", "a", "d"] and built == ["a", "b", "c", "d"]
    _compile.compiled("b", None, ())
    assert built[-1] == "b" and "c" not in _compile._COMPILED

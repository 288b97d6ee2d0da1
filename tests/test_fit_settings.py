"""Process settings a fit holds changed while it runs and gives back after:
NumPy's huge-page advice off (``fitter.hugepages``), one BLAS thread
(``fitter.blasthreads``) and fewer garbage collections (``fitter.gcthreshold``),
all through ``fitter._switch.SharedSwitch``."""

import gc
import threading

import numpy as np
import pytest
from threadpoolctl import ThreadpoolController

from fitter import blasthreads, gcthreshold, hugepages, serialize
from fitter.cases import CASES
from fitter.fit import _drivers

_ADVICE = np._core.multiarray._set_madvise_hugepage


def advice() -> bool:
    """NumPy's huge-page advice now, read without changing it."""
    now = _ADVICE(False)
    _ADVICE(now)
    return bool(now)


def blas_threads() -> int:
    """The most threads any loaded BLAS library may use now."""
    return max(info["num_threads"] for info in ThreadpoolController().select(
        user_api="blas").info())


def young_threshold() -> int:
    """The garbage collector's young-generation threshold now."""
    return gc.get_threshold()[0]


#: CPython's default young threshold, which the fixture sets.
DEFAULT_THRESHOLD = 700
#: (decorator, the setting now, its value inside a fit, before and after).
SWITCHES = {"huge-page advice": (hugepages.advice_off, advice, False, True),
            "BLAS threads": (blasthreads.one_blas_thread, blas_threads, 1, 2),
            "collector threshold": (gcthreshold.fewer_collections, young_threshold,
                                    gcthreshold.THRESHOLD, DEFAULT_THRESHOLD)}


@pytest.fixture(autouse=True)
def known_settings(monkeypatch):
    """The advice on, every BLAS library at two threads and the collector at its
    default: values that differ from a fit's."""
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    before = _ADVICE(True)
    limiter = ThreadpoolController().limit(limits=2, user_api="blas")
    assert blas_threads() == 2
    thresholds = gc.get_threshold()
    gc.set_threshold(DEFAULT_THRESHOLD, *thresholds[1:])
    yield
    gc.set_threshold(*thresholds)
    limiter.restore_original_limits()
    _ADVICE(before)


@pytest.fixture(params=list(SWITCHES))
def switch(request):
    return SWITCHES[request.param]


def test_changed_inside_and_restored_after(switch):
    decorator, now, inside, outside = switch
    seen = []
    decorator(lambda: seen.append(now()))()
    assert seen == [inside] and now() == outside


def test_restored_after_an_error(switch):
    decorator, now, _, outside = switch

    def boom():
        raise RuntimeError("x")

    with pytest.raises(RuntimeError):
        decorator(boom)()
    assert now() == outside


def test_nested_and_concurrent_calls_restore_once_the_last_returns(switch):
    decorator, now, inside, outside = switch
    entered, release, seen = threading.Event(), threading.Event(), []

    def slow():
        entered.set()
        release.wait(5)

    thread = threading.Thread(target=decorator(slow))
    thread.start()
    entered.wait(5)
    decorator(decorator(lambda: seen.append(now())))()
    seen.append(now())  # the other call still runs
    release.set()
    thread.join()
    assert seen == [inside, inside] and now() == outside


class _Stop(Exception):
    pass


@pytest.mark.parametrize("entry", ["fit", "fit_batch"])
def test_fit_entry_points_run_with_every_setting(monkeypatch, entry):
    seen = []

    def probe(*args, **kwargs):
        seen.append((advice(), blas_threads(), young_threshold()))
        raise _Stop

    monkeypatch.setattr(_drivers, "check_scene", probe)
    target = np.zeros((8, 8, 3)) if entry == "fit" else np.zeros((1, 8, 8, 3))
    scene = serialize.scene_from_dict(CASES["plastic"]["scene"], "plastic")
    with pytest.raises(_Stop):
        getattr(_drivers, entry)(target, scene, "lambert")
    assert seen == [(False, 1, gcthreshold.THRESHOLD)]
    assert (advice(), blas_threads(), young_threshold()) == (True, 2, DEFAULT_THRESHOLD)


def test_a_disabled_collector_is_left_alone():
    gc.disable()
    try:
        seen = []
        gcthreshold.fewer_collections(lambda: seen.append(young_threshold()))()
        assert seen == [DEFAULT_THRESHOLD] and not gc.isenabled()
    finally:
        gc.enable()


def test_a_scene_is_prepared_with_both_settings(monkeypatch):
    from fitter import render

    seen = []
    real = render.build_geometry

    def probe(*args, **kwargs):
        seen.append((advice(), blas_threads()))
        return real(*args, **kwargs)

    monkeypatch.setattr(render, "build_geometry", probe)
    scene = serialize.scene_from_dict(CASES["plastic"]["scene"], "plastic")
    render._prepare.__wrapped__(scene.replace(width=9, height=7), np.dtype(np.float64), None)
    assert seen == [(False, 1)] and (advice(), blas_threads()) == (True, 2)

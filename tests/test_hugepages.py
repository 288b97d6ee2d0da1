"""NumPy's huge-page advice is off while a fit runs and restored after (fitter.hugepages)."""

import threading

import numpy as np
import pytest

from fitter import hugepages, serialize
from fitter.cases import CASES
from fitter.fit import _drivers

switch = np._core.multiarray._set_madvise_hugepage


def advice() -> bool:
    """NumPy's current setting, read without changing it."""
    now = switch(False)
    switch(now)
    return bool(now)


@pytest.fixture(autouse=True)
def numpy_default(monkeypatch):
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    before = switch(True)
    yield
    switch(before)


@pytest.mark.parametrize("start", [True, False])
def test_off_inside_and_restored_after(start):
    switch(start)
    seen = []
    hugepages.advice_off(lambda: seen.append(advice()))()
    assert seen == [False] and advice() is start


def test_restored_after_an_error():
    def boom():
        raise RuntimeError("x")

    with pytest.raises(RuntimeError):
        hugepages.advice_off(boom)()
    assert advice() is True


def test_nested_and_concurrent_calls_restore_once_the_last_returns():
    inside, release, seen = threading.Event(), threading.Event(), []

    def slow():
        inside.set()
        release.wait(5)

    thread = threading.Thread(target=hugepages.advice_off(slow))
    thread.start()
    inside.wait(5)
    hugepages.advice_off(hugepages.advice_off(lambda: seen.append(advice())))()
    seen.append(advice())  # the other call still runs
    release.set()
    thread.join()
    assert seen == [False, False] and advice() is True


def test_numpy_environment_switch_is_left_in_charge(monkeypatch):
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
    seen = []
    hugepages.advice_off(lambda: seen.append(advice()))()
    assert seen == [True]


class _Stop(Exception):
    pass


@pytest.mark.parametrize("entry", ["fit", "fit_batch"])
def test_fit_entry_points_run_with_the_advice_off(monkeypatch, entry):
    seen = []

    def probe(*args, **kwargs):
        seen.append(advice())
        raise _Stop

    monkeypatch.setattr(_drivers, "check_fit", probe)
    target = np.zeros((8, 8, 3)) if entry == "fit" else np.zeros((1, 8, 8, 3))
    scene = serialize.scene_from_dict(CASES["plastic"]["scene"], "plastic")
    with pytest.raises(_Stop):
        getattr(_drivers, entry)(target, scene, "lambert")
    assert seen == [False] and advice() is True


def test_a_scene_is_prepared_with_the_advice_off(monkeypatch):
    from fitter import render

    seen = []
    real = render.build_geometry

    def probe(*args, **kwargs):
        seen.append(advice())
        return real(*args, **kwargs)

    monkeypatch.setattr(render, "build_geometry", probe)
    scene = serialize.scene_from_dict(CASES["plastic"]["scene"], "plastic")
    render._prepare.__wrapped__(scene.replace(width=9, height=7), np.dtype(np.float64), None)
    assert seen == [False] and advice() is True

"""NumPy's huge-page advice (fitter.hugepages): its own cases; what every fit setting
shares is in test_fit_settings.py."""

import numpy as np
import pytest

from fitter import hugepages

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


def test_numpy_environment_switch_is_left_in_charge(monkeypatch):
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
    seen = []
    hugepages.advice_off(lambda: seen.append(advice()))()
    assert seen == [True]

"""One BLAS thread while a fit runs (fitter.blasthreads): libraries loaded meanwhile and
libraries that cannot be limited; what every fit setting shares is in test_fit_settings.py."""

import pytest
from threadpoolctl import ThreadpoolController

from fitter import blasthreads


def blas_threads() -> int:
    """The most threads any loaded BLAS library may use now."""
    return max(info["num_threads"] for info in ThreadpoolController().select(
        user_api="blas").info())


@pytest.fixture(autouse=True)
def two_threads():
    """Every BLAS library at two threads (its limit is known, and differs from one)."""
    limiter = ThreadpoolController().limit(limits=2, user_api="blas")
    assert blas_threads() == 2
    yield
    limiter.restore_original_limits()


def test_a_library_loaded_inside_is_limited_and_restored(monkeypatch):
    """A BLAS library that appears while the switch is on (as SciPy's OpenBLAS
    does at a process's first LAPACK lowering) is limited by ``catch_up`` and
    given back its own limit after. Stand-in: the libraries blasthreads sees
    grow by one fake library (2 threads) while the call runs."""
    real = blasthreads._blas
    fake = {"threads": 2, "loaded": False}

    class Blas:
        def __init__(self, rescan=True):
            self.real = real(rescan)

        def info(self):
            extra = [{"num_threads": fake["threads"]}] if fake["loaded"] else []
            return self.real.info() + extra

        def limit(self, limits):
            limiter, before = self.real.limit(limits=limits), fake["threads"]
            if fake["loaded"]:
                fake["threads"] = limits

            class Restore:
                def restore_original_limits(self):
                    limiter.restore_original_limits()
                    fake["threads"] = before

            return Restore()

    monkeypatch.setattr(blasthreads, "_blas", Blas)
    seen = []

    def body():
        fake["loaded"] = True
        seen.append(fake["threads"])
        blasthreads.catch_up()
        seen.append((blas_threads(), fake["threads"]))

    blasthreads.one_blas_thread(body)()
    assert seen == [2, (1, 1)]
    assert blas_threads() == 2 and fake["threads"] == 2


def test_a_fit_reuses_the_last_scan_and_a_compile_scans_again(monkeypatch):
    """Turning the switch on does not scan the process's libraries again (1.5 ms
    a fit); ``catch_up``, run after each compile, does."""
    from threadpoolctl import ThreadpoolController

    scans = []
    real = ThreadpoolController.__init__

    def counted(self, *a, **k):
        scans.append(1)
        real(self, *a, **k)

    blasthreads.one_blas_thread(lambda: None)()  # a scan to reuse
    monkeypatch.setattr(ThreadpoolController, "__init__", counted)
    seen = []
    blasthreads.one_blas_thread(lambda: seen.append(blas_threads()))()
    assert seen == [1] and len(scans) == 1  # blas_threads' own scan only
    blasthreads.one_blas_thread(blasthreads.catch_up)()
    assert len(scans) == 2
    assert blas_threads() == 2


def test_catch_up_does_nothing_while_off():
    blasthreads.catch_up()
    assert blas_threads() == 2


def test_a_library_that_cannot_be_limited_leaves_the_call_running(monkeypatch):
    """threadpoolctl failing (an odd BLAS build) leaves the limits as they are
    and the decorated call runs and returns as without the switch."""
    def broken():
        raise OSError("no symbol")

    monkeypatch.setattr(blasthreads, "_blas", broken)
    seen = []
    out = blasthreads.one_blas_thread(lambda: seen.append(blas_threads()) or 7)()
    blasthreads.catch_up()
    assert out == 7 and seen == [2] and blas_threads() == 2

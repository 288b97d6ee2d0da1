"""One BLAS thread while a fit runs.

NumPy's OpenBLAS keeps a worker thread per core, and after each call its
workers spin-wait for the next one before they sleep. A fit's NumPy calls
(J^T J, the profile's matrix products, QR and least squares of n x n
matrices) are small and come between XLA runs, which use every core: the
spinning workers took one of the two cores from them. Measured on 2 cores,
256^2 plastic, compiled ``fitter.fit`` (the benchmark's noisy target): 0.27 s
wall and 0.50 s of CPU with two BLAS threads, 0.20 s and 0.29 s with one;
after a fit returned, its BLAS workers went on spinning for 88 ms of CPU.
A Gauss-Newton step's XLA run took 40 ms beside them and 21 ms alone.

``one_blas_thread`` limits every loaded BLAS library to one thread
(``threadpoolctl``) while a decorated call, or any thread it starts, runs,
and restores the libraries' settings when the last such call returns. A
library loaded while it runs is limited by ``catch_up``: jaxlib takes its
CPU LAPACK kernels from SciPy's own OpenBLAS, loaded when the first
linear-algebra op of a process is lowered (inside a first fit).
"""

from __future__ import annotations

import threading

from ._switch import SharedSwitch

#: The limits set while the switch is on, each with the number of BLAS libraries
#: loaded when it was set; restored last first (``catch_up`` adds one when
#: libraries were loaded meanwhile).
_LIMITERS: list = []
_LOCK = threading.Lock()


#: The last controller ``_blas`` made: a fit reuses it (the scan was 1.5 ms of
#: a compiled 256^2 fit's 0.1 s); ``catch_up``, after each compile, scans again.
_SEEN: list = []


def _blas(rescan: bool = True):
    """threadpoolctl's controller of the BLAS libraries loaded now (~1.5 ms: it
    scans the process's shared libraries), or, without ``rescan``, of those
    loaded at the last scan (a library loaded between fits by other code,
    without a compile since, then keeps its own thread count)."""
    if rescan or not _SEEN:
        from threadpoolctl import ThreadpoolController

        _SEEN[:] = [ThreadpoolController().select(user_api="blas")]
    return _SEEN[0]


def _limit():
    """Limit BLAS to one thread: the function restoring the previous limits,
    or None where the libraries cannot be limited (left as they are: a speed
    setting never fails a fit)."""
    with _LOCK:
        try:
            _free()
            blas = _blas(rescan=False)
            _LIMITERS[:] = [(blas.limit(limits=1), len(blas.info()))]
            _free()
        except Exception:  # noqa: BLE001
            _LIMITERS.clear()
            return None

    def restore():
        with _LOCK:
            for limiter, _ in reversed(_LIMITERS):
                limiter.restore_original_limits()
            _LIMITERS.clear()
            _free()

    return restore


def catch_up() -> None:
    """Limit the BLAS libraries loaded since the switch turned on (a call after
    an XLA compile: ~1 ms); nothing while it is off."""
    with _LOCK:
        if not one_blas_thread.on or not _LIMITERS:
            return
        try:
            blas = _blas()
            if len(blas.info()) > _LIMITERS[-1][1]:
                _free()
                _LIMITERS.append((blas.limit(limits=1), len(blas.info())))
                _free()
        except Exception:  # noqa: BLE001 (as in ``_limit``)
            pass


def _free() -> None:
    """Let any thread set OpenBLAS's limit next: threadpoolctl >= 3.8 lets only
    the thread that set its process-wide pool last change it, and the first and
    last callers of the switch may be different threads."""
    from threadpoolctl import OpenBLASController

    clear = getattr(OpenBLASController, "clear_controlling_thread", None)
    if clear is not None:
        clear(force=True)


#: ``f`` run with one BLAS thread (nested and concurrent calls share one
#: switch: the last to return restores the libraries' limits).
one_blas_thread = SharedSwitch(_limit)

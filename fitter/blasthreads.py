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
and restores the libraries' settings when the last such call returns.
"""

from __future__ import annotations

from ._switch import SharedSwitch


def _limit():
    """Limit BLAS to one thread: the function restoring the previous limits."""
    from threadpoolctl import ThreadpoolController  # (scans the loaded libraries: ~1 ms)

    _free()
    limiter = ThreadpoolController().limit(limits=1, user_api="blas")
    _free()

    def restore():
        limiter.restore_original_limits()
        _free()

    return restore


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

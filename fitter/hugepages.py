"""NumPy's transparent-huge-page advice, off while a fit runs.

NumPy advises the kernel to back every array of 4 MiB or more with
transparent huge pages (``madvise(MADV_HUGEPAGE)``). On the 2-core virtual
machine the targets are measured on, each such fault cost ~12 ms of system
time (``/proc/vmstat``: a 256^2 first fit took 340 of them, 4.0 s; no
compaction stall), so a fit's large short-lived NumPy arrays (the finer
geometry of the discretisation term, the sky tables) spent most of their
time in the kernel. Measured (``benchmarks/compile_time.py``'s 256^2
plastic, first fit in a fresh process): 7.9 s with the advice and 3.6 s
without, system time 4.2 -> 0.36 s (4 KiB faults instead, ~2 us each);
env_plastic's first fit: system time 4.5 -> 1.2 s. Compiled fits do not
change.

``advice_off`` turns the advice off for the arrays made while a decorated
call (or any thread it starts) runs, and restores NumPy's setting when the
last such call returns. ``NUMPY_MADVISE_HUGEPAGE`` set in the environment (NumPy's
own switch) is left in charge.
"""

from __future__ import annotations

import os

from ._switch import SharedSwitch


def _switch():
    """NumPy's switch (it returns the previous setting), or None where absent."""
    from numpy._core import multiarray

    return getattr(multiarray, "_set_madvise_hugepage", None)


def _turn_off():
    """Turn the advice off: the function restoring it, or None where left to the user."""
    switch = _switch()
    if "NUMPY_MADVISE_HUGEPAGE" in os.environ or switch is None:
        return None
    saved = bool(switch(False))
    return lambda: switch(saved)


#: ``f`` with NumPy's huge-page advice off while it runs (nested and concurrent
#: calls share one switch: the last to return restores it).
advice_off = SharedSwitch(_turn_off)

"""Fewer garbage collections while a fit runs.

A first fit traces its executables: JAX's tracing allocates millions of
short-lived Python containers, and CPython's cyclic collector runs its young
generation every 700 net allocations (``gc.get_threshold()[0]``), each run
walking the survivors. On the 2-core machine the targets are measured on,
env_plastic's first fit spent ~3 % of its CPU in the collector (``perf``:
``gc_collect_main``, ``visit_decref``, ``visit_reachable``); with the young
generation's threshold at ``THRESHOLD`` the fit took 8.40 -> 8.13 CPU-s and
4.66 -> 4.46 s (three runs each, medians; collector off: 4.41 s). The fit's
garbage is still collected, in fewer, larger passes, and the threshold is
restored when the fit returns.

``fewer_collections`` raises the threshold while a decorated call (or any
call beside it) runs; a collector the user turned off is left alone.
"""

from __future__ import annotations

import gc

from ._switch import SharedSwitch

#: The young generation's threshold while a fit runs (CPython's default: 700).
THRESHOLD = 100_000


def _raise():
    """Raise the threshold: the function restoring it, or None where the
    collector is off or already as lax (left to the user)."""
    saved = gc.get_threshold()
    if not gc.isenabled() or saved[0] == 0 or saved[0] >= THRESHOLD:
        return None
    gc.set_threshold(THRESHOLD, *saved[1:])
    return lambda: gc.set_threshold(*saved)


#: ``f`` run with the collector's young threshold at ``THRESHOLD`` (nested and
#: concurrent calls share one switch: the last to return restores it).
fewer_collections = SharedSwitch(_raise)

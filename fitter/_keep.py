"""Scene-sized values kept between calls, bounded by their bytes as well as their count.

``functools.lru_cache(maxsize=8)`` of a scene's arrays kept eight scenes: fits
of five different 256^2 env-lit scenes in one process (a Python loop over
captures, a batch worker) held 12.5 GB afterwards, 2.2 GB more with each.
``recent`` keeps the most recent value whatever its size (a refit of the same
scene reuses it) and older ones only while they total under ``max_bytes``.
"""

from __future__ import annotations

import functools
import math
import threading
import weakref
from types import ModuleType


def nbytes(value, _seen=None) -> int:
    """Bytes of the arrays in ``value``: an array's ``nbytes``, summed through
    tuples, lists, dicts and objects' attributes (not functions', classes' or
    modules'; each array counted once)."""
    seen = set() if _seen is None else _seen
    if id(value) in seen:
        return 0
    seen.add(id(value))
    size = getattr(value, "nbytes", None)
    if isinstance(size, int):
        return size
    if isinstance(value, dict):
        return sum(nbytes(v, seen) for v in value.values())
    if isinstance(value, (tuple, list)):
        return sum(nbytes(v, seen) for v in value)
    if hasattr(value, "__dict__") and not (callable(value) or isinstance(value, ModuleType)):
        return sum(nbytes(v, seen) for v in vars(value).values())
    return 0


def hold(kept: dict, key, value, most: int, max_bytes: float = math.inf, size=nbytes,
         protect: int = 1) -> None:
    """Put ``value`` under ``key`` as the newest entry of ``kept`` (a dict keeps
    insertion order), then ``trim`` it."""
    kept.pop(key, None)
    kept[key] = value
    trim(kept, most, max_bytes, size, protect)


def trim(kept: dict, most: int, max_bytes: float = math.inf, size=nbytes,
         protect: int = 0) -> None:
    """Drop the oldest entries of ``kept`` while it holds over ``most`` or their
    ``size`` totals over ``max_bytes``; the newest ``protect`` stay."""
    while len(kept) > protect and (len(kept) > most or (
            max_bytes < math.inf and sum(size(v) for v in kept.values()) > max_bytes)):
        kept.pop(next(iter(kept)))


#: Every ``recent`` cache of the process (``release``).
_ALL: list = []
#: ``derived``'s values: [(weak reference to the owner's anchor, {name: value})],
#: the newest last, at most ``KEEP_DERIVED``.
_DERIVED: list = []
_DERIVED_LOCK = threading.Lock()
KEEP_DERIVED = 4


def release() -> None:
    """Empty every ``recent`` cache and ``derived``'s values: a batch worker does
    so before a job of another scene, so that one job's arrays are not held
    beside the next's."""
    for f in _ALL:
        f.cache_clear()
    _DERIVED.clear()


def derived(anchor, name: str, make):
    """``make()``, a value that depends only on the object that owns ``anchor``
    (an array of it, weakly referenced: nothing is kept alive by this), kept
    with that object's other values under ``name`` for the last
    ``KEEP_DERIVED`` objects asked about; its arrays made read-only."""
    with _DERIVED_LOCK:
        for k, (ref, values) in enumerate(_DERIVED):
            if ref() is anchor:
                _DERIVED.append(_DERIVED.pop(k))
                break
        else:
            live = [e for e in _DERIVED if e[0]() is not None]
            values = {}
            _DERIVED[:] = live[max(0, len(live) - KEEP_DERIVED + 1):]
            _DERIVED.append((weakref.ref(anchor), values))
        if name in values:
            return values[name]
    value = make()  # outside the lock (two threads may both make it: the same value)
    for a in value if isinstance(value, tuple) else (value,):
        if hasattr(a, "flags"):
            a.flags.writeable = False
    with _DERIVED_LOCK:
        return values.setdefault(name, value)


def recent(max_items: int, max_bytes: float):
    """Decorator: ``functools.lru_cache(maxsize=max_items)`` that also drops the
    least recently used values while the kept values total over ``max_bytes``
    (``nbytes``). The newest value stays whatever its size, and so does the one
    before it when the newest is under ``max_bytes`` (a fit's half-size coarse
    problem after its full-size one: both are asked for again by the next fit).
    On a miss the values over the bounds go before the new one is made, the
    newest excepted, so a process holds at most two large scenes at once.
    ``f.cache_clear()`` empties it, ``f.cache_info()`` is (values kept, their
    bytes) and ``f.max_bytes`` the bound (it may be changed)."""
    def wrap(f):
        kept: dict = {}  # key -> (value, its bytes), oldest first
        lock = threading.Lock()
        second = lambda entry: entry[1]  # noqa: E731

        @functools.wraps(f)
        def g(*args, **kwargs):
            key = (args, tuple(sorted(kwargs.items())))
            with lock:
                if key in kept:
                    kept[key] = kept.pop(key)  # now the newest
                    return kept[key][0]
                trim(kept, max_items - 1, g.max_bytes, second, protect=1)
            value = f(*args, **kwargs)  # outside the lock: a slow build blocks no other key
            with lock:
                size = nbytes(value)
                hold(kept, key, (value, size), max_items, g.max_bytes, second,
                     protect=2 if size <= g.max_bytes else 1)
            return value

        def cache_clear() -> None:
            with lock:
                kept.clear()

        def cache_info() -> tuple[int, int]:
            with lock:
                return len(kept), sum(b for _, b in kept.values())

        g.cache_clear, g.cache_info, g.max_bytes = cache_clear, cache_info, max_bytes
        _ALL.append(g)
        return g

    return wrap

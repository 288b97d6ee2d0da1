"""A process-wide setting held changed while any call of a decorated function runs.

Nested and concurrent calls (fits on threads, Dask's threaded workers) share
one switch: the first call to enter changes the setting, the last to leave
restores it, also when a call raises.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable


class SharedSwitch:
    """Decorator: ``change()`` changes the setting and returns the function
    that restores it, or None where the setting is left alone (the user's own
    switch is in charge)."""

    def __init__(self, change: Callable[[], Callable[[], object] | None]):
        self._change = change
        self._lock = threading.Lock()
        self._depth = 0
        self._restore: Callable[[], object] | None = None

    @property
    def on(self) -> bool:
        """Whether the setting is changed now (some decorated call runs)."""
        return self._depth > 0

    def _enter(self) -> bool:
        with self._lock:
            if self._depth == 0:
                self._restore = self._change()
                if self._restore is None:
                    return False
            self._depth += 1
        return True

    def _leave(self) -> None:
        with self._lock:
            self._depth -= 1
            if self._depth == 0:
                restore, self._restore = self._restore, None
                restore()

    def __call__(self, f):
        @functools.wraps(f)
        def g(*args, **kwargs):
            entered = self._enter()
            try:
                return f(*args, **kwargs)
            finally:
                if entered:
                    self._leave()

        return g

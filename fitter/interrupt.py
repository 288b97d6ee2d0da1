"""SIGINT and SIGTERM during a command: unwound as ``KeyboardInterrupt`` at a
safe point, so staged outputs are removed and ``--out`` keeps its old result."""

from __future__ import annotations

import contextlib
import sys

_INTERRUPTED: list[int] = []  # signals received during this command


def check_interrupt() -> None:
    """Raise ``KeyboardInterrupt`` if a signal arrived during this command."""
    if _INTERRUPTED:
        raise KeyboardInterrupt


@contextlib.contextmanager
def signals_as_interrupt():
    """Let SIGINT and SIGTERM unwind as ``KeyboardInterrupt``, so staged outputs are removed.

    SIGINT is set explicitly: a shell starts background jobs with it ignored,
    and ``kill -INT`` must still stop a fit rather than let it replace ``--out``.
    The signal is also remembered, because Python drops an exception raised
    inside a garbage-collector callback (JAX has one): ``check_interrupt``
    raises it again at the next stage boundary. During an import it is only
    remembered: an exception thrown into a native module's initialisation
    (jaxlib's, OpenImageIO's) aborts or crashes the interpreter.
    """
    import signal

    def handler(signum, frame):
        _INTERRUPTED.append(signum)
        if not _importing(frame):
            raise KeyboardInterrupt

    def unraisable(info, default=sys.unraisablehook):
        if not issubclass(info.exc_type, KeyboardInterrupt):  # remembered; raised later
            default(info)

    _INTERRUPTED.clear()
    hook, sys.unraisablehook = sys.unraisablehook, unraisable
    try:
        previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, handler),
                    signal.SIGINT: signal.signal(signal.SIGINT, handler)}
    except ValueError:  # not the main thread: leave signals alone
        previous = {}
    try:
        yield
        check_interrupt()  # one that arrived during the command's last import
    finally:
        for sig, prev in previous.items():
            signal.signal(sig, prev)
        sys.unraisablehook = hook


def _importing(frame) -> bool:
    """Whether ``frame`` runs inside an ``import`` (importlib's frames are on its stack)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False

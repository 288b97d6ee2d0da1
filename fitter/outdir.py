"""Output folders that never lose anything: fitter replaces only what it wrote.

A job's outputs are written into a hidden temporary sibling of ``--out``
(``.NAME.tmp-PID-XXXX``) that holds a marker file (``MARKER``). When the
outputs are complete the temporary folder and ``--out`` are exchanged in one
atomic ``renameat2(RENAME_EXCHANGE)`` (Linux), so at every instant ``--out``
holds either the whole old result or the whole new one; the old one is then
deleted. ``--out`` may be replaced only if it is empty, holds the marker, or
holds nothing but fitter's own output files (folders written before the marker
existed); anything else is an ``OutputError`` naming the folder, raised before
any work is done. Temporaries left by a killed run are removed by the next run
once their process is gone.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import re
import shutil
import sys
import tempfile

from .errors import FitterError
from .imageio import current_umask

#: File that marks a folder as written by fitter (JSON, a few bytes).
MARKER = ".fitter-output"
#: Every name ``fitter fit`` writes into its output folder.
OUTPUT_NAMES = frozenset({"result.json", "fit.exr", "residual.exr", "validation.exr",
                          "report.png", "config.toml", "scene.xml", "material.json", MARKER})


class OutputError(FitterError):
    """An output folder fitter must not or cannot write (message names it)."""


def check_out(out: str) -> str:
    """The absolute output folder for ``--out``; raises ``OutputError`` if unusable.

    Checked before any fitting: a file or broken link in the way, a folder
    holding files fitter did not write, a parent that cannot be created or
    written to.
    """
    out = os.path.abspath(out)
    if os.path.islink(out):
        if not os.path.exists(out):
            raise OutputError(f"{out}: is a broken symbolic link; remove it or choose "
                              "another --out")
        out = os.path.realpath(out)  # write where the link points, keep the link
    if os.path.exists(out):
        if not os.path.isdir(out):
            raise OutputError(f"{out}: exists and is not a folder; choose another --out")
        foreign = foreign_entries(out)
        if foreign:
            shown = ", ".join(repr(n) for n in foreign[:3]) + (" ..." if len(foreign) > 3 else "")
            raise OutputError(
                f"{out}: holds {len(foreign)} file(s) fitter did not write ({shown}); "
                "fitter replaces only its own output folders, so choose another --out "
                "(e.g. a new sub-folder)")
    parent = _existing_ancestor(os.path.dirname(out))
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{out}: cannot write in {parent} (permission denied); "
                          "choose another --out")
    return out


def foreign_entries(folder: str) -> list[str]:
    """Names in ``folder`` that make it not fitter's to replace (empty if it may be)."""
    try:
        names = sorted(os.listdir(folder))
    except OSError as exc:
        raise OutputError(f"{folder}: cannot be read ({exc.strerror})") from None
    if MARKER in names:
        return []
    return [n for n in names if n not in OUTPUT_NAMES]


@contextlib.contextmanager
def staged_dir(out: str):
    """Yield a temporary folder next to ``out``; swap it into ``out`` on success.

    On any failure (exception, Ctrl-C, SIGTERM) the temporary folder is removed
    and ``out`` is untouched. Stale temporaries of dead runs are cleaned first.
    """
    out = check_out(out)
    parent, name = os.path.dirname(out), os.path.basename(out)
    try:
        made = make_folders(parent)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create {parent} ({exc.strerror})") from None
    for note in clean_stale(parent, name):
        print(f"fitter: {note}", file=sys.stderr)
    tmp = tempfile.mkdtemp(prefix=f".{name}.tmp-{os.getpid()}-", dir=parent)
    try:
        os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp folders are 0700
        _write_marker(tmp)
        yield tmp
        _swap_in(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        remove_made(made)
        raise
    shutil.rmtree(tmp, ignore_errors=True)  # now the old result, if there was one


def make_folders(path: str) -> list[str]:
    """``os.makedirs(path, exist_ok=True)``, returning the folders it created,
    deepest first, for ``remove_made``."""
    made, p = [], os.path.abspath(path)
    while not os.path.isdir(p) and p != os.path.dirname(p):
        made.append(p)
        p = os.path.dirname(p)
    os.makedirs(path, exist_ok=True)
    return made


def remove_made(made: list[str]) -> None:
    """Remove the folders ``make_folders`` created where they are still empty:
    those only (``os.removedirs`` would go on up through a user's empty folders)."""
    for folder in made:
        with contextlib.suppress(OSError):
            os.rmdir(folder)


def clean_stale(parent: str, name: str) -> list[str]:
    """Remove ``.NAME.tmp-PID-*`` folders of processes that are gone; notes on the rest.

    Only folders that hold ``MARKER`` are removed; anything else that looks
    like a leftover is reported, never deleted.
    """
    notes = []
    out = os.path.join(parent, name)
    pattern = re.compile(rf"^\.{re.escape(name)}\.(tmp|old)-(\d+-)?")
    with contextlib.suppress(OSError):
        for entry in sorted(os.listdir(parent)):
            m = pattern.match(entry)
            path = os.path.join(parent, entry)
            if not m or not os.path.isdir(path) or os.path.islink(path):
                continue
            pid = int(m.group(2)[:-1]) if m.group(2) else None
            if pid is not None and _alive(pid):
                continue
            if pid is not None and entry.endswith(".old") and not os.path.lexists(out):
                os.rename(path, out)  # died mid-swap (no atomic exchange): undo
                notes.append(f"restored {out} from {path}, left by an interrupted run")
            elif pid is not None and os.path.isfile(os.path.join(path, MARKER)):
                shutil.rmtree(path, ignore_errors=True)
                notes.append(f"removed {path}, left by an interrupted run")
            else:
                notes.append(f"{path} looks like a leftover of an interrupted run; "
                             "fitter leaves it to you (delete it if nothing in it is needed)")
    return notes


def _swap_in(tmp: str, out: str) -> None:
    """Put ``tmp`` at ``out``; afterwards ``tmp`` holds the old ``out`` (or nothing)."""
    for _ in range(3):  # another run may create or replace ``out`` meanwhile
        if not os.path.lexists(out):
            try:
                _rename(tmp, out, noreplace=True)
                os.mkdir(tmp)  # so the caller's clean-up finds a folder either way
                return
            except FileExistsError:
                continue
        check_out(out)  # it may have changed since the fit started
        try:
            _exchange(tmp, out)
            return
        except FileNotFoundError:
            continue
    raise OutputError(f"{out}: kept changing while fitter tried to replace it; "
                      "is another run writing the same --out?")


_RENAME_NOREPLACE, _RENAME_EXCHANGE = 1, 2
_AT_FDCWD = -100


def _renameat2(src: str, dst: str, flags: int) -> bool:
    """``renameat2``; False where the kernel, libc or filesystem lacks it."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    if fn(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), flags) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), dst)


def _rename(src: str, dst: str, noreplace: bool) -> None:
    if not _renameat2(src, dst, _RENAME_NOREPLACE if noreplace else 0):
        if noreplace and os.path.lexists(dst):
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), dst)
        os.rename(src, dst)


def _exchange(tmp: str, out: str) -> None:
    if _renameat2(tmp, out, _RENAME_EXCHANGE):
        return
    # No atomic exchange here: the old folder is moved aside under a name the
    # next run restores (see clean_stale) if this process dies in between.
    aside = f"{tmp}.old"
    os.rename(out, aside)
    os.rename(tmp, out)
    os.rename(aside, tmp)


def _write_marker(folder: str) -> None:
    from . import __version__

    with open(os.path.join(folder, MARKER), "w", encoding="utf-8") as fh:
        json.dump({"written_by": "fitter", "version": __version__,
                   "note": "fitter may replace this folder on a later run"}, fh)
        fh.write("\n")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _existing_ancestor(path: str) -> str:
    while not os.path.isdir(path):
        path = os.path.dirname(path)
    return path


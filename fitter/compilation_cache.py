"""JAX's persistent compilation cache, shared by the commands and batch workers.

``enable_compilation_cache()`` keeps compiled solvers on disk (and, through
``fitter.fit._cache``, their traces), so a repeated job -- in a later
``fitter fit`` or on another ``fitter batch`` worker -- skips XLA compilation.
Importing this module is free; JAX is imported only when the cache is set.
``FAST_COMPILE`` holds the XLA options the fit's executables are compiled with.
``cached_arrays`` keeps a scene-independent table (the sky stencil's) beside
the cache, so a later process loads it instead of computing it again.

fitter's own files there are named ``fitter-<kind>-<made by>-<key>.<ext>``
(``made_by``: a hash of the sources and libraries that wrote it). Storing one
removes the files of its kind made by other sources but the last other one
(``remove_stale``): without this each upgrade (or, in development, each edit)
left ~0.25 GB of sky tables behind -- a development cache reached 9.3 GB, 6.9
GB of it tables no code could read. JAX's own entries are JAX's.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import pathlib
import re
import tempfile

#: XLA compiler options of the fitter's executables (``jax.jit(...,
#: compiler_options=...)`` or ``.compile(options)``). XLA's CPU fusion
#: emitters (MLIR, on by default in jax 0.10) compile the renderer's graphs
#: about twice as slowly as the older emitters, for code no faster: measured on
#: the dielectric (128^2) solve, compile 2.7 -> 1.4 s, a solve 1.17 -> 1.12 s;
#: its start check 2.1 -> 1.2 s, 35 -> 24 ms. Results change by rounding only.
#: A field of XLA's DebugOptions, so every backend accepts it; only the CPU
#: compiler reads it.
FAST_COMPILE = {"xla_cpu_use_fusion_emitters": False}
#: ``FAST_COMPILE`` without XLA's YNNPACK library fusions, for gather-heavy
#: elementwise graphs: the sky table (``fitter.skystencil.sky_table``, per env
#: sample and stencil cell: a rotation, atan2s and mip-map gathers) ran 1.6 ->
#: 1.1 s at 128^2 with them off, as YNNPACK ran its small products and norms
#: as separate library calls. The fit's executables keep them: their batched
#: sky sums are YNNPACK dots (env_plastic's compiled fit 1.8 -> 2.8 s without).
NO_LIBRARY_FUSIONS = {**FAST_COMPILE, "xla_cpu_experimental_ynn_fusion_type": ""}


def cache_dir() -> str:
    """The cache folder: ``$FITTER_CACHE_DIR``, else ``$XDG_CACHE_HOME/fitter/jax``
    (default ``~/.cache/fitter/jax``); ``""`` when ``FITTER_CACHE_DIR=""`` turns it off."""
    folder = os.environ.get("FITTER_CACHE_DIR")
    if folder is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        folder = os.path.join(base, "fitter", "jax")
    return folder


def enable_compilation_cache() -> None:
    """Point JAX's persistent compilation cache at ``cache_dir()`` (nothing if off).

    Set only by code that compiles (after its inputs are checked): the CLI's
    ``fit`` and ``render``, and each ``fitter batch`` job on its worker.
    """
    folder = cache_dir()
    if not folder:
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def active_dir() -> str:
    """The folder of JAX's persistent cache if code set one (``enable_compilation_cache``),
    else ``""``; without JAX imported, ``""``."""
    import sys

    jax = sys.modules.get("jax")
    return (getattr(jax.config, "jax_compilation_cache_dir", None) or "") if jax else ""


@functools.lru_cache(maxsize=1)
def sources_fingerprint() -> str:
    """SHA-256 of fitter's Python sources (what a cached file was made by)."""
    h = hashlib.sha256()
    for path in sorted(pathlib.Path(__file__).resolve().parent.rglob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()


def store_atomically(folder: str, path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (a reader never sees half a file)."""
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


#: (folder, kind, made by) swept by ``remove_stale`` in this process.
_SWEPT: set = set()


def remove_stale(folder: str, kind: str, made_by: str, ext: str, legacy: str) -> int:
    """Remove the files of ``kind`` in ``folder`` made by other sources
    (``fitter-<kind>-<other 16 hex>-<32 hex>.<ext>``), except those of the
    other sources that wrote last, and those of the names before the tag
    (``legacy``, a regular expression of a whole name); the number removed.
    Two versions used in turn on one folder (an installed one and a checkout)
    so keep each other's files instead of making them again on every run,
    and a string of versions (each edit, in development) leaves two behind.
    No other file is touched; a file in use elsewhere that vanishes is made
    again by its reader (as a corrupt one is)."""
    if (folder, kind, made_by) in _SWEPT:  # once a process: later files are all ours
        return 0
    _SWEPT.add((folder, kind, made_by))
    tagged = re.compile(rf"fitter-{re.escape(kind)}-([0-9a-f]{{16}})-[0-9a-f]{{32}}\.{ext}")
    before_tags = re.compile(legacy)
    doomed, others = [], {}
    with contextlib.suppress(OSError):
        for entry in os.scandir(folder):
            m = tagged.fullmatch(entry.name)
            if m is not None and m.group(1) != made_by:
                with contextlib.suppress(OSError):
                    others.setdefault(m.group(1), []).append((entry.stat().st_mtime, entry.path))
            elif m is None and before_tags.fullmatch(entry.name):
                doomed.append(entry.path)
    last = max(others, key=lambda tag: max(others[tag])[0], default=None)
    doomed += [path for tag, files in others.items() if tag != last for _, path in files]
    removed = 0
    for path in doomed:
        with contextlib.suppress(OSError):
            os.unlink(path)
            removed += 1
    return removed


def cached_arrays(name: str, key: str, make):
    """``make()`` (a tuple of NumPy arrays), kept in the active cache folder
    (``active_dir``) under a name hashing ``key`` and tagged by NumPy's version
    and fitter's sources, and loaded from there by later processes. Without a
    cache folder, or on any problem with the file, ``make()`` itself. Storing
    one removes this ``name``'s files of other sources but the last other's
    (``remove_stale``)."""
    import numpy as np

    folder = active_dir()
    if not folder:
        return make()
    made_by = hashlib.sha256((np.__version__ + sources_fingerprint()).encode()).hexdigest()[:16]
    digest = hashlib.sha256((name + key).encode()).hexdigest()[:32]
    path = os.path.join(folder, f"fitter-{name}-{made_by}-{digest}.npz")
    try:
        with np.load(path, allow_pickle=False) as f:
            return tuple(f[f"a{i}"] for i in range(len(f.files)))
    except Exception:  # noqa: BLE001 (missing, stale or unreadable: made anew below)
        pass
    arrays = make()
    with contextlib.suppress(Exception):  # a cache problem must never stop the work
        import io

        buf = io.BytesIO()
        np.savez(buf, **{f"a{i}": a for i, a in enumerate(arrays)})
        store_atomically(folder, path, buf.getvalue())
        remove_stale(folder, name, made_by, "npz", rf"fitter-{re.escape(name)}-[0-9a-f]{{32}}\.npz")
    return arrays

"""JAX's persistent compilation cache, shared by the commands and batch workers.

``enable_compilation_cache()`` keeps compiled solvers on disk (and, through
``fitter.fit._cache``, their traces), so a repeated job -- in a later
``fitter fit`` or on another ``fitter batch`` worker -- skips XLA compilation.
Importing this module is free; JAX is imported only when the cache is set.
``FAST_COMPILE`` holds the XLA options the fit's executables are compiled with.
``cached_arrays`` keeps a scene-independent table (the sky stencil's) beside
the cache, so a later process loads it instead of computing it again.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import pathlib
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


def cached_arrays(name: str, key: str, make):
    """``make()`` (a tuple of NumPy arrays), kept in the active cache folder
    (``active_dir``) under a name hashing ``key``, NumPy's version and fitter's
    sources, and loaded from there by later processes. Without a cache folder,
    or on any problem with the file, ``make()`` itself."""
    import numpy as np

    folder = active_dir()
    if not folder:
        return make()
    digest = hashlib.sha256((name + key + np.__version__ + sources_fingerprint()).encode())
    path = os.path.join(folder, f"fitter-{name}-{digest.hexdigest()[:32]}.npz")
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
    return arrays

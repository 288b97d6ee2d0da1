"""JAX's persistent compilation cache, shared by the commands and batch workers.

``enable_compilation_cache()`` keeps compiled solvers on disk (and, through
``fitter.fit._cache``, their traces), so a repeated job -- in a later
``fitter fit`` or on another ``fitter batch`` worker -- skips XLA compilation.
Importing this module is free; JAX is imported only when the cache is set.
``FAST_COMPILE`` holds the XLA options the fit's executables are compiled with.
"""

from __future__ import annotations

import os

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

"""Traced solvers kept on disk, so a repeated job neither traces nor compiles.

JAX's persistent compilation cache (enabled by the CLI, see
``fitter.compilation_cache``) only skips XLA's compilation; tracing
an optimistix solve through the renderer still costs about a second. When that
cache is on, the traced function is also exported (``jax.export``, StableHLO
serialised with flatbuffers) next to it and reloaded by later processes; XLA
then finds the compiled code in its own cache. The file name hashes the call's
structure and shapes, the JAX and solver libraries' versions and the fitter
sources, so a change of any of them traces anew. A cached trace runs without
optimistix (``_solvers.outcome_table`` names its result codes). Any problem with the files falls back to tracing.
"""

from __future__ import annotations

import functools
import hashlib
import os

import jax
from jax import export

from ..bsdf.base import Cosines
from ..compilation_cache import active_dir, remove_stale, sources_fingerprint, store_atomically
from ..environment import EnvData
from ..geometry import Geometry
from ..suncells import SunCells
from ._problem import Data

for _cls in (Data, Geometry, Cosines, EnvData, SunCells):
    export.register_namedtuple_serialization(_cls, serialized_name=f"fitter.{_cls.__name__}")


@functools.lru_cache(maxsize=1)
def _source_fingerprint() -> str:
    from ._solvers import library_versions  # a trace holds their code and result codes

    return hashlib.sha256((jax.__version__ + library_versions()
                           + sources_fingerprint()).encode()).hexdigest()


def compile_cached(f, args, key: str, options: dict | None = None):
    """``jax.jit(f).lower(*args).compile(options)``, reusing an exported trace if one
    is on disk. ``options``: XLA compiler options (part of XLA's cache key).

    A file that cannot be read back or no longer fits ``args`` (truncated,
    corrupt, from an incompatible JAX) is replaced by a fresh export, so only
    one run pays for tracing again; if that fails too, the fit traces as if
    there were no cache.
    """
    return _cached(f, args, key, lambda lowered: lowered.compile(options))


def lower_cached(f, args, key: str):
    """``jax.jit(f).lower(*args)``, from an exported trace on disk as in
    ``compile_cached`` (a trace that lowers but does not compile is left to it).
    Tracing holds the interpreter and XLA's compile does not: a caller may trace
    here and compile the result on a thread."""
    return _cached(f, args, key, lambda lowered: lowered)


def _cached(f, args, key: str, finish):
    """``finish(jax.jit(g).lower(*args))`` with g the exported trace on disk, else a
    fresh export (stored), else ``f`` itself."""
    folder = active_dir()
    if not folder:
        return finish(jax.jit(f).lower(*args))
    made_by = _source_fingerprint()
    digest = hashlib.sha256((key + made_by).encode()).hexdigest()[:32]
    path = os.path.join(folder, f"fitter-trace-{made_by[:16]}-{digest}.jaxexport")
    try:
        with open(path, "rb") as fh:
            exported = export.deserialize(bytearray(fh.read()))
        return finish(jax.jit(exported.call).lower(*args))
    except Exception:  # noqa: BLE001 (missing, stale or unreadable: export anew below)
        pass
    try:
        exported = export.export(jax.jit(f))(*args)
        store_atomically(folder, path, exported.serialize())
        # (the traces of other sources: no later run reads them)
        remove_stale(folder, "trace", made_by[:16], "jaxexport", r"fitter-[0-9a-f]{32}\.jaxexport")
        return finish(jax.jit(exported.call).lower(*args))
    except Exception:  # noqa: BLE001 (a cache problem must never break a fit)
        return finish(jax.jit(f).lower(*args))

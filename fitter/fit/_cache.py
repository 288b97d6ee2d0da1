"""Traced solvers kept on disk, so a repeated job neither traces nor compiles.

JAX's persistent compilation cache (enabled by the CLI, see
``fitter.cli._enable_compilation_cache``) only skips XLA's compilation; tracing
an optimistix solve through the renderer still costs about a second. When that
cache is on, the traced function is also exported (``jax.export``, StableHLO
serialised with flatbuffers) next to it and reloaded by later processes; XLA
then finds the compiled code in its own cache. The file name hashes the call's
structure and shapes, the JAX version and the fitter sources, so a change of
any of them traces anew. Any problem with the files falls back to tracing.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pathlib
import tempfile

import jax
from jax import export

from ..bsdf.base import Cosines
from ..environment import EnvData
from ..geometry import Geometry
from ._problem import Data

for _cls in (Data, Geometry, Cosines, EnvData):
    export.register_namedtuple_serialization(_cls, serialized_name=f"fitter.{_cls.__name__}")


@functools.lru_cache(maxsize=1)
def _source_fingerprint() -> str:
    root = pathlib.Path(__file__).resolve().parents[1]
    h = hashlib.sha256(jax.__version__.encode())
    for path in sorted(root.rglob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()


def compile_cached(f, args, key: str, options: dict | None = None):
    """``jax.jit(f).lower(*args).compile(options)``, reusing an exported trace if one
    is on disk. ``options``: XLA compiler options (part of XLA's cache key)."""
    folder = jax.config.jax_compilation_cache_dir
    if not folder:
        return jax.jit(f).lower(*args).compile(options)
    digest = hashlib.sha256((key + _source_fingerprint()).encode()).hexdigest()[:32]
    path = os.path.join(folder, f"fitter-{digest}.jaxexport")
    try:
        if os.path.exists(path):
            with open(path, "rb") as fh:
                exported = export.deserialize(bytearray(fh.read()))
        else:
            exported = export.export(jax.jit(f))(*args)
            os.makedirs(folder, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-")
            with os.fdopen(fd, "wb") as fh:
                fh.write(exported.serialize())
            os.replace(tmp, path)
        return jax.jit(exported.call).lower(*args).compile(options)
    except Exception:  # a stale or unreadable file must never break a fit
        return jax.jit(f).lower(*args).compile(options)

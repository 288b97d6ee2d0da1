"""Choosing the Mitsuba variant, and making sure drjit gets a usable LLVM.

``llvm_ad_rgb`` runs on the CPU through LLVM; drjit needs libLLVM >= 16
(Debian 12's LLVM 15 aborts the whole process with ``LLVM ERROR: Cannot
select ... fmaximum`` on the first ``roughconductor`` kernel). So before
drjit is first imported we look for the newest libLLVM in the usual folders
and point ``DRJIT_LIBLLVM_PATH`` at it, and after the variant is set we check
the version drjit actually loaded and stop with an actionable message.
"""

from __future__ import annotations

import glob
import os
import re
import sys

from ..errors import FitterError

ENV_VAR = "FITTER_MITSUBA_VARIANT"
CPU_VARIANT = "llvm_ad_rgb"
GPU_VARIANT = "cuda_ad_rgb"
LLVM_MIN = 16

_LLVM_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64",
              "/usr/lib", "/usr/local/lib", "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib")
_LLVM_FIX = ("install a newer LLVM (`apt-get install -y libllvm19`) or set DRJIT_LIBLLVM_PATH "
             "to a libLLVM.so of version >= 16")


class MitsubaError(FitterError, RuntimeError):
    """Mitsuba cannot render this request (message says what to change)."""


def _llvm_version(path: str) -> int:
    m = re.search(r"LLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
    return int(m.group(1)) if m else 0


def find_libllvm(dirs=_LLVM_DIRS) -> str | None:
    """Path of the newest libLLVM >= 16 in ``dirs``, or None."""
    found = []
    for d in dirs:
        for path in glob.glob(os.path.join(d, "libLLVM*.so*")) + glob.glob(
                os.path.join(d, "libLLVM*.dylib")):
            v = _llvm_version(path)
            if v >= LLVM_MIN:
                found.append((v, path))
    return max(found)[1] if found else None


def _prepare_llvm() -> None:
    """Point drjit at a new enough libLLVM before drjit is imported (no-op after)."""
    if "drjit" in sys.modules or os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    path = find_libllvm()
    if path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path


def _gpu_present() -> bool:
    return os.path.exists("/dev/nvidia0") or os.path.exists("/dev/nvidiactl")


def choose_variant(variant: str | None = None) -> str:
    """The variant to use: the argument, else $FITTER_MITSUBA_VARIANT, else
    ``cuda_ad_rgb`` when an NVIDIA GPU is present, else ``llvm_ad_rgb``."""
    if variant:
        return variant
    if os.environ.get(ENV_VAR):
        return os.environ[ENV_VAR]
    return GPU_VARIANT if _gpu_present() else CPU_VARIANT


def load(variant: str | None = None):
    """Import Mitsuba, set the variant, check the JIT backend; returns ``(mi, variant)``.

    Raises MitsubaError with one sentence if the variant does not exist or the
    backend is unusable (an LLVM older than 16, no CUDA device).
    """
    explicit = bool(variant) or bool(os.environ.get(ENV_VAR))
    variant = choose_variant(variant)
    _prepare_llvm()
    import drjit as dr
    import mitsuba as mi

    if variant not in mi.variants():
        raise MitsubaError(f"Mitsuba variant {variant!r} is not available; "
                           f"available: {', '.join(mi.variants())}")
    if variant.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
        if explicit:
            raise MitsubaError(f"Mitsuba variant {variant!r} needs a CUDA GPU, none is usable; "
                               f"use {CPU_VARIANT!r} (set {ENV_VAR})")
        variant = CPU_VARIANT
    if variant.startswith("llvm"):
        if not dr.has_backend(dr.JitBackend.LLVM):
            raise MitsubaError("drjit found no usable libLLVM for the CPU variant; " + _LLVM_FIX)
        major = dr.detail.llvm_version()[0]
        if major < LLVM_MIN:
            raise MitsubaError(f"drjit loaded LLVM {major}, which aborts Mitsuba's kernels; "
                               + _LLVM_FIX)
    mi.set_variant(variant)
    return mi, variant

"""What one job may cost, checked before any work: memory, starts, samples.

A request over a limit is a ``ResourceError`` (exit 2 in the CLI) that states
the estimate and how to reduce it, instead of a process the kernel kills
without a word. The memory model is measured (``fitter fit`` peak RSS,
lambert + torrance_sparrow, 2 point lights, on the 2-core CI machine):
256^2 x 4^2 samples 0.9 GB, 512^2 x 4^2 1.8 GB, 1024^2 x 4^2 6.0 GB, i.e.
about ``BASE_BYTES`` plus ``BYTES_PER_SAMPLE`` per film sample.
"""

from __future__ import annotations

import os

from .errors import FitterError

#: Most multi-start starts (each is a full solve; 1024 already takes minutes).
MAX_STARTS = 1024
#: Most sub-pixel samples per axis (k^2 samples per pixel; 16 -> 256).
MAX_SUPERSAMPLING = 16
#: Most samples per pixel of a Mitsuba validation or synth render.
MAX_SPP = 1 << 16
#: Fit memory: fixed part and bytes per film sample (see the module docstring).
BASE_BYTES = 0.6e9
BYTES_PER_SAMPLE = 350.0
#: Extra fit memory per pixel when an environment lights opaque lobes (its
#: sky table, ``fitter.envlight``): peak RSS 1.6 GB at 128^2 (env_plastic, CLI
#: fit with the discretisation term), ~55 kB a pixel above the rest; twice that
#: for a margin.
ENV_BYTES_PER_PIXEL = 1.1e5
#: Share of the machine's available memory a fit may plan to use.
MEMORY_SHARE = 0.8


class ResourceError(FitterError):
    """A request larger than this machine or the documented limits allow."""


def fit_bytes(width: int, height: int, supersampling: int, env_lit: bool = False) -> float:
    """Estimated peak memory (bytes) of a fit at this film size (``env_lit``: an
    environment lights opaque lobes)."""
    return (BASE_BYTES + BYTES_PER_SAMPLE * width * height * supersampling ** 2
            + (ENV_BYTES_PER_PIXEL * width * height if env_lit else 0.0))


def available_bytes() -> float | None:
    """Memory the kernel says is available now (``MemAvailable``), None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_fit(width: int, height: int, supersampling: int, n_starts: int,
              where: str = "", env_lit: bool = False) -> None:
    """Raise ``ResourceError`` if a fit of this size cannot run here.

    ``where`` prefixes the message (a config path, or "" for the Python API).
    """
    at = f"{where}: " if where else ""
    if n_starts > MAX_STARTS:
        raise ResourceError(f"{at}fit.n_starts = {n_starts} is over the limit of {MAX_STARTS} "
                            "starts; use fewer starts")
    if supersampling > MAX_SUPERSAMPLING:
        raise ResourceError(f"{at}scene.supersampling = {supersampling} is over the limit of "
                            f"{MAX_SUPERSAMPLING} (that is {MAX_SUPERSAMPLING ** 2} samples a "
                            "pixel); 4 is enough for smooth lobes")
    need = fit_bytes(width, height, supersampling, env_lit)
    have = available_bytes()
    if have is not None and need > MEMORY_SHARE * have:
        raise ResourceError(
            f"{at}a {width}x{height} fit at scene.supersampling = {supersampling}"
            f"{' lit by its environment' if env_lit else ''} needs about "
            f"{need / 1e9:.1f} GB of memory and this machine has {have / 1e9:.1f} GB "
            "available; lower scene.supersampling or the image size (or crop the image to "
            "the sphere)")


def check_spp(spp: int, key: str, where: str = "") -> None:
    """Raise ``ResourceError`` for a Mitsuba sample count over ``MAX_SPP``."""
    if spp > MAX_SPP:
        at = f"{where}: " if where else ""
        raise ResourceError(f"{at}{key} = {spp} is over the limit of {MAX_SPP} samples per "
                            "pixel; use fewer samples")

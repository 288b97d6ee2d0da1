"""What one job may cost, checked before any work: memory, starts, samples.

A request over a limit is a ``ResourceError`` (exit 2 in the CLI) that states
the estimate and how to reduce it, instead of a process the kernel kills
without a word. The memory model (``MEMORY_MODEL``) is measured: peak RSS of
one fit or render in a fresh process, per pixel and per film sample, with and
without an environment lighting the opaque lobes
(``benchmarks/memory_model.py``).
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
#: Peak memory of one job, (fixed bytes, bytes per pixel, bytes per film sample),
#: by (task, whether an environment lights opaque lobes). Measured
#: (``benchmarks/memory_model.py``, 2026-12-05: lambert + torrance_sparrow, the
#: shipped "plastic" (2 point lights) and "env_plastic" scenes, fresh processes,
#: repeated runs differing by up to 8 %) and chosen so that each estimate is 5-40 %
#: above every measured peak. A fit: point-lit 256^2 x 4^2 samples 1.05-1.09 GB,
#: 1024^2 x 4^2 5.4-6.2 GB; env-lit 128^2 x 4^2 1.6-1.7 GB, 128^2 x 8^2 3.4-3.5 GB,
#: 512^2 x 4^2 11.8 GB (the sky table per env sample, the sun's cells per
#: highlight sample and the finer model of the stated errors). A render:
#: point-lit 1024^2 x 4^2 5.3-5.5 GB (5.5 since the lights' samples carry their
#: cotangents, ``Cosines``), env-lit 512^2 x 4^2 8.6-8.8 GB.
MEMORY_MODEL = {
    ("fit", False): (0.8e9, 0.0, 350.0),
    ("fit", True): (0.9e9, 1.3e4, 2650.0),
    ("render", False): (0.3e9, 0.0, 340.0),
    ("render", True): (0.55e9, 8e3, 1600.0),
}
#: Peak memory an envmap adds, per texel of its file (its float64 read and device copy,
#: beside the model's film terms, which the shipped 128-wide probe calibrated): measured
#: 25-45 bytes a texel with the probe's scene 2048, 4096 and 8192 wide (fits at 128^2 x
#: 4^2 of 1.8, 2.1 and 2.5 GB peak RSS), 48 estimated.
ENVMAP_BYTES_PER_TEXEL = 48.0
#: Peak memory a sun cell adds per film sample (width x height x k^2), by task, beyond
#: ``CALIBRATED_SUN_CELLS`` (``envlight.split_sun``: a bright source lights the opaque
#: lobes as that many directional lights on every sub-pixel sample near its highlight,
#: in the fitted model and, for a fit, in the stated errors' finer ones). Measured with
#: the probe's sun made 10 and 20 deg wide (100-308 cells, 128^2 at k = 2 and 4, the sun
#: where the probe has it and behind the camera): a fit 57-66 bytes, a render 7.5. A 20
#: deg sun took a 128^2 fit to 5.7-6.6 GB and a 256^2 one past 17 GB, where the model
#: without this term said 1.8 and 4.5; at 256^2 a 10 deg sun (100 cells) peaked at
#: 4.5 GB, estimated 9.9 with this term (the finer model then samples its pixels,
#: ``fit._discretisation.MAX_FINER_SAMPLES``): an over-statement, never an under one.
#: Since the fitted geometry's pairs keep their cotangents (``suncells.sun_samples``,
#: 16 bytes a pair: ~2.1 bytes a cell and film sample at the measured suns' 0.13 pairs
#: a film sample) 80 and 12, from 75 and 9 (the 20 deg fit's 6.59 GB against 6.61
#: estimated would have been under-stated).
SUN_CELL_BYTES = {"fit": 80.0, "render": 12.0}
#: Sun cells of the shipped probe (a 3 deg sun), which ``MEMORY_MODEL`` includes.
CALIBRATED_SUN_CELLS = 32
#: Share of the machine's available memory a fit may plan to use.
MEMORY_SHARE = 0.8


class ResourceError(FitterError):
    """A request larger than this machine or the documented limits allow."""


def job_bytes(task: str, width: int, height: int, supersampling: int,
              env_lit: bool = False, env_texels: int = 0, sun_cells: int = 0) -> float:
    """Estimated peak memory (bytes) of a ``task`` ("fit" or "render") at this
    film size (``env_lit``: an environment lights opaque lobes; ``env_texels``: its
    envmap's size; ``sun_cells``: its sun's cells); ``MEMORY_MODEL``,
    ``ENVMAP_BYTES_PER_TEXEL``, ``SUN_CELL_BYTES``."""
    fixed, per_pixel, per_sample = MEMORY_MODEL[(task, bool(env_lit))]
    samples = float(width) * float(height) * supersampling ** 2
    extra_cells = max(sun_cells - CALIBRATED_SUN_CELLS, 0) if env_lit else 0
    return (fixed + per_pixel * float(width) * float(height) + per_sample * samples
            + ENVMAP_BYTES_PER_TEXEL * env_texels + SUN_CELL_BYTES[task] * extra_cells * samples)


def envmap_texels(scene, base_dir: str | None = None) -> int:
    """Texels of the scene's envmap, read from its file's header (0 without one, or
    where the header cannot be read: reading the map says why)."""
    env = scene.environment
    if env.type != "envmap" or not env.file:
        return 0
    from .imageio import image_size
    from .scene import resolve_path

    try:
        width, height = image_size(resolve_path(env.file, base_dir))
    except Exception:  # noqa: BLE001 (the read names the problem)
        return 0
    return width * height


def sun_cell_count(scene, material, base_dir: str | None = None) -> int:
    """Cells of the sun lighting ``material``'s opaque lobes (``envlight.env_lights``,
    which the fit then reuses); 0 without an envmap lighting them, or where the map
    cannot be read (reading it says why)."""
    from .envlight import env_lights, lit_by_environment

    env = scene.environment
    if env.type != "envmap" or not lit_by_environment(scene, material):
        return 0
    from .environment import load_environment
    from .hugepages import advice_off

    @advice_off  # (a wide map's read and pyramid are large: ``fitter.hugepages``)
    def split():
        data = load_environment(env, base_dir)
        return env_lights(env.type, data.image, data.constant)

    try:
        lights = split()
    except Exception:  # noqa: BLE001 (the read names the problem)
        return 0
    return 0 if lights is None else int(lights.sun_dir.shape[0])


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


def scene_bytes(task: str, scene, material, base_dir: str | None = None) -> float:
    """``job_bytes`` of a ``task`` on ``scene`` with ``material`` (env-lit where its
    environment lights an opaque lobe, ``envlight.lit_by_environment``; its envmap's
    texels, ``envmap_texels``; its sun's cells, ``sun_cell_count``)."""
    return job_bytes(task, scene.width, scene.height, scene.supersampling,
                     *_env_terms(scene, material, base_dir))


def _env_terms(scene, material, base_dir) -> tuple:
    """``job_bytes``' (env_lit, env_texels, sun_cells) of a scene and material."""
    from .envlight import lit_by_environment

    return (lit_by_environment(scene, material), envmap_texels(scene, base_dir),
            sun_cell_count(scene, material, base_dir))


def check_scene(task: str, scene, material, where: str = "", n_starts: int = 1,
                base_dir: str | None = None) -> None:
    """``check_fit`` (``task`` "fit") or the same check of a render, of ``scene``
    with ``material`` (an envmap's path relative to ``base_dir``): what
    ``fitter.fit``, ``fitter.render`` and the CLI check before any work."""
    args = (scene.width, scene.height, scene.supersampling)
    env = _env_terms(scene, material, base_dir)
    if task == "fit":
        check_fit(*args, n_starts, where, *env)
    else:
        _check_film(task, *args, where, *env)


def check_fit(width: int, height: int, supersampling: int, n_starts: int,
              where: str = "", env_lit: bool = False, env_texels: int = 0,
              sun_cells: int = 0) -> None:
    """Raise ``ResourceError`` if a fit of this size cannot run here.

    ``where`` prefixes the message (a config path, or "" for the Python API).
    """
    if n_starts > MAX_STARTS:
        at = f"{where}: " if where else ""
        raise ResourceError(f"{at}fit.n_starts = {n_starts} is over the limit of {MAX_STARTS} "
                            "starts; use fewer starts")
    _check_film("fit", width, height, supersampling, where, env_lit, env_texels, sun_cells)


def _check_film(task: str, width: int, height: int, supersampling: int, where: str,
                env_lit: bool, env_texels: int = 0, sun_cells: int = 0) -> None:
    """Raise ``ResourceError`` over ``MAX_SUPERSAMPLING``, or where ``job_bytes``
    is over ``MEMORY_SHARE`` of the memory available now."""
    at = f"{where}: " if where else ""
    if supersampling > MAX_SUPERSAMPLING:
        raise ResourceError(f"{at}scene.supersampling = {supersampling} is over the limit of "
                            f"{MAX_SUPERSAMPLING} (that is {MAX_SUPERSAMPLING ** 2} samples a "
                            "pixel); 4 is enough for smooth lobes")
    need = job_bytes(task, width, height, supersampling, env_lit, env_texels, sun_cells)
    have = available_bytes()
    if have is not None and need > MEMORY_SHARE * have:
        big_sun = env_lit and sun_cells > CALIBRATED_SUN_CELLS
        raise ResourceError(
            f"{at}a {width}x{height} {task} at scene.supersampling = {supersampling}"
            f"{' lit by its environment' if env_lit else ''}"
            f"{f' with an envmap of {env_texels / 1e6:.1f} M texels' if env_texels else ''}"
            f"{f' whose bright source makes {sun_cells} sun cells' if big_sun else ''}"
            " needs about "
            f"{need / 1e9:.1f} GB of memory and this machine has {have / 1e9:.1f} GB "
            "available; lower scene.supersampling or the image size (or crop the image to "
            f"the sphere){', or use a narrower envmap' if env_texels and not big_sun else ''}"
            f"{', or an envmap with a smaller bright source' if big_sun else ''}")


def check_spp(spp: int, key: str, where: str = "") -> None:
    """Raise ``ResourceError`` for a Mitsuba sample count over ``MAX_SPP``."""
    if spp > MAX_SPP:
        at = f"{where}: " if where else ""
        raise ResourceError(f"{at}{key} = {spp} is over the limit of {MAX_SPP} samples per "
                            "pixel; use fewer samples")

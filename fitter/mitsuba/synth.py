"""Synthetic targets rendered by Mitsuba 3: one folder per case.

``write_case`` writes ``target.exr`` (float32 linear RGB), ``preview.png``
(sRGB) and ``case.json`` (scene, material, truth, Mitsuba settings), each
atomically; the same Mitsuba version, variant, spp and seed give the same
bytes. ``generate_all(root)`` renders every case of ``fitter.cases``.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np

from .. import serialize
from ..imageio import atomic_write, write_image
from ..material import Material
from ..scene import Scene, resolve_path


#: A fixed file time stamp: OpenImageIO otherwise writes the current time.
_FIXED_STAMP = {"DateTime": "2000:01:01 00:00:00"}


def make_envmap(path: str, width: int = 64, height: int = 32) -> None:
    """Write a small asymmetric latitude-longitude EXR (Mitsuba's envmap mapping).

    A blue-to-white sky over a brown ground, a warm "sun" blob at azimuth
    u = 0.3, elevation 35 deg, and a green panel at u = 0.75: every direction
    reads differently, so a flipped or rotated mapping shows. Linear RGB.
    """
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    u = (u + 0.5) / width
    theta = v / (height - 1) * np.pi  # 0 = up (+y)
    elev = np.pi / 2 - theta
    sky = np.where(elev[..., None] > 0,
                   np.stack([0.3 + 0.5 * np.cos(elev), 0.5 + 0.4 * np.cos(elev),
                             np.full_like(elev, 1.0)], -1),
                   np.stack([0.25 + 0.1 * u, 0.18 + 0.0 * u, 0.1 + 0.0 * u], -1))
    sun_u, sun_e = 0.3, np.radians(35.0)
    d_ang = np.hypot((u - sun_u) * 2 * np.pi * np.cos(elev), elev - sun_e)
    sky = sky + np.array([6.0, 4.5, 3.0]) * np.exp(-(d_ang / 0.15) ** 2)[..., None]
    panel = (np.abs(u - 0.75) < 0.08) & (np.abs(elev - 0.1) < 0.35)
    sky = np.where(panel[..., None], np.array([0.1, 0.9, 0.2]), sky)
    write_image(path, sky, _FIXED_STAMP)


#: The HDR probe's sun: unit direction towards it, angular diameter (deg), radiance / sky.
PROBE_SUN = ((0.45, 0.55, 0.70), 3.0, 300.0)


def make_probe(path: str, width: int = 128, height: int = 64, sub: int = 8,
               suns: tuple = (PROBE_SUN,)) -> None:
    """Write a small HDR light probe (Mitsuba's lat-long mapping, linear RGB).

    A sky gradient (zenith blue, horizon pale) over a darker ground, a dim
    warm window (a rectangle left of the camera) and bright suns (``suns``: each
    a direction, angular diameter in degrees and radiance / sky; ``PROBE_SUN``:
    ~3 deg at ~300x the sky radiance near it), each texel the average of ``sub``
    x ``sub`` sub-samples so that a sun's disk is area-weighted.
    """
    s = sub
    v, u = np.mgrid[0:height * s, 0:width * s].astype(np.float64)
    u = ((u + 0.5) / s - 0.5 + 0.5) / width  # sub-samples about texel centres (i + 0.5) / W
    v = np.clip(((v + 0.5) / s - 0.5) / (height - 1), 0.0, 1.0)  # rows at v = j / (H - 1)
    phi, theta = 2 * np.pi * u, np.pi * v
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    elev = d[..., 1]
    up = np.clip(elev, 0.0, 1.0)[..., None]
    sky = (1 - up) * np.array([1.0, 1.0, 1.05]) + up * np.array([0.35, 0.55, 1.0])
    ground = np.array([0.25, 0.2, 0.15]) * (1.0 + 0.3 * np.sin(3 * phi))[..., None]
    rad = np.where((elev > 0)[..., None], sky, ground)
    window = (np.abs(np.arctan2(d[..., 0], -d[..., 2]) + 1.9) < 0.35) & (np.abs(elev - 0.2) < 0.25)
    rad = np.where(window[..., None], np.array([2.0, 1.7, 1.3]), rad)
    for sun, diam, ratio in suns:
        disk = d @ (np.asarray(sun) / np.linalg.norm(sun)) > np.cos(np.radians(diam / 2))
        rad = np.where(disk[..., None], ratio * np.array([1.0, 0.95, 0.85]), rad)
    img = rad.reshape(height, s, width, s, 3).mean((1, 3))
    write_image(path, img, _FIXED_STAMP)


def _env_for_json(scene: Scene, out_dir: str, base_dir: str | None) -> Scene:
    env = scene.environment
    if env.type != "envmap":
        return scene
    path = resolve_path(env.file, base_dir)
    rel = os.path.relpath(os.path.abspath(path), os.path.abspath(out_dir))
    return scene.replace(environment=env.__class__(type="envmap", file=rel, scale=env.scale))


def write_case(out_dir: str, scene: Scene, material: Material, params, *, spp: int, seed: int,
               variant: str | None = None, base_dir: str | None = None,
               extra: dict | None = None, paths_relative_to: str | None = None) -> dict:
    """Render the case with Mitsuba and write it to ``out_dir``; returns the case dict.

    ``case.json`` holds ``scene`` and ``material`` in the config layout
    (``fitter.serialize.scene_to_dict`` / ``material_to_dict``; an envmap path
    relative to ``paths_relative_to``, default ``out_dir``: pass the final
    folder when writing into a staging folder first), the full true parameters (``truth``, defaults
    included), ``mitsuba`` (version, variant, spp, seed, integrator,
    sampler) and ``extra``. Render time is returned, not written, so the
    files are reproducible.
    """
    from . import render
    from .variant import load
    from .translate import integrator_dict, stratified_spp

    truth = serialize.plain(material.full_params(params))
    t0 = time.perf_counter()
    img = render(scene, material, params, spp=spp, seed=seed, variant=variant, base_dir=base_dir)
    seconds = time.perf_counter() - t0
    mi, used = load(variant)
    case = {
        "scene": serialize.scene_to_dict(_env_for_json(scene, paths_relative_to or out_dir,
                                                       base_dir)),
        "material": serialize.material_to_dict(material, truth=truth),
        "truth": truth,
        "mitsuba": {"version": mi.__version__, "variant": used, "spp": stratified_spp(spp),
                    "seed": int(seed), "sampler": "stratified", "rfilter": "box",
                    "integrator": integrator_dict(material, scene)},
        **(extra or {}),
    }
    os.makedirs(out_dir, exist_ok=True)
    write_image(os.path.join(out_dir, "target.exr"), img, _FIXED_STAMP)
    write_image(os.path.join(out_dir, "preview.png"), img, _FIXED_STAMP)
    text = json.dumps(case, indent=2, sort_keys=True) + "\n"

    def _write(tmp):
        with open(tmp, "w") as fh:
            fh.write(text)

    atomic_write(os.path.join(out_dir, "case.json"), _write)
    case["render_time_s"] = seconds
    return case


def generate_all(root: str, names=None, *, variant: str | None = None, log=print) -> dict:
    """Regenerate ``root/envmap.exr`` and every case (or ``names``) under ``root``.

    Returns ``{name: render seconds}``.
    """
    from ..cases import CASES, ENVMAP, NOTES, PROBE

    os.makedirs(root, exist_ok=True)
    make_envmap(os.path.join(root, ENVMAP))
    make_probe(os.path.join(root, PROBE))
    times = {}
    for name in names or CASES:
        spec = CASES[name]
        out_dir = os.path.join(root, name)
        os.makedirs(out_dir, exist_ok=True)
        label = f"<case {name}>"
        scene = serialize.scene_from_dict(spec["scene"], label, base_dir=out_dir)
        material, truth, _, _ = serialize.material_from_dict(spec["material"], label)
        synth = serialize.synth_from_dict(spec["synth"], label)
        case = write_case(out_dir, scene, material, truth, spp=synth.spp, seed=synth.seed,
                          variant=variant, extra={"name": name, "description": NOTES[name]})
        times[name] = case["render_time_s"]
        if log:
            log(f"{name:22s} {case['render_time_s']:6.2f} s  spp {case['mitsuba']['spp']}")
    return times

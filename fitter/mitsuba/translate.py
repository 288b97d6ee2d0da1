"""The project's ``Scene`` + ``Material`` as a Mitsuba 3 scene dict of the same meaning.

=====================  ==========================================================
project                Mitsuba 3
=====================  ==========================================================
perspective camera     ``perspective``, ``fov_axis = "x"``, ``look_at`` frame
orthographic camera    ``orthographic``, ``look_at`` * scale(half_width)
k x k supersampling    ``hdrfilm`` + ``box`` filter (pixel-area average), many spp
point light            ``point`` (``intensity``, W/sr)
directional light      ``directional`` (``irradiance``)
environment            none (black), ``constant``, ``envmap`` (``scale``)
exposure               every emitter's radiance/intensity/irradiance/scale times it
                       (Mitsuba is linear in its emitters: the exposed image)
lobes                  ``Lobe.mitsuba(p, opts)``; several: ``fitter_sum``
interior medium        ``Lobe.mitsuba.interior`` (the dielectric's absorption)
integrator             ``direct`` (1 emitter sample, no BSDF samples) unless a lobe
                       asks for a depth (``Lobe.mitsuba.max_depth``) or an opaque
                       lobe sees a constant/envmap environment (``path``, MIS,
                       ``max_depth`` >= 2: exactly direct light on a convex
                       sphere), or ``volpathmis`` when a lobe has an interior medium
sampler                ``stratified`` (spp rounded up to a square), fixed seed
=====================  ==========================================================

The environment lights the opaque ("brdf") lobes in both (``fitter.envlight``
on the project's side). One difference in meaning is refused rather than
translated: a transmissive lobe (``Lobe.transmissive``) must be alone:
Mitsuba would apply the whole sum at the internal hits, the project traces
the interior with that lobe only.
"""

from __future__ import annotations

import math
import os

from ..bsdf.mitsuba_map import SIGMA_T_MAX as SIGMA_T_MAX, absorbing_medium, rgb as _rgb
from ..material import EXPOSURE_KEY, Material, lobe_params
from ..scene import DirectionalLight, PointLight, Scene, resolve_path
from .variant import MitsubaError

#: An absorbing medium (kept under its former name).
medium_dict = absorbing_medium


def stratified_spp(spp: int) -> int:
    """The sample count Mitsuba's ``stratified`` sampler uses: the next square."""
    if int(spp) < 1:
        raise MitsubaError(f"spp = {spp} must be >= 1")
    r = math.isqrt(int(spp) - 1) + 1
    return r * r


def _vec(v):
    return [float(x) for x in v]


def _mappings(material: Material):
    """(lobe, its Mitsuba mapping, its options) for each lobe of the material."""
    out = []
    for lobe in material.lobe_objects:
        if lobe.mitsuba is None:
            raise MitsubaError(f"lobe {lobe.name!r} has no Mitsuba mapping (Lobe.mitsuba)")
        out.append((lobe, lobe.mitsuba, material.options_of(lobe.name)))
    return out


def bsdf_dict(material: Material, params) -> dict:
    """The Mitsuba BSDF of the material's summed lobes (without any interior medium)."""
    full = material.full_params(params)
    parts = [m.bsdf(lobe_params(full, lobe.name), opts) for lobe, m, opts in _mappings(material)]
    if len(parts) == 1:
        return parts[0]
    return {"type": "fitter_sum", **{f"bsdf_{i}": d for i, d in enumerate(parts)}}


def interior_dict(material: Material, params) -> dict | None:
    """The medium inside the sphere, from the lobe that has one (None: vacuum)."""
    full = material.full_params(params)
    for lobe, m, opts in _mappings(material):
        medium = m.interior(lobe_params(full, lobe.name), opts) if m.interior else None
        if medium is not None:
            return medium
    return None


#: Path depth that is exactly direct light on an opaque convex sphere.
ENV_OPAQUE_DEPTH = 2


def integrator_dict(material: Material, scene: Scene | None = None) -> dict:
    """The integrator; ``scene`` says whether an environment lights opaque lobes."""
    maps = _mappings(material)
    depths = [m.max_depth(opts) for _, m, opts in maps if m.max_depth is not None]
    if scene is not None and scene.environment.type != "black" and material.opaque:
        depths.append(ENV_OPAQUE_DEPTH)
    if not depths:
        return {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}
    depth = max(depths)
    if any(m.interior is not None for _, m, _ in maps):
        # volpathmis = volpath + spectral MIS over the RGB channels: 3x less noise
        # than volpath for an RGB absorption (measured), same estimator otherwise.
        return {"type": "volpathmis", "max_depth": depth, "rr_depth": depth + 1}
    return {"type": "path", "max_depth": depth, "rr_depth": depth + 1}


def check_translatable(scene: Scene, material: Material) -> None:
    """Raise MitsubaError where Mitsuba would render a different meaning."""
    clear = [lb.name for lb in material.lobe_objects if lb.transmissive]
    if clear and len(material.lobes) > 1:
        raise MitsubaError(f"the Mitsuba translation supports the transmissive lobe {clear[0]!r} "
                           f"only on its own, not summed with "
                           f"{[n for n in material.lobes if n != clear[0]]}")


def _camera(mi, scene: Scene) -> dict:
    cam = scene.camera
    frame = mi.ScalarTransform4f().look_at(origin=_vec(cam.origin), target=_vec(cam.target),
                                           up=_vec(cam.up))
    if cam.type == "perspective":
        return {"type": "perspective", "fov": float(cam.fov), "fov_axis": "x",
                "to_world": frame}
    if cam.type == "orthographic":
        hw = float(cam.half_width)
        return {"type": "orthographic", "to_world": frame @ mi.ScalarTransform4f().scale([hw, hw, 1.0])}
    raise MitsubaError(f"camera.type = {cam.type!r}; allowed: 'perspective', 'orthographic'")


def exposure_of(material: Material, params) -> float:
    """The material's exposure in ``params`` (``fitter.material.EXPOSURE``), else 1."""
    return float(material.full_params(params)[EXPOSURE_KEY]) if material.exposure else 1.0


def _emitters(scene: Scene, base_dir, exposure: float = 1.0) -> dict:
    """Mitsuba's emitters of the scene, each scaled by ``exposure``."""
    x = float(exposure)
    scaled = lambda v: [float(c) * x for c in v]  # noqa: E731
    out = {}
    for i, light in enumerate(scene.lights):
        if isinstance(light, PointLight):
            out[f"light_{i}"] = {"type": "point", "position": _vec(light.position),
                                 "intensity": _rgb(scaled(light.intensity))}
        elif isinstance(light, DirectionalLight):
            out[f"light_{i}"] = {"type": "directional", "direction": _vec(light.direction),
                                 "irradiance": _rgb(scaled(light.irradiance))}
        else:
            raise MitsubaError(f"unknown light {light!r}")
    env = scene.environment
    if env.type == "constant":
        out["environment"] = {"type": "constant",
                              "radiance": _rgb(scaled([c * env.scale for c in env.radiance]))}
    elif env.type == "envmap":
        path = resolve_path(env.file, base_dir)
        if not os.path.exists(path):
            raise MitsubaError(f"environment.file = {env.file!r}: file not found ({path})")
        from ..environment import load_environment  # (checks the texels: Mitsuba would
        # render NaNs; read once per version of the file, as the fit's own read)

        load_environment(env, base_dir)
        out["environment"] = {"type": "envmap", "filename": os.path.abspath(path),
                              "scale": float(env.scale) * x}
    elif env.type != "black":
        raise MitsubaError(f"environment.type = {env.type!r}; allowed: black, constant, envmap")
    return out


def scene_dict(scene: Scene, material: Material, params, *, spp: int, seed: int,
               base_dir: str | None = None, variant: str | None = None, mi=None) -> dict:
    """Mitsuba 3 scene dict (for ``mi.load_dict``) equivalent to ``fitter.render``.

    Sets the Mitsuba variant (see ``fitter.mitsuba.choose_variant``) because
    the camera transform is a Mitsuba object; the Python plugins the dict
    names are registered by ``fitter.mitsuba.render`` before loading.
    ``mi``: a stand-in for the mitsuba module (``fitter.mitsuba.export`` writes
    scene.xml with a NumPy transform, without importing Mitsuba).
    """
    if mi is None:
        from .variant import load

        mi, _ = load(variant)
    check_translatable(scene, material)
    sphere = {"type": "sphere", "center": _vec(scene.sphere.center),
              "radius": float(scene.sphere.radius), "bsdf": bsdf_dict(material, params)}
    medium = interior_dict(material, params)
    if medium is not None:
        sphere["interior"] = medium
    sensor = _camera(mi, scene)
    sensor["film"] = {"type": "hdrfilm", "width": int(scene.width), "height": int(scene.height),
                      "rfilter": {"type": "box"}, "pixel_format": "rgb",
                      "component_format": "float32"}
    sensor["sampler"] = {"type": "stratified", "sample_count": stratified_spp(spp),
                         "seed": int(seed), "jitter": True}
    return {"type": "scene", "integrator": integrator_dict(material, scene), "sensor": sensor,
            "sphere": sphere, **_emitters(scene, base_dir, exposure_of(material, params))}

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
lobes                  ``Lobe.mitsuba(p, opts)``; several: ``fitter_sum``
dielectric             ``dielectric`` (ext_ior 1) + interior ``homogeneous`` medium,
                       sigma_t = -ln(attenuation), albedo 0
integrator             ``direct`` (1 emitter sample, no BSDF samples) for opaque
                       lobes; ``path`` with a mirror; ``volpathmis`` for a dielectric
sampler                ``stratified`` (spp rounded up to a square), fixed seed
=====================  ==========================================================

One difference in meaning is refused rather than translated: the project's
opaque ("brdf") lobes are lit by the point/directional lights only, while a
Mitsuba constant/envmap emitter would light them too. A material with an
opaque lobe therefore needs a black environment here.
"""

from __future__ import annotations

import math
import os

import numpy as np

from ..material import Material
from ..scene import DirectionalLight, PointLight, Scene
from ._variant import MitsubaError

#: Extra vertices beyond the internal reflections the project traces
#: (camera hit, entry, exit): Mitsuba's max_depth for the same truncation.
_DIELECTRIC_DEPTH = 3
_MIRROR_DEPTH = 4
#: Largest sigma_t (1 / world unit) given to Mitsuba for an attenuation of 0.
SIGMA_T_MAX = 1e4


def stratified_spp(spp: int) -> int:
    """The sample count Mitsuba's ``stratified`` sampler uses: the next square."""
    if int(spp) < 1:
        raise MitsubaError(f"spp = {spp} must be >= 1")
    r = math.isqrt(int(spp) - 1) + 1
    return r * r


def _rgb(v):
    return {"type": "rgb", "value": [float(x) for x in np.broadcast_to(np.asarray(v, float), 3)]}


def _vec(v):
    return [float(x) for x in v]


def bsdf_dict(material: Material, params) -> dict:
    """The Mitsuba BSDF of the material's summed lobes (without the dielectric's medium)."""
    full = material.full_params(params)
    parts = []
    for lobe in material.lobe_objects:
        if lobe.mitsuba is None:
            raise MitsubaError(f"lobe {lobe.name!r} has no Mitsuba mapping (Lobe.mitsuba)")
        p = {k.split(".", 1)[1]: v for k, v in full.items() if k.startswith(lobe.name + ".")}
        parts.append(lobe.mitsuba(p, material.options_of(lobe.name)))
    if len(parts) == 1:
        return parts[0]
    return {"type": "fitter_sum", **{f"bsdf_{i}": d for i, d in enumerate(parts)}}


def medium_dict(attenuation) -> dict | None:
    """Interior absorbing medium with transmittance ``attenuation`` per unit length.

    sigma_t = -ln(c) (RGB); Mitsuba rejects RGB sigma_t above 1, so the
    largest channel goes into ``scale``. None when nothing is absorbed.
    """
    c = np.broadcast_to(np.asarray(attenuation, dtype=np.float64), 3)
    sigma = np.where(c > 0, -np.log(np.where(c > 0, c, 1.0)), SIGMA_T_MAX)
    sigma = np.clip(sigma, 0.0, SIGMA_T_MAX)
    scale = float(sigma.max())
    if scale == 0.0:
        return None
    return {"type": "homogeneous", "albedo": 0.0, "sigma_t": _rgb(sigma / scale),
            "scale": scale}


def integrator_dict(material: Material) -> dict:
    kinds = {lb.kind for lb in material.lobe_objects}
    if "dielectric" in material.lobes:
        depth = material.options_of("dielectric")["bounces"] + _DIELECTRIC_DEPTH
        # volpathmis = volpath + spectral MIS over the RGB channels: 3x less noise
        # than volpath for an RGB absorption (measured), same estimator otherwise.
        return {"type": "volpathmis", "max_depth": depth, "rr_depth": depth + 1}
    if "specular" in kinds:
        return {"type": "path", "max_depth": _MIRROR_DEPTH, "rr_depth": _MIRROR_DEPTH + 1}
    return {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}


def check_translatable(scene: Scene, material: Material) -> None:
    """Raise MitsubaError where Mitsuba would render a different meaning."""
    if "dielectric" in material.lobes and len(material.lobes) > 1:
        raise MitsubaError("the Mitsuba translation supports the dielectric lobe only on its "
                           f"own, not summed with {[n for n in material.lobes if n != 'dielectric']}")
    opaque = [lb.name for lb in material.lobe_objects if lb.kind == "brdf"]
    if opaque and scene.environment.type != "black":
        raise MitsubaError(
            f"environment.type = {scene.environment.type!r}: Mitsuba's environment emitter would "
            f"also light the opaque lobe(s) {opaque}, which the project lights with the point/"
            "directional lights only; use a black environment for these lobes")


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


def _emitters(scene: Scene, base_dir) -> dict:
    out = {}
    for i, light in enumerate(scene.lights):
        if isinstance(light, PointLight):
            out[f"light_{i}"] = {"type": "point", "position": _vec(light.position),
                                 "intensity": _rgb(light.intensity)}
        elif isinstance(light, DirectionalLight):
            out[f"light_{i}"] = {"type": "directional", "direction": _vec(light.direction),
                                 "irradiance": _rgb(light.irradiance)}
        else:
            raise MitsubaError(f"unknown light {light!r}")
    env = scene.environment
    if env.type == "constant":
        out["environment"] = {"type": "constant", "radiance": _rgb(env.radiance)}
    elif env.type == "envmap":
        path = env.file
        if base_dir is not None and not os.path.isabs(path):
            path = os.path.join(base_dir, path)
        if not os.path.exists(path):
            raise MitsubaError(f"environment.file = {env.file!r}: file not found ({path})")
        out["environment"] = {"type": "envmap", "filename": os.path.abspath(path),
                              "scale": float(env.scale)}
    elif env.type != "black":
        raise MitsubaError(f"environment.type = {env.type!r}; allowed: black, constant, envmap")
    return out


def scene_dict(scene: Scene, material: Material, params, *, spp: int, seed: int,
               base_dir: str | None = None, variant: str | None = None) -> dict:
    """Mitsuba 3 scene dict (for ``mi.load_dict``) equivalent to ``fitter.render``.

    Sets the Mitsuba variant (see ``fitter.mitsuba.choose_variant``) because
    the camera transform is a Mitsuba object; the Python plugins the dict
    names are registered by ``fitter.mitsuba.render`` before loading.
    """
    from ._variant import load

    mi, _ = load(variant)
    check_translatable(scene, material)
    sphere = {"type": "sphere", "center": _vec(scene.sphere.center),
              "radius": float(scene.sphere.radius), "bsdf": bsdf_dict(material, params)}
    if "dielectric" in material.lobes:
        full = material.full_params(params)
        medium = medium_dict(full["dielectric.attenuation"])
        if medium is not None:
            sphere["interior"] = medium
    sensor = _camera(mi, scene)
    sensor["film"] = {"type": "hdrfilm", "width": int(scene.width), "height": int(scene.height),
                      "rfilter": {"type": "box"}, "pixel_format": "rgb",
                      "component_format": "float32"}
    sensor["sampler"] = {"type": "stratified", "sample_count": stratified_spp(spp),
                         "seed": int(seed), "jitter": True}
    return {"type": "scene", "integrator": integrator_dict(material), "sensor": sensor,
            "sphere": sphere, **_emitters(scene, base_dir)}

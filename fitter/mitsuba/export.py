"""A fit as a Mitsuba 3 scene file: ``scene.xml`` that stock Mitsuba loads.

``export_scene(path, scene, material, params, spp=..., seed=...)`` writes the
scene dict of ``fitter.mitsuba.translate.scene_dict`` -- the dict the
validation renders, so the two cannot disagree -- as Mitsuba 3 XML
(``xml.etree.ElementTree``; Mitsuba 3.9 has no dict -> XML writer):

=======================  ==================================================
scene dict               XML
=======================  ==================================================
``{"type": t, ...}``     ``<bsdf|emitter|shape|... type="t">`` (the tag is
                         the plugin's object type, asked of Mitsuba)
float / int / bool / str ``<float>`` / ``<integer>`` / ``<boolean>`` / ``<string>``
3 numbers                ``<point>`` (``<vector>`` for ``direction``)
``{"type": "rgb"}``      ``<rgb name=... value="r, g, b"/>``
transform                ``<transform><matrix value="16 numbers"/></transform>``
envmap ``filename``      the map copied beside the XML, named relatively
exposure                 every emitter's radiance times it (``translate``), said
                         in a comment at the top
=======================  ==================================================

A sum of lobes (``fitter_sum``, a plugin) becomes stock ``blendbsdf``s when
every child is a built-in whose scale is a parameter (``SCALE_KEYS``): a
sum of n BSDFs is n times their mean, the mean a chain of blends,
mean(b_1..b_n) = blend(weight (n-1)/n; b_1, mean(b_2..b_n)), each child's
reflectance multiplied by n (an ``srgb`` texture with ``unbounded``: a plain
rgb reflectance must lie in [0, 1]).
Otherwise -- a lobe without a built-in (Oren-Nayar, Phong, V-groove
Torrance-Sparrow), or a delta lobe (mirror) summed with others under an
environment, which Mitsuba's ``blendbsdf`` gets wrong (``DELTA_TYPES``) --
the XML names the fitter plugin and a comment at its top
gives the import that registers it.

Reference: Mitsuba 3 documentation, "File format" (scene XML) and the
``blendbsdf`` plugin page.
"""

from __future__ import annotations

import os
import shutil
import xml.etree.ElementTree as ET

import numpy as np

from ..material import Material
from ..scene import Scene
from . import translate
from .variant import MitsubaError

#: Built-in BSDF type -> its parameter that scales the whole BSDF linearly.
SCALE_KEYS = {"diffuse": "reflectance", "roughconductor": "specular_reflectance",
              "conductor": "specular_reflectance"}
#: Delta BSDFs: Mitsuba 3.9's ``blendbsdf`` of a delta and a smooth child is biased
#: under ``path`` with MIS (measured: diffuse (0.6, 0.4, 0.2) + mirror 0.4 under a
#: constant sky, 1024 spp: (0.157, 0.120, 0.083) against the exact mean (0.150,
#: 0.120, 0.090)); under ``direct`` without BSDF samples, or with point/directional
#: lights only (no BSDF sample meets them), it is exact. So a sum with a delta child
#: under an environment stays ``fitter_sum``.
DELTA_TYPES = ("conductor", "dielectric")
#: How to make a Mitsuba that does not know the fitter plugins know them.
PLUGIN_IMPORT = ("import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); "
                 "from fitter.mitsuba.plugins import register; register(mi)")
#: Mitsuba object type -> XML tag.
_TAGS = {"BSDF": "bsdf", "Emitter": "emitter", "Film": "film", "Shape": "shape",
         "Medium": "medium", "Integrator": "integrator", "ReconstructionFilter": "rfilter",
         "Sampler": "sampler", "Sensor": "sensor", "Texture": "texture", "PhaseFunction": "phase"}


#: XML tag of every plugin type the translation writes (asked of Mitsuba only for others).
_KNOWN_TAGS = {
    **dict.fromkeys(("diffuse", "roughconductor", "conductor", "dielectric", "roughdielectric",
                     "plastic", "roughplastic", "blendbsdf", "twosided"), "bsdf"),
    **dict.fromkeys(("point", "directional", "constant", "envmap"), "emitter"),
    **dict.fromkeys(("direct", "path", "volpath", "volpathmis", "prb"), "integrator"),
    **dict.fromkeys(("perspective", "orthographic"), "sensor"),
    "hdrfilm": "film", "box": "rfilter", "stratified": "sampler", "independent": "sampler",
    "multijitter": "sampler", "sphere": "shape", "homogeneous": "medium",
    "isotropic": "phase", "srgb": "texture", "bitmap": "texture",
}


class _Transform:
    """A 4x4 NumPy stand-in for ``mi.ScalarTransform4f``: ``look_at``, ``scale``, ``@``
    (Mitsuba 3's conventions), so scene.xml is written without importing Mitsuba."""

    def __init__(self, matrix=None):
        self.matrix = np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64)

    def look_at(self, origin, target, up):
        o, t, u = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
        d = (t - o) / np.linalg.norm(t - o)
        left = np.cross(u, d)
        left /= np.linalg.norm(left)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(d, left), d, o
        return _Transform(self.matrix @ m)

    def scale(self, v):
        return _Transform(self.matrix @ np.diag([*np.asarray(v, dtype=np.float64), 1.0]))

    def __matmul__(self, other):
        return _Transform(self.matrix @ other.matrix)


class _NumpyMitsuba:
    """What ``translate.scene_dict`` asks of the mitsuba module, in NumPy."""

    ScalarTransform4f = _Transform


def _num(x) -> str:
    return repr(float(x))


def _blend_sum(d: dict, direct: bool) -> dict:
    """``fitter_sum`` as nested stock ``blendbsdf``s, or ``d`` unchanged if a child's
    scale is not a parameter of a built-in, or a delta child would be sampled
    (``direct``: False; see the module docstring)."""
    children = [d[k] for k in sorted(d) if k != "type"]
    if not all(c.get("type") in SCALE_KEYS for c in children):
        return d
    if not direct and any(c.get("type") in DELTA_TYPES for c in children):
        return d
    n = len(children)
    scaled = []
    for c in children:
        key = SCALE_KEYS[c["type"]]
        value = c.get(key, {"type": "rgb", "value": [1.0, 1.0, 1.0]})
        rgb = ([float(value)] * 3 if not isinstance(value, dict)
               else value["value"] if value["type"] == "rgb" else value["color"])
        # An rgb reflectance must lie in [0, 1]; ``srgb`` with ``unbounded`` may exceed it.
        value = {"type": "srgb", "color": [n * float(v) for v in rgb], "unbounded": True}
        scaled.append({**c, key: value})

    def mean(parts):
        if len(parts) == 1:
            return parts[0]
        m = len(parts)
        return {"type": "blendbsdf", "weight": (m - 1) / m, "bsdf_0": parts[0],
                "bsdf_1": mean(parts[1:])}

    return mean(scaled)


def _stock(d, direct=None):
    """The scene dict with every ``fitter_sum`` of built-ins replaced by blends."""
    if not isinstance(d, dict):
        return d
    if direct is None:  # BSDF samples can hit only an environment (lights are points)
        direct = d.get("integrator", {}).get("type") == "direct" or "environment" not in d
    d = {k: _stock(v, direct) for k, v in d.items()}
    return _blend_sum(d, direct) if d.get("type") == "fitter_sum" else d


def plugin_types(d) -> list[str]:
    """The fitter plugin types (``fitter_*``) the dict names, sorted."""
    found = set()

    def walk(x):
        if isinstance(x, dict):
            if str(x.get("type", "")).startswith("fitter_"):
                found.add(x["type"])
            for v in x.values():
                walk(v)

    walk(d)
    return sorted(found)


def _tag(mi, type_name: str) -> str:
    if type_name.startswith("fitter_"):  # Python plugins: every fitter plugin is a BSDF
        return "bsdf"
    if type_name in _KNOWN_TAGS:
        return _KNOWN_TAGS[type_name]
    if mi is None:
        from .variant import load

        mi, _ = load(None)
    kind = str(mi.PluginManager.instance().plugin_type(type_name)).split(".")[-1]
    if kind not in _TAGS:
        raise MitsubaError(f"cannot write Mitsuba plugin type {type_name!r} ({kind}) as XML")
    return _TAGS[kind]


def _element(mi, parent, name, value, folder):
    """Append ``name = value`` to ``parent`` as the XML element of its kind."""
    if isinstance(value, dict) and value.get("type") == "rgb":
        ET.SubElement(parent, "rgb", name=name,
                      value=", ".join(_num(v) for v in value["value"]))
    elif isinstance(value, dict):
        attrs = {"type": value["type"]}
        if name is not None:
            attrs["name" if parent.tag != "scene" else "id"] = name
        child = ET.SubElement(parent, _tag(mi, value["type"]), attrs)
        for k, v in value.items():
            if k == "type":
                continue
            if k == "filename":
                v = _copy_beside(v, folder)
            _element(mi, child, k, v, folder)
    elif isinstance(value, bool):
        ET.SubElement(parent, "boolean", name=name, value="true" if value else "false")
    elif isinstance(value, (int, np.integer)):
        ET.SubElement(parent, "integer", name=name, value=str(int(value)))
    elif isinstance(value, (float, np.floating)):
        ET.SubElement(parent, "float", name=name, value=_num(value))
    elif isinstance(value, str):
        ET.SubElement(parent, "string", name=name, value=value)
    elif isinstance(value, (list, tuple)) and len(value) == 3 and name == "color":
        ET.SubElement(parent, "rgb", name=name, value=", ".join(_num(v) for v in value))
    elif isinstance(value, (list, tuple)) and len(value) == 3:
        ET.SubElement(parent, "vector" if name == "direction" else "point", name=name,
                      value=", ".join(_num(v) for v in value))
    elif hasattr(value, "matrix"):  # a ScalarTransform4f
        m = np.asarray(value.matrix, dtype=np.float64).reshape(4, 4)
        t = ET.SubElement(parent, "transform", name=name)
        ET.SubElement(t, "matrix", value=" ".join(_num(v) for v in m.reshape(-1)))
    else:
        raise MitsubaError(f"cannot write {name} = {value!r} as Mitsuba XML")


def _copy_beside(path: str, folder: str) -> str:
    """Copy a file the scene reads (the envmap) into ``folder``; its name there."""
    name = os.path.basename(path)
    dest = os.path.join(folder, name)
    if os.path.abspath(path) != os.path.abspath(dest):
        shutil.copyfile(path, dest)
    return name


def scene_xml(d: dict, folder: str, exposure: float = 1.0) -> str:
    """The XML text of scene dict ``d`` (files it reads copied into ``folder``).
    Mitsuba is imported only for a plugin type ``_KNOWN_TAGS`` does not name.
    ``exposure`` (already applied to ``d``'s emitters) is stated in a comment."""
    mi = None
    d = _stock(d)
    root = ET.Element("scene", version="3.0.0")
    for k, v in d.items():
        if k != "type":
            _element(mi, root, k, v, folder)
    ET.indent(root)
    body = ET.tostring(root, encoding="unicode")
    plugins = plugin_types(d)
    head = '<?xml version="1.0" encoding="utf-8"?>\n'
    if plugins:
        head += (f"<!-- {', '.join(plugins)}: fitter plugin(s), not built into Mitsuba. "
                 f"Register them before loading this file:\n     {PLUGIN_IMPORT}\n-->\n")
    else:
        head += "<!-- Written by fitter; stock Mitsuba 3 (llvm_ad_rgb) loads it. -->\n"
    if exposure != 1.0:
        head += (f"<!-- exposure {exposure!r}: every emitter's intensity, irradiance, radiance "
                 "or scale below is the config's times this, so the render is the exposed "
                 "image (Mitsuba is linear in its emitters). -->\n")
    return head + body + "\n"


def export_scene(path: str, scene: Scene, material: Material, params, *, spp: int, seed: int,
                 base_dir: str | None = None) -> list[str]:
    """Write ``path`` (scene.xml) for the fitted ``params``; returns the plugin types
    it needs (empty: stock Mitsuba loads it)."""
    d = translate.scene_dict(scene, material, params, spp=spp, seed=seed, base_dir=base_dir,
                             mi=_NumpyMitsuba)
    folder = os.path.dirname(os.path.abspath(path))
    text = scene_xml(d, folder, translate.exposure_of(material, params))
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return plugin_types(_stock(d))


def export_job(folder: str, job, params) -> list[str]:
    """``folder/scene.xml`` of a job (``fitter.config.Job``) at ``params``, rendered as
    its validation renders (``fit.validate_spp``, the validation seed)."""
    from ..pipeline import validation_seed

    return export_scene(os.path.join(folder, "scene.xml"), job.scene, job.material,
                        job.material.full_params(params), spp=job.fit.validate_spp,
                        seed=validation_seed(job), base_dir=job.base_dir)


def export_outdir(folder: str) -> tuple[str, str]:
    """``fitter export OUTDIR``: scene.xml and material.json of a ``fitter fit``
    output folder (its config.toml and result.json); returns both paths.

    material.json is plain data: ``{"lobes": [...], "options": {...}, "params":
    {...}}`` -- what a renderer other than Mitsuba needs to rebuild the material.
    """
    import json

    from ..config import load_config

    config, result = (os.path.join(folder, n) for n in ("config.toml", "result.json"))
    for path in (config, result):
        if not os.path.isfile(path):
            raise MitsubaError(f"{path}: not found; OUTDIR must be a folder `fitter fit` wrote")
    job = load_config(config)
    with open(result, encoding="utf-8") as fh:
        params = json.load(fh)["params"]
    export_job(folder, job, params)
    material = {"lobes": list(job.material.lobes), "options": dict(job.material.options),
                "params": params}
    out = os.path.join(folder, "material.json")
    with open(out, "w", encoding="utf-8") as fh:
        json.dump(material, fh, indent=2)
    return os.path.join(folder, "scene.xml"), out

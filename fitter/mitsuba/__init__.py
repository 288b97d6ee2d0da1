"""Mitsuba 3 as the independent renderer: synthetic targets and validation.

``render(scene, material, params)`` renders the project's scene with Mitsuba
(see ``translate`` for the mapping, ``plugins`` for the lobes Mitsuba lacks);
``synth.write_case`` writes a synthetic target; ``fitter.cases`` lists the
shipped ones. Mitsuba and drjit are imported on the first call, never by
``import fitter``.

Variant: the ``variant`` argument, else ``$FITTER_MITSUBA_VARIANT``, else
``cuda_ad_rgb`` when an NVIDIA GPU is present, else ``llvm_ad_rgb`` (which
needs libLLVM >= 16; see ``variant``).
"""

from __future__ import annotations

import numpy as np

from .variant import MitsubaError as MitsubaError, choose_variant as choose_variant
from .translate import scene_dict as scene_dict, stratified_spp as stratified_spp


def load_scene(scene, material, params, *, spp=256, seed=0, variant=None, base_dir=None):
    """The loaded ``mi.Scene`` (variant set, plugins registered)."""
    from ..material import Material
    from . import plugins
    from .variant import load

    material = Material.given(material, params)
    mi, _ = load(variant)
    plugins.register(mi)
    d = scene_dict(scene, material, params, spp=spp, seed=seed, base_dir=base_dir,
                   variant=variant)
    return mi.load_dict(d)


def render(scene, material, params, *, spp: int = 256, seed: int = 0, variant: str | None = None,
           base_dir: str | None = None) -> np.ndarray:
    """Render with Mitsuba 3: (H, W, 3) float64 linear RGB radiance.

    Args:
        scene: a ``fitter.Scene``.
        material: a ``fitter.Material``, a lobe list or a ``"lambert+phong"``
            string (``Material.given``: option values in ``params`` apply).
        params: flat ``{"lobe.param": value}``; missing ones take the defaults.
        spp: samples per pixel (``stratified``: rounded up to a square).
        seed: sampler seed; the same seed, spp and Mitsuba version give the
            same image.
        variant: Mitsuba variant; see ``choose_variant``.
        base_dir: folder a relative envmap path is resolved against.
    """
    mi_scene = load_scene(scene, material, params, spp=spp, seed=seed, variant=variant,
                          base_dir=base_dir)
    import mitsuba as mi

    img = mi.render(mi_scene, spp=stratified_spp(spp), seed=int(seed))
    return np.array(img, dtype=np.float64)[..., :3]

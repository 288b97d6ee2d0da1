"""The parts of an environment's sky term, by how the sky lights each opaque lobe.

A lobe with ``Lobe.uniform`` (and ``Lobe.kernel``) is lit by sums over the map
made once per scene (``fitter.irradiance``), the others by the sky stencil
(``fitter.skystencil``), per solver step. The stated errors
(``_discretisation.sky_terms``) bound each part by its own measured accuracy.
"""

from __future__ import annotations

import numpy as np

from .._math import to_device
from ..material import EXPOSURE_KEY, Material, lobe_params
from ..render import sky_parts


def opaque_lobes(material) -> list:
    """``material``'s opaque (brdf) lobe objects."""
    return [lb for lb in material.lobe_objects if lb.name in material.opaque]


def summed_parts(geo, params, material, lobe) -> tuple[np.ndarray, np.ndarray]:
    """``lobe``'s uniform and kernel parts under the sky (P, 3) each
    (``render.sky_parts``), times its scale and the exposure if any; the kernel's
    zeros without one. ``params``: complete, in user units."""
    p = lobe_params(params, lobe.name)
    scale = np.asarray(p[lobe.scale], dtype=np.float64)
    scale = scale * float(params[EXPOSURE_KEY]) if material.exposure else scale
    # On the host: host parameters times device sums compiled an eager kernel per product.
    kernels = geo.env_kernels and {k: np.asarray(v) for k, v in geo.env_kernels.items()}
    geo = geo._replace(env_irradiance=np.asarray(geo.env_irradiance), env_kernels=kernels)
    uniform, kernel = (None if a is None else scale * np.asarray(a, dtype=np.float64)
                       for a in sky_parts(lobe, p, material.options_of(lobe.name), geo))
    return uniform, np.zeros_like(uniform) if kernel is None else kernel


def lobes_alone(material, names) -> Material:
    """``material``'s lobes ``names`` alone, with their options (no exposure)."""
    return Material.make(names, {k: v for k, v in material.options
                                 if k.split(".")[0] in names})


def dark(geo):
    """``geo`` with its lights, sun cells and background dropped: the sky term alone."""
    return geo._replace(
        cosines=type(geo.cosines)(*(a[:0] for a in geo.cosines)),
        light_weight=geo.light_weight[:0], light_color=geo.light_color[:0], sun=(),
        background=to_device(np.zeros(np.shape(geo.background)), geo.background.dtype))

"""How a lobe tells ``fitter.mitsuba`` to render it: ``MitsubaMapping``.

A lobe's module builds its mapping beside its formula. Nothing here imports
Mitsuba or drjit: the callables that need them receive the Mitsuba module
``mi`` from ``fitter.mitsuba`` (variant already set), so ``import fitter.bsdf``
stays free of both.

Python plugins derive from ``cosine_sampled(mi)``: Mitsuba's ``eval`` returns
f(wi, wo) cos(theta_o) and must vanish below either horizon; sampling is
cosine-weighted over the hemisphere. Under the project's point and directional
lights only ``eval`` enters the image (``direct``, emitter sampling only); the
samplers just have to be valid.

References:
    Mitsuba 3 documentation, "Custom plugins in Python", "BSDF" and
        "homogeneous" plugin pages.
    Teschner, *Materials 3*, "Light attenuation" (Beer-Lambert L_a = c^d L_b).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping

import numpy as np

#: Largest sigma_t (1 / world unit) given to Mitsuba for an attenuation of 0.
SIGMA_T_MAX = 1e4


@dataclasses.dataclass(frozen=True, eq=False)
class MitsubaMapping:
    """The Mitsuba 3 equivalent of a lobe.

    Attributes:
        bsdf: ``bsdf(p, opts) -> dict``, the BSDF dict for ``mi.load_dict``
            (plain data); the mapping itself is callable the same way.
        plugins: ``{type name: make(mi) -> mi.BSDF subclass}`` for the Python
            plugins the dict may name; ``fitter.mitsuba.plugins`` registers
            them before loading a scene.
        interior: ``interior(p, opts) -> dict | None``, a medium inside the
            sphere (None: nothing); a lobe that has one needs a volumetric
            integrator.
        max_depth: ``max_depth(opts) -> int``, the path length the lobe
            needs; None: direct lighting (one emitter sample) suffices.
    """

    bsdf: Callable[[dict, dict], dict]
    plugins: Mapping[str, Callable[[Any], type]] = dataclasses.field(default_factory=dict)
    interior: Callable[[dict, dict], dict | None] | None = None
    max_depth: Callable[[dict], int] | None = None

    def __call__(self, p, opts) -> dict:
        return self.bsdf(p, opts)


def rgb(v) -> dict:
    """Mitsuba's ``rgb`` texture of a grey value or three values."""
    return {"type": "rgb", "value": [float(x) for x in np.broadcast_to(np.asarray(v, float), 3)]}


def rgb_unbounded(v) -> dict:
    """A colour texture that may exceed 1 (Mitsuba's ``rgb`` of a reflectance may not):
    ``srgb`` with ``unbounded``; the plain ``rgb`` where every value is in [0, 1]."""
    d = rgb(v)
    if all(0.0 <= x <= 1.0 for x in d["value"]):
        return d
    return {"type": "srgb", "color": d["value"], "unbounded": True}


def absorbing_medium(attenuation) -> dict | None:
    """Interior ``homogeneous`` medium with transmittance ``attenuation`` per unit length.

    Beer-Lambert c^d = exp(-sigma_t d), so sigma_t = -ln(c) (RGB); Mitsuba
    rejects RGB sigma_t above 1, so the largest channel goes into ``scale``.
    None when nothing is absorbed.
    """
    c = np.broadcast_to(np.asarray(attenuation, dtype=np.float64), 3)
    sigma = np.where(c > 0, -np.log(np.where(c > 0, c, 1.0)), SIGMA_T_MAX)
    sigma = np.clip(sigma, 0.0, SIGMA_T_MAX)
    scale = float(sigma.max())
    if scale == 0.0:
        return None
    return {"type": "homogeneous", "albedo": 0.0, "sigma_t": rgb(sigma / scale), "scale": scale}


def props_rgb(mi, props, name, default):
    """A plugin's colour property (a float, a colour or a texture) as ``mi.Color3f``."""
    import drjit as dr

    if name in props:
        v = props[name]
        if isinstance(v, (int, float)):
            return mi.Color3f(float(v))
        if hasattr(v, "eval"):
            return mi.Color3f(v.eval(dr.zeros(mi.SurfaceInteraction3f)))
        return mi.Color3f(v[0], v[1], v[2])
    return mi.Color3f(default)


_BASES: dict[str, type] = {}


def cosine_sampled(mi) -> type:
    """Base class of a glossy-reflection plugin: subclasses define ``_value(wi, wo)``
    = f(wi, wo) for directions above the horizon (local frame, normal +z)."""
    if mi.variant() not in _BASES:
        _BASES[mi.variant()] = _make_base(mi)
    return _BASES[mi.variant()]


def _make_base(mi):
    import drjit as dr

    class CosineSampled(mi.BSDF):
        """Shared glossy-reflection flags, cosine sampling and pdf."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _value(self, wi, wo):  # f(wi, wo), both above the horizon
            raise NotImplementedError

        def eval(self, ctx, si, wo, active=True):
            ci = mi.Frame3f.cos_theta(si.wi)
            co = mi.Frame3f.cos_theta(wo)
            ok = active & (ci > 0) & (co > 0)
            return dr.select(ok, self._value(si.wi, wo) * co, mi.Color3f(0.0))

        def pdf(self, ctx, si, wo, active=True):
            ci = mi.Frame3f.cos_theta(si.wi)
            co = mi.Frame3f.cos_theta(wo)
            return dr.select(active & (ci > 0) & (co > 0),
                             mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            ci = mi.Frame3f.cos_theta(si.wi)
            active = active & (ci > 0)
            bs = mi.BSDFSample3f()
            bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(bs.wo)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            co = mi.Frame3f.cos_theta(bs.wo)
            ok = active & (co > 0) & (bs.pdf > 0)
            # f cos / pdf with pdf = cos / pi
            weight = dr.select(ok, self._value(si.wi, bs.wo) * math.pi, mi.Color3f(0.0))
            return bs, weight

        def traverse(self, cb):
            pass

        def parameters_changed(self, keys):
            pass

    return CosineSampled

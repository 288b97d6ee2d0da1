"""Torrance-Sparrow microfacet specular lobe with the lecture's Beckmann D.

f = rho_s D(h) G(wi, wo) F(wo.h; eta) / (pi cos_i cos_o), with the lecture's
D = exp(-tan^2(beta)/m^2) / (4 m^2 cos^4(beta)). Since that D is pi/4 times
the normalised Beckmann D_n, f = rho_s D_n G F / (4 cos_i cos_o): the same
BRDF as Mitsuba 3's ``roughconductor`` (``beckmann``, alpha = m, k = 0) when
G is ``smith``. F is the dielectric Fresnel reflectance at the microfacet,
cos = wo.h (= wi.h; the lecture writes F(wo)).

Options:
    geometry: ``"v_groove"`` (Cook-Torrance, default, the lecture's model) or
        ``"smith"`` (Beckmann Smith G1(wi) G1(wo), Walter et al. rational
        form, as Mitsuba).

Mitsuba: ``smith`` is its ``roughconductor`` (Beckmann, alpha = m, k = 0
gives the dielectric Fresnel); ``v_groove`` is the ``fitter_torrance_sparrow``
plugin here (``alpha`` = m, ``eta``, ``specular_reflectance``).

References:
    Teschner, *Materials 3*, "Torrance-Sparrow specular material".
    Torrance, Sparrow (1967), JOSA 57(9); Cook, Torrance (1982), ACM TOG 1(1).
"""

import math

from .._lazy import jnp
from .._math import safe_div
from .base import Hints, Lobe, Option, Param, Point, Quadrature
from .fresnel import fresnel_dielectric, fresnel_dielectric_deta
from .microfacet import (beckmann_d_lecture, beckmann_dlog_d_dm, g_smith, g_v_groove,
                         smith_g1_beckmann_dm)
from .mitsuba_map import MitsubaMapping, cosine_sampled, props_rgb, rgb


def _shape(p, opts, c):
    ci, co, m = c.cos_i, c.cos_o, p["m"]
    ok = (ci > 0) & (co > 0)
    d = beckmann_d_lecture(c.cos_h, c.tan2_h, m)
    if opts["geometry"] == "smith":
        g = g_smith(ci, co, m)
    else:
        g = g_v_groove(c.cos_h, ci, co, c.cos_d)
    f = fresnel_dielectric(jnp.clip(c.cos_d, 0.0, 1.0), p["eta"])
    return safe_div(d * g * f, jnp.pi * ci * co, ok)


def _shape_grad(p, opts, c):
    """Shape and its derivatives in m and eta (``Lobe.shape_grad``)."""
    ci, co, m = c.cos_i, c.cos_o, p["m"]
    ok = (ci > 0) & (co > 0)
    d = beckmann_d_lecture(c.cos_h, c.tan2_h, m)
    dlog_d = beckmann_dlog_d_dm(jnp.where(d > 0, c.tan2_h, 0.0), m)
    f, df = fresnel_dielectric_deta(jnp.clip(c.cos_d, 0.0, 1.0), p["eta"])
    if opts["geometry"] == "smith":
        g_i, dg_i = smith_g1_beckmann_dm(ci, m)
        g_o, dg_o = smith_g1_beckmann_dm(co, m)
        g, dg = g_i * g_o, dg_i * g_o + g_i * dg_o
    else:
        g, dg = g_v_groove(c.cos_h, ci, co, c.cos_d), 0.0
    base = safe_div(d, jnp.pi * ci * co, ok)
    value = base * g * f
    return value, {"m": value * dlog_d + base * dg * f, "eta": base * g * df}


def _mitsuba(p, opts):
    scale = rgb(p["rho_s"])
    if opts["geometry"] == "smith":
        return {"type": "roughconductor", "distribution": "beckmann", "alpha": float(p["m"]),
                "eta": float(p["eta"]), "k": 0.0, "specular_reflectance": scale}
    return {"type": "fitter_torrance_sparrow", "alpha": float(p["m"]),
            "eta": float(p["eta"]), "specular_reflectance": scale}


def _plugin(mi):
    import drjit as dr

    base = cosine_sampled(mi)

    class TorranceSparrow(base):
        """rho_s D_n G F / (4 ci co): normalised Beckmann D, V-groove G, dielectric F."""

        def __init__(self, props):
            base.__init__(self, props)
            self.rho = props_rgb(mi, props, "specular_reflectance", 1.0)
            self.m = mi.Float(max(float(props.get("alpha", 0.2)), 1e-4))
            self.eta = mi.Float(float(props.get("eta", 1.5)))

        def _value(self, wi, wo):
            ci, co = wi.z, wo.z
            h = dr.normalize(wi + wo)
            ch = h.z
            tan2 = (h.x * h.x + h.y * h.y) / dr.maximum(ch * ch, 1e-30)
            m2 = self.m * self.m
            d = dr.exp(-tan2 / m2) / (dr.pi * m2 * dr.square(dr.square(ch)))
            woh = dr.dot(wo, h)
            g = dr.minimum(1.0, 2.0 * ch * dr.minimum(ci, co) / dr.maximum(woh, 1e-30))
            f = mi.fresnel(dr.clip(woh, 0.0, 1.0), self.eta)[0]
            val = d * dr.maximum(g, 0.0) * f / (4.0 * ci * co)
            return self.rho * dr.select(ch > 0, val, 0.0)

        def to_string(self):
            return f"fitter_torrance_sparrow[alpha={self.m}, eta={self.eta}]"

    return TorranceSparrow


def _quadrature(p):
    """Half vectors about n within the cap where the Beckmann exponent > e^-40;
    the horizon cuts broad lobes (a kink), hence twice the nodes."""
    return Quadrature("half", min(math.pi / 2, math.atan(float(p["m"]) * math.sqrt(40.0))), 2)


LOBE = Lobe(
    name="torrance_sparrow",
    kind="brdf",
    params=(
        Param("m", 1, 0.2, 1e-3, 1.0, "log", "Beckmann roughness (RMS facet slope)"),
        Param("eta", 1, 1.5, 1.0, 4.0, "eta", "relative index of refraction of the Fresnel term"),
        Param("rho_s", 1, 1.0, 0.0, 1.0, "logit", "scale of the lobe", free=False),
    ),
    options=(Option("geometry", ("v_groove", "smith"), "v_groove",
                    "shadowing-masking G: the lecture's V-groove (Cook-Torrance) or Beckmann "
                    "Smith (as Mitsuba's `roughconductor`)"),),
    scale="rho_s",
    shape=_shape,
    shape_grad=_shape_grad,
    doc="D G F / (π cosθ_i cosθ_o) with the lecture's D = exp(−tan²β/m²)/(4m²cos⁴β), i.e. "
        "normalized Beckmann D_n G F/(4 cosθ_i cosθ_o); Smith G is Walter et al.'s rational "
        "form, as Mitsuba's `roughconductor`",
    mitsuba=MitsubaMapping(_mitsuba, plugins={"fitter_torrance_sparrow": _plugin}),
    hints=Hints(
        points=(*(Point(f"ts_{g}-m{m:g}", {"m": m, "eta": 4.0, "rho_s": 1.0}, {"geometry": g})
                  for g in ("v_groove", "smith") for m in (0.01, 0.2, 1.0)),
                # eta = 1: F = 0, nothing is reflected (positivity, reciprocity only).
                Point("ts_v_groove-eta1", {"m": 0.3, "eta": 1.0, "rho_s": 1.0},
                      {"geometry": "v_groove"}, conserving=False)),
        example={"m": 0.3, "eta": 1.7},
        quadrature=_quadrature),
)

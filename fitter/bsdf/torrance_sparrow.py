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

References:
    Teschner, *Materials 3*, "Torrance-Sparrow specular material".
    Torrance, Sparrow (1967), JOSA 57(9); Cook, Torrance (1982), ACM TOG 1(1).
"""

import jax.numpy as jnp

from .._math import safe_div
from .base import Lobe, Option, Param
from .fresnel import fresnel_dielectric, fresnel_dielectric_deta
from .microfacet import (beckmann_d_lecture, beckmann_dlog_d_dm, g_smith, g_v_groove,
                         smith_g1_beckmann_dm)


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
    """``smith``: Mitsuba's ``roughconductor`` (Beckmann, alpha = m, k = 0 gives the
    dielectric Fresnel); ``v_groove``: the ``fitter_torrance_sparrow`` plugin."""
    scale = {"type": "rgb", "value": [float(p["rho_s"])] * 3}
    if opts["geometry"] == "smith":
        return {"type": "roughconductor", "distribution": "beckmann", "alpha": float(p["m"]),
                "eta": float(p["eta"]), "k": 0.0, "specular_reflectance": scale}
    return {"type": "fitter_torrance_sparrow", "alpha": float(p["m"]),
            "eta": float(p["eta"]), "specular_reflectance": scale}


LOBE = Lobe(
    name="torrance_sparrow",
    kind="brdf",
    params=(
        Param("m", 1, 0.2, 1e-3, 1.0, "log", "Beckmann roughness (RMS facet slope)"),
        Param("eta", 1, 1.5, 1.0, 4.0, "eta", "relative index of refraction of the Fresnel term"),
        Param("rho_s", 1, 1.0, 0.0, 1.0, "logit", "scale of the lobe (fixed at 1 by default)",
              free=False),
    ),
    options=(Option("geometry", ("v_groove", "smith"), "v_groove",
                    "shadowing-masking term G"),),
    scale="rho_s",
    shape=_shape,
    shape_grad=_shape_grad,
    doc="Torrance-Sparrow: D G F / (pi cos_i cos_o), Beckmann D.",
    mitsuba=_mitsuba,
)

"""Torrance-Sparrow microfacet specular lobe with the lecture's Beckmann D.

f = rho_s D(h) G(wi, wo) F(wo.h; eta) / (pi cos_i cos_o), with the lecture's
D = exp(-tan^2(beta)/m^2) / (4 m^2 cos^4(beta)). Since that D is pi/4 times
the normalised Beckmann D_n, f = rho_s D_n G F / (4 cos_i cos_o): the same
BRDF as Mitsuba 3's ``roughconductor`` (``beckmann``, alpha = m, k = 0) when
G is ``smith``. F is the Fresnel reflectance at the microfacet, cos = wo.h
(= wi.h; the lecture writes F(wo)): the dielectric one of a scalar eta, or
(``fresnel = "conductor"``) the exact unpolarised conductor one of a complex
index eta + i k per RGB channel (``fresnel.fresnel_conductor``), which makes
the shape an RGB (..., 3) array and ``eta``, ``k`` RGB parameters (the lobe's
``variants``).

Identifiability of a conductor: F(theta) is nearly flat up to ~60 degrees and
rises to 1 only at grazing, so one image fixes F0 = ((eta - 1)^2 + k^2) /
((eta + 1)^2 + k^2) per channel well and eta, k only along the curve of equal
F0; ``derived`` reports F0 with its standard error and says so. That curve
has a dielectric-like branch (k -> 0, eta large) ending in the box's corner
eta = 10, k = 1e-3, where F0 cannot rise (dF0/dk ~ k, eta on its bound): a
fit that wanders there from a poor start stops, converged, at a wrong F0
(measured: gold under a sky with a small sun, F0 6-8 stated errors off), so
``interior`` puts such a channel back on the metal branch at the same F0.

Options:
    fresnel: ``"dielectric"`` (default, scalar ``eta``) or ``"conductor"``
        (RGB ``eta`` and ``k``).
    geometry: ``"v_groove"`` (Cook-Torrance, default, the lecture's model) or
        ``"smith"`` (Beckmann Smith G1(wi) G1(wo), Walter et al. rational
        form, as Mitsuba).

Mitsuba: ``smith`` is its ``roughconductor`` (Beckmann, alpha = m, k = 0
gives the dielectric Fresnel; a conductor passes rgb ``eta`` and ``k``);
``v_groove`` is the ``fitter_torrance_sparrow`` plugin here (``alpha`` = m,
``eta``, optional rgb ``k`` for a conductor, ``specular_reflectance``).

References:
    Teschner, *Materials 3*, "Torrance-Sparrow specular material".
    Torrance, Sparrow (1967), JOSA 57(9); Cook, Torrance (1982), ACM TOG 1(1).
    Pharr, Jakob, Humphreys, *pbrt-v4*, sec. 9.3 (``FrComplex``): conductors.
"""

import math

import numpy as np

from .._lazy import jnp
from .._math import safe_div
from .base import Hints, Lobe, Option, Param, Point, Quadrature, cotangents
from .fresnel import (conductor_f0, fresnel_conductor, fresnel_conductor_grad, fresnel_dielectric,
                      fresnel_dielectric_deta)
from .metals import METALS
from .microfacet import (beckmann_d_lecture, beckmann_dlog_d_dm, g_smith, g_v_groove,
                         smith_g1_beckmann_dm)
from .mitsuba_map import MitsubaMapping, cosine_sampled, props_rgb, rgb


def _fresnel(p, opts, cos_d):
    """F at cos = wo.h and its derivatives {name: dF/d name}: dielectric (...) in
    scalar eta, or conductor (..., 3) per channel in RGB eta and k (the
    derivatives of an RGB parameter are the diagonal, channel c by eta_c)."""
    cos_d = jnp.clip(cos_d, 0.0, 1.0)
    if opts.get("fresnel", "dielectric") == "conductor":
        f, d_eta, d_k = fresnel_conductor_grad(cos_d[..., None], p["eta"], p["k"])
        return f, {"eta": d_eta, "k": d_k}
    f, d_eta = fresnel_dielectric_deta(cos_d, p["eta"])
    return f, {"eta": d_eta}


#: Floor of cos_i cos_o in the denominator. Directions within ~1e-10 rad of the
#: horizon (no pixel integral sees them) otherwise give values near the float64
#: limit and infinite derivatives in m (hypothesis: cos_i = cos_o = 1e-150).
MIN_COS_PRODUCT = 1e-20


def _denominator(ci, co):
    return jnp.pi * jnp.maximum(ci * co, MIN_COS_PRODUCT)


def _shape(p, opts, c):
    ci, co, m = c.cos_i, c.cos_o, p["m"]
    ok = (ci > 0) & (co > 0)
    d = beckmann_d_lecture(c.cos_h, c.tan2_h, m)
    if opts.get("geometry", "v_groove") == "smith":
        g = g_smith(*cotangents(c), m)
    else:
        g = g_v_groove(c.cos_h, ci, co, c.cos_d)
    if opts.get("fresnel", "dielectric") == "conductor":
        f = fresnel_conductor(jnp.clip(c.cos_d, 0.0, 1.0)[..., None], p["eta"], p["k"])
        return safe_div(d * g, _denominator(ci, co), ok)[..., None] * f
    f = fresnel_dielectric(jnp.clip(c.cos_d, 0.0, 1.0), p["eta"])
    return safe_div(d * g * f, _denominator(ci, co), ok)


def _shape_grad(p, opts, c):
    """Shape and its derivatives in m and eta (and k) (``Lobe.shape_grad``)."""
    ci, co, m = c.cos_i, c.cos_o, p["m"]
    ok = (ci > 0) & (co > 0)
    d = beckmann_d_lecture(c.cos_h, c.tan2_h, m)
    dlog_d = beckmann_dlog_d_dm(jnp.where(d > 0, c.tan2_h, 0.0), m)
    f, df = _fresnel(p, opts, c.cos_d)
    if opts.get("geometry", "v_groove") == "smith":
        cot_i, cot_o = cotangents(c)
        g_i, dg_i = smith_g1_beckmann_dm(cot_i, m)
        g_o, dg_o = smith_g1_beckmann_dm(cot_o, m)
        g, dg = g_i * g_o, dg_i * g_o + g_i * dg_o
    else:
        g, dg = g_v_groove(c.cos_h, ci, co, c.cos_d), 0.0
    base = safe_div(d, _denominator(ci, co), ok)
    if jnp.ndim(f) > jnp.ndim(base):  # RGB Fresnel: colour axis last
        base, g, dg = base[..., None], jnp.asarray(g)[..., None], jnp.asarray(dg)[..., None]
        dlog_d = dlog_d[..., None]
    value = base * g * f
    return value, {"m": value * dlog_d + base * dg * f, **{k: base * g * v for k, v in df.items()}}


def _mitsuba(p, opts):
    scale = rgb(p["rho_s"])
    if opts.get("fresnel", "dielectric") == "conductor":
        index = {"eta": rgb(p["eta"]), "k": rgb(p["k"])}
    else:
        index = {"eta": float(p["eta"])}
    if opts.get("geometry", "v_groove") == "smith":
        return {"type": "roughconductor", "distribution": "beckmann", "alpha": float(p["m"]),
                "k": 0.0, **index, "specular_reflectance": scale}
    return {"type": "fitter_torrance_sparrow", "alpha": float(p["m"]), **index,
            "specular_reflectance": scale}


def _plugin(mi):
    import drjit as dr

    base = cosine_sampled(mi)

    class TorranceSparrow(base):
        """rho_s D_n G F / (4 ci co): normalised Beckmann D, V-groove G, and the
        dielectric F (a float ``eta``) or Mitsuba's conductor F (rgb ``eta``, ``k``)."""

        def __init__(self, props):
            base.__init__(self, props)
            self.rho = props_rgb(mi, props, "specular_reflectance", 1.0)
            self.m = mi.Float(max(float(props.get("alpha", 0.2)), 1e-4))
            self.conductor = "k" in props
            if self.conductor:
                self.eta = props_rgb(mi, props, "eta", 1.0)
                self.k = props_rgb(mi, props, "k", 3.0)
            else:
                self.eta = mi.Float(float(props.get("eta", 1.5)))

        def _fresnel(self, cos):
            if not self.conductor:
                return mi.fresnel(cos, self.eta)[0]
            return mi.Color3f(*(mi.fresnel_conductor(cos, dr.llvm.ad.Complex2f(
                self.eta[c], self.k[c])) for c in range(3)))

        def _value(self, wi, wo):
            # Written from the lecture's angle forms, not the JAX identities:
            # beta the half vector's angle (atan2, float32-accurate near 0),
            # D_n = exp(-tan^2 beta / m^2) / (pi m^2 cos^4 beta), and the
            # V-groove G = min(1, 2 (n.h)(n.wo)/(wo.h), 2 (n.h)(n.wi)/(wo.h)).
            ci, co = wi.z, wo.z
            h = dr.normalize(wi + wo)
            ch = h.z
            beta = dr.atan2(dr.sqrt(h.x * h.x + h.y * h.y), ch)
            m2 = self.m * self.m
            cos4 = dr.square(dr.square(dr.cos(beta)))
            d = dr.exp(-dr.square(dr.tan(beta)) / m2) / (dr.pi * m2 * cos4)
            woh = dr.maximum(dr.dot(wo, h), 1e-30)
            g = dr.minimum(1.0, dr.minimum(2.0 * ch * co / woh, 2.0 * ch * ci / woh))
            f = self._fresnel(dr.clip(woh, 0.0, 1.0))
            val = d * dr.maximum(g, 0.0) * f / (4.0 * ci * co)
            return self.rho * dr.select(ch > 0, val, 0.0)

        def to_string(self):
            return f"fitter_torrance_sparrow[alpha={self.m}, eta={self.eta}]"

    return TorranceSparrow


def _derived(p, opts):
    """F0 per channel of a conductor (``fitter.bsdf.derived``); nothing for a dielectric."""
    if opts.get("fresnel", "dielectric") != "conductor":
        return {}
    return {"F0": conductor_f0(p["eta"], p["k"])}


#: eta of ``_interior``'s point, on the metal branch as the default start is (its k is
#: F0's inverse at eta = 1 only).
INTERIOR_ETA = 1.0


def _interior(p, opts, at_edge):
    """For a conductor channel with eta or k on its box's edge: eta = 1 and
    k = 2 sqrt(F0 / (1 - F0)), the point of the same F0 = k^2 / (4 + k^2)
    (``conductor_f0`` at eta = 1) on the metal branch (``Lobe.interior``)."""
    if opts.get("fresnel", "dielectric") != "conductor":
        return {}
    stuck = np.asarray(at_edge.get("eta", False)) | np.asarray(at_edge.get("k", False))
    if not np.any(stuck):
        return {}
    eta = np.asarray(p["eta"], dtype=np.float64)
    k = np.asarray(p["k"], dtype=np.float64)
    f0 = np.clip(conductor_f0(eta, k), 1e-12, 0.99)
    k_lo, k_hi = _K.lower, _K.upper
    k_new = np.clip(2.0 * np.sqrt(f0 / (1.0 - f0)), 2.0 * k_lo, 0.95 * k_hi)
    return {"eta": np.where(stuck, INTERIOR_ETA, eta), "k": np.where(stuck, k_new, k)}


def _complex_index(opts):
    """A conductor's eta + i k (``Lobe.complex_index``): solved along its circles of
    equal F0 (``fitter.fit._valley``)."""
    return ("eta", "k") if opts.get("fresnel") == "conductor" else None


def _quadrature(p):
    """Half vectors about n within the cap where the Beckmann exponent > e^-40;
    the horizon cuts broad lobes (a kink), hence twice the nodes."""
    return Quadrature("half", min(math.pi / 2, math.atan(float(p["m"]) * math.sqrt(40.0))), 2)


_M = Param("m", 1, 0.2, 1e-3, 1.0, "log", "Beckmann roughness (RMS facet slope)")
_K = Param("k", 3, 3.0, 1e-3, 20.0, "log",
           "extinction coefficient, the imaginary part of the complex index "
           "(Au ≈ 3.98, 2.39, 1.60); or a Mitsuba metal's name",
           named={n: k for n, (_, k) in METALS.items()})
_RHO = Param("rho_s", 1, 1.0, 0.0, 1.0, "logit", "scale of the lobe", free=False)

LOBE = Lobe(
    name="torrance_sparrow",
    kind="brdf",
    params=(
        _M,
        Param("eta", 1, 1.5, 1.0, 4.0, "eta", "relative index of refraction of the Fresnel term"),
        _RHO,
    ),
    options=(Option("geometry", ("v_groove", "smith"), "v_groove",
                    "shadowing-masking G: the lecture's V-groove (Cook-Torrance) or Beckmann "
                    "Smith (as Mitsuba's `roughconductor`)"),
             Option("fresnel", ("dielectric", "conductor"), "dielectric",
                    "Fresnel term: dielectric (scalar `eta`) or conductor (complex index "
                    "`eta` + i `k` per RGB channel, as Mitsuba's `roughconductor`; one image "
                    "pins F0 per channel, not `eta` and `k` separately)")),
    variants={("fresnel", "conductor"): (
        _M,
        Param("eta", 3, 1.0, 1e-2, 10.0, "log",
              "real part of the conductor's complex index of refraction (Au ≈ 0.14, 0.37, "
              "1.44); with `k` only F0 = ((η−1)²+k²)/((η+1)²+k²) is well determined; "
              "or a Mitsuba metal's name (`\"Au\"`, `\"Cu\"`, ...: `fitter/bsdf/metals.py`)",
              named={n: eta for n, (eta, _) in METALS.items()}),
        _K,
        _RHO)},
    scale="rho_s",
    shape=_shape,
    shape_grad=_shape_grad,
    doc="D G F / (π cosθ_i cosθ_o) with the lecture's D = exp(−tan²β/m²)/(4m²cos⁴β), i.e. "
        "normalized Beckmann D_n G F/(4 cosθ_i cosθ_o); Smith G is Walter et al.'s rational "
        "form, as Mitsuba's `roughconductor`",
    mitsuba=MitsubaMapping(_mitsuba, plugins={"fitter_torrance_sparrow": _plugin}),
    derived=_derived,
    interior=_interior,
    complex_index=_complex_index,
    hints=Hints(
        points=(*(Point(f"ts_{g}-m{m:g}", {"m": m, "eta": 4.0, "rho_s": 1.0}, {"geometry": g})
                  for g in ("v_groove", "smith") for m in (0.01, 0.2, 1.0)),
                # eta = 1: F = 0, nothing is reflected (positivity, reciprocity only).
                Point("ts_v_groove-eta1", {"m": 0.3, "eta": 1.0, "rho_s": 1.0},
                      {"geometry": "v_groove"}, conserving=False),
                # Gold and a dark, nearly dielectric conductor: F <= 1 per channel.
                *(Point(f"ts_{g}-conductor-m{m:g}", {"m": m, "eta": (0.143, 0.375, 1.442),
                                                       "k": (3.983, 2.386, 1.603), "rho_s": 1.0},
                        {"geometry": g, "fresnel": "conductor"})
                  for g in ("v_groove", "smith") for m in (0.05, 0.5)),
                Point("ts_smith-conductor-dark", {"m": 0.3, "eta": (4.0, 2.0, 0.5),
                                                  "k": (1e-3, 0.5, 8.0), "rho_s": 1.0},
                      {"geometry": "smith", "fresnel": "conductor"})),
        example={"m": 0.3, "eta": 1.7},
        quadrature=_quadrature),
)

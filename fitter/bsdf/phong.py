"""Phong-style glossy lobe, f = rho_s cos^e(alpha), alpha = angle(r(n, wi), wo).

r(n, wi) = 2 (n.wi) n - wi, so cos(alpha) = r.wo = 2 cos_i cos_o - wi.wo.
With ``normalized = true`` the lobe is scaled by (e + 2) / (2 pi), which makes
its directional-hemispherical reflectance at normal incidence exactly rho_s
(the lecture's integral of cos^n: 2 pi / (n + 2) with n = e + 1). The
lecture's un-normalised form can reflect more energy than it receives (for
e = 1, 2 pi / 3 rho_s at normal incidence); it is kept as the default because
it is the lecture's model, and flagged by ``tests/test_bsdf_properties.py``.
There rho_s is the lobe's peak, not a reflectance: energy conservation bounds
its albedo rho_s 2 pi / (e + 2), not rho_s, so a bright sharp highlight
(rho_s = 4, e = 300: albedo 0.083) is physical and its box reaches
``RHO_MAX``; normalised, rho_s is the albedo and its box is [0, 1]
(``Lobe.variants``).

pow is evaluated as exp(e log c) so e up to 1e4 is exact in float64.

Mitsuba has no Phong: the ``fitter_phong`` plugin here evaluates the same
lobe in drjit (``specular_reflectance`` rgb, ``exponent``, ``normalized``).

Reference: Teschner, *Materials 2*, "Example - glossy / specular reflection".
"""

import math

from .._lazy import jnp
from .._math import safe_pow
from .base import Hints, Lobe, Option, Param, Point, Quadrature
from .mitsuba_map import MitsubaMapping, cosine_sampled, props_rgb, rgb_unbounded


def _shape(p, opts, c):
    cos_alpha = 2.0 * c.cos_i * c.cos_o - c.cos_io
    e = p["e"]
    lobe = safe_pow(cos_alpha, e)
    if opts["normalized"]:
        lobe = lobe * (e + 2.0) / (2.0 * jnp.pi)
    return lobe


def _shape_grad(p, opts, c):
    """Shape and d shape / d e = shape * ln cos(alpha) (``Lobe.shape_grad``)."""
    cos_alpha = 2.0 * c.cos_i * c.cos_o - c.cos_io
    e = p["e"]
    pos = cos_alpha > 0
    log_c = jnp.where(pos, jnp.log(jnp.where(pos, cos_alpha, 1.0)), 0.0)
    lobe = jnp.where(pos, jnp.exp(e * log_c), 0.0)
    if opts["normalized"]:
        norm = (e + 2.0) / (2.0 * jnp.pi)
        return lobe * norm, {"e": lobe * (norm * log_c + 1.0 / (2.0 * jnp.pi))}
    return lobe, {"e": lobe * log_c}


def _mitsuba(p, opts):
    return {"type": "fitter_phong", "specular_reflectance": rgb_unbounded(p["rho_s"]),
            "exponent": float(p["e"]), "normalized": bool(opts["normalized"])}


def _plugin(mi):
    import drjit as dr

    base = cosine_sampled(mi)

    class Phong(base):
        """rho_s ((2 (n.wi) n - wi).wo)^e, optionally (e+2)/(2 pi)."""

        def __init__(self, props):
            base.__init__(self, props)
            self.rho = props_rgb(mi, props, "specular_reflectance", 0.5)
            e = float(props.get("exponent", 20.0))
            self.e = mi.Float(e)
            self.norm = mi.Float((e + 2.0) / (2.0 * math.pi)
                                 if props.get("normalized", False) else 1.0)

        def _value(self, wi, wo):
            # The lecture's form with the mirror vector built explicitly,
            # r = 2 (n.wi) n - wi (n = +z locally), not ``_shape``'s identity.
            r = mi.Vector3f(-wi.x, -wi.y, wi.z)
            c = dr.dot(r, wo)
            lobe = dr.select(c > 0, dr.exp(self.e * dr.log(dr.maximum(c, 1e-30))), 0.0)
            return self.rho * (lobe * self.norm)

        def to_string(self):
            return f"fitter_phong[e={self.e}, norm={self.norm}]"

    return Phong


def _quadrature(p):
    """Nodes about the mirror direction, within the cap where cos^e > e^-40."""
    return Quadrature("mirror", min(math.pi, math.sqrt(80.0 / float(p["e"]))))


_ONES = (1.0, 1.0, 1.0)

#: Upper bound of the lecture form's rho_s: its albedo at normal incidence is
#: rho_s 2 pi / (e + 2), so albedo <= 1 allows rho_s up to (e + 2) / (2 pi), 1592
#: at the largest e of the box (1e4). The box cannot follow e; this is the bound
#: physics sets over the whole box (fit in logit, which is log-like well below it).
RHO_MAX = 1600.0
_E = Param("e", 1, 20.0, 1.0, 1e4, "log", "specular exponent")

LOBE = Lobe(
    name="phong",
    kind="brdf",
    params=(
        Param("rho_s", 3, 0.5, 0.0, RHO_MAX, "logit",
              "peak value of the lobe (1/sr), not a reflectance: its albedo at normal "
              "incidence is ρ_s 2π/(e+2), ≤ 1 for ρ_s ≤ (e+2)/2π (the box allows that at "
              "e = 1e4)"),
        _E,
    ),
    variants={("normalized", True): (
        Param("rho_s", 3, 0.5, 0.0, 1.0, "logit",
              "specular albedo at normal incidence (directional-hemispherical reflectance)"),
        _E)},
    options=(Option("normalized", (False, True), False,
                    "scale by (e + 2)/(2π) so the lobe's albedo at normal incidence is ρ_s"),),
    scale="rho_s",
    shape=_shape,
    shape_grad=_shape_grad,
    doc="ρ_s cos^e α; normalized variant × (e+2)/2π. In the lecture form ρ_s is the peak "
        "(albedo at normal incidence ρ_s 2π/(e+2), which energy conservation bounds, not ρ_s); "
        "it can exceed energy conservation (flagged in the tests)",
    mitsuba=MitsubaMapping(_mitsuba, plugins={"fitter_phong": _plugin}),
    # cos alpha from float32 cosines is off by ~1e-7, cos^e by e times that: the
    # profile sent 10-18 of 30-54 points to float64 (benchmarks/profile_subset.py)
    single_precision=False,
    hints=Hints(
        points=(*(Point(f"phong_norm-e{e:g}", {"rho_s": _ONES, "e": e}, {"normalized": True})
                  for e in (1.0, 10.0, 100.0, 1e4)),
                # The lecture's form reflects up to 2 pi / (e + 2) > 1 (see above).
                *(Point(f"phong_lecture-e{e:g}", {"rho_s": _ONES, "e": e},
                        {"normalized": False}, conserving=False) for e in (1.0, 50.0))),
        example={"rho_s": (0.5, 0.4, 0.3), "e": 40.0},
        quadrature=_quadrature),
)

"""Beckmann microfacet distribution and shadowing-masking terms.

Directions point away from the surface; ``n`` is the macro normal and the
half vector is h = (wi + wo) / |wi + wo|.

References:
    Teschner, *Materials 3*, "Torrance-Sparrow specular material",
        "Beckmann distribution".
    Cook, Torrance (1982), "A reflectance model for computer graphics",
        ACM TOG 1(1) -- the V-groove shadowing/masking term.
    Walter, Marschner, Li, Torrance (2007), "Microfacet models for refraction
        through rough surfaces", EGSR, eq. 27 -- the rational approximation of
        the Beckmann Smith G1 that Mitsuba 3 uses.
"""

from __future__ import annotations

from .._lazy import jnp
from .._math import safe_div

#: Smallest roughness evaluated (Mitsuba clamps alpha the same way).
M_MIN = 1e-4

# Divisions by a function of m are written as products with its reciprocal,
# taken once per call: the Jacobian's renders are bound by per-sample divisions
# (benchmarks/README.md, "fourth stop" of 2026-12-05).


def beckmann_d_lecture(cos_h, tan2_h, m):
    """The lecture's Beckmann D = exp(-tan^2(beta)/m^2) / (4 m^2 cos^4(beta)).

    Args:
        cos_h: cos(beta) = n.h, (...); D = 0 where cos_h <= 0.
        tan2_h: tan^2(beta), (...), best computed as |n x H|^2 / (n.H)^2
            (``fitter.bsdf.base.cosines``), which is accurate near beta = 0.
        m: roughness, clamped to ``M_MIN``.

    This D is pi/4 times the normalised Beckmann D_n = exp(-tan^2/m^2) /
    (pi m^2 cos^4), so the lecture's D G F / (pi cos_i cos_o) equals
    D_n G F / (4 cos_i cos_o).
    """
    m = jnp.maximum(m, M_MIN)
    m2 = m * m
    # exp(-746) is 0 in float64, so D is exactly 0 beyond; and 1/cos^4 is
    # written (1 + tan^2)^2: cos_h^4 underflows (its gradient overflows) at
    # grazing half vectors.
    up = (cos_h > 0) & (tan2_h < 746.0 * m2)
    tan2 = jnp.where(up, tan2_h, 0.0)
    inv_m2 = 1.0 / m2
    return jnp.where(up, jnp.exp(-tan2 * inv_m2) * (1.0 + tan2) ** 2 * (0.25 * inv_m2), 0.0)


def beckmann_dlog_d_dm(tan2_h, m):
    """d ln D / d m = 2 tan^2(beta) / m^3 - 2 / m of the lecture's (or the
    normalised) Beckmann D, (...); m clamped to ``M_MIN`` (derivative 0 below)."""
    mc = jnp.maximum(m, M_MIN)
    return jnp.where(m >= M_MIN, tan2_h * (2.0 / (mc * mc * mc)) - 2.0 / mc, 0.0)


def g_v_groove(cos_h, cos_i, cos_o, wo_h):
    """Torrance-Sparrow / Cook-Torrance V-groove shadowing-masking.

    G = min(1, 2 (n.h)(n.wo)/(wo.h), 2 (n.h)(n.wi)/(wo.h)), inputs (...), with
    n.h >= 0 (``Cosines.cos_h``).
    """
    ok = wo_h > 0
    # With n.h >= 0 and wo.h > 0, min(2 n.h a / x, 2 n.h b / x) = 2 n.h min(a, b) / x
    # bit for bit (rounding is monotonic): one division per sample, not two.
    return jnp.clip(safe_div(2.0 * cos_h * jnp.minimum(cos_o, cos_i), wo_h, ok), 0.0, 1.0)


def smith_g1_beckmann(cot_w, m):
    """Walter et al. (2007) rational approximation of the Beckmann Smith G1.

    a = 1 / (m tan(theta)); G1 = 1 for a >= 1.6, else
    (3.535 a + 2.181 a^2) / (1 + 2.276 a + 2.577 a^2). Mitsuba 3's
    ``roughconductor`` uses the same form. ``cot_w`` is cot(theta) of w's
    angle to n (``Cosines.cot_i``, ``cot_o``; ``base.COT_NORMAL`` along n).
    """
    return smith_g1_beckmann_dm(cot_w, m)[0]  # the unused derivative is compiled away


def smith_g1_beckmann_dm(cot_w, m):
    """G1 (as ``smith_g1_beckmann``) and dG1/dm, each (...).

    a = cot / m gives da/dm = -a/m; G1 = N(a)/Q(a) gives
    dG1/da = (N' Q - N Q') / Q^2. Zero where G1 = 1 (a >= 1.6) or m < M_MIN.
    """
    mc = jnp.maximum(m, M_MIN)
    a = cot_w * (1.0 / mc)  # (COT_NORMAL / mc stays finite: 1e34 at M_MIN)
    short = a < 1.6
    a_s = jnp.where(short, a, 1.0)
    num = 3.535 * a_s + 2.181 * a_s * a_s
    den = 1.0 + 2.276 * a_s + 2.577 * a_s * a_s
    dg_da = ((3.535 + 4.362 * a_s) * den - num * (2.276 + 5.154 * a_s)) / (den * den)
    dg_dm = jnp.where(short & (m >= M_MIN), dg_da * (-a_s * (1.0 / mc)), 0.0)
    return jnp.where(short, num / den, 1.0), dg_dm


def g_smith(cot_i, cot_o, m):
    """Separable Smith shadowing-masking G1(wi) G1(wo) (Beckmann, Walter form), from
    the cotangents of wi's and wo's angles to n."""
    return smith_g1_beckmann(cot_i, m) * smith_g1_beckmann(cot_o, m)

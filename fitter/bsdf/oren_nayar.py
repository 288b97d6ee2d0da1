"""Oren-Nayar rough diffuse lobe, the lecture's qualitative A/B model.

f = rho_d / pi * (A + B max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta)),
A = 1 - sigma^2 / (2 (sigma^2 + 0.33)), B = 0.45 sigma^2 / (sigma^2 + 0.09),
alpha = max(theta_i, theta_o), beta = min(theta_i, theta_o).

``sigma`` is the standard deviation, in radians, of the angle between the
facet normals and the surface normal (sigma^2 its variance). sigma = 0 gives
A = 1, B = 0: exactly Lambert.

No angles are formed (arccos has an infinite derivative at 1): with
sin(theta_i) sin(theta_o) cos(phi_i - phi_o) = wi.wo - cos_i cos_o and
sin(alpha) sin(beta) = sin(theta_i) sin(theta_o), cos(beta) = max(cos_i, cos_o),

    max(0, cos dphi) sin(alpha) tan(beta) = max(0, wi.wo - cos_i cos_o) / max(cos_i, cos_o).

References:
    Teschner, *Materials 3*, "Oren-Nayar diffuse material".
    Oren, Nayar (1994), "Generalization of Lambert's reflectance model",
        SIGGRAPH, eq. 30 (qualitative model).
"""

import jax.numpy as jnp

from .._math import safe_div
from .base import Lobe, Param


def coefficients(sigma):
    """(A, B) of the qualitative Oren-Nayar model for facet slope std-dev sigma."""
    s2 = sigma * sigma
    return 1.0 - s2 / (2.0 * (s2 + 0.33)), 0.45 * s2 / (s2 + 0.09)


def _shape(p, opts, c):
    a, b = coefficients(p["sigma"])
    cmax = jnp.maximum(c.cos_i, c.cos_o)
    term = safe_div(jnp.maximum(c.cos_io - c.cos_i * c.cos_o, 0.0), cmax, cmax > 0)
    return (a + b * term) / jnp.pi


def _shape_grad(p, opts, c):
    """Shape and d shape / d sigma (``Lobe.shape_grad``): dA/dsigma =
    -0.33 sigma / (sigma^2 + 0.33)^2, dB/dsigma = 0.081 sigma / (sigma^2 + 0.09)^2."""
    sigma = p["sigma"]
    s2 = sigma * sigma
    a, b = coefficients(sigma)
    da = -0.33 * sigma / ((s2 + 0.33) * (s2 + 0.33))
    db = 0.081 * sigma / ((s2 + 0.09) * (s2 + 0.09))
    cmax = jnp.maximum(c.cos_i, c.cos_o)
    term = safe_div(jnp.maximum(c.cos_io - c.cos_i * c.cos_o, 0.0), cmax, cmax > 0)
    return (a + b * term) / jnp.pi, {"sigma": (da + db * term) / jnp.pi}


def _mitsuba(p, opts):
    """Mitsuba has no Oren-Nayar: ``fitter.mitsuba`` registers this plugin."""
    return {"type": "fitter_oren_nayar", "reflectance": {"type": "rgb", "value": [float(x) for x in p["rho_d"]]},
            "sigma": float(p["sigma"])}


LOBE = Lobe(
    name="oren_nayar",
    kind="brdf",
    params=(
        Param("rho_d", 3, 0.5, 0.0, 1.0, "logit", "diffuse reflectance, RGB"),
        Param("sigma", 1, 0.3, 0.0, 1.5, "box",
              "std-dev of facet slope angle, radians (lecture: sigma^2 <= 1)"),
    ),
    scale="rho_d",
    shape=_shape,
    shape_grad=_shape_grad,
    doc="Oren-Nayar (qualitative A/B form); sigma = 0 is Lambert.",
    mitsuba=_mitsuba,
)

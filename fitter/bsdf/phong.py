"""Phong-style glossy lobe, f = rho_s cos^e(alpha), alpha = angle(r(n, wi), wo).

r(n, wi) = 2 (n.wi) n - wi, so cos(alpha) = r.wo = 2 cos_i cos_o - wi.wo.
With ``normalized = true`` the lobe is scaled by (e + 2) / (2 pi), which makes
its directional-hemispherical reflectance at normal incidence exactly rho_s
(the lecture's integral of cos^n: 2 pi / (n + 2) with n = e + 1). The
lecture's un-normalised form can reflect more energy than it receives (for
e = 1, 2 pi / 3 rho_s at normal incidence); it is kept as the default because
it is the lecture's model, and flagged by ``tests/test_bsdf_properties.py``.

pow is evaluated as exp(e log c) so e up to 1e4 is exact in float64.

Reference: Teschner, *Materials 2*, "Example - glossy / specular reflection".
"""

import jax.numpy as jnp

from .._math import safe_pow
from .base import Lobe, Option, Param


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
    """Mitsuba has no Phong: ``fitter.mitsuba`` registers this plugin."""
    return {"type": "fitter_phong", "specular_reflectance": {"type": "rgb", "value": [float(x) for x in p["rho_s"]]},
            "exponent": float(p["e"]), "normalized": bool(opts["normalized"])}


LOBE = Lobe(
    name="phong",
    kind="brdf",
    params=(
        Param("rho_s", 3, 0.5, 0.0, 1.0, "logit", "specular reflectance, RGB"),
        Param("e", 1, 20.0, 1.0, 1e4, "log", "specular exponent"),
    ),
    options=(Option("normalized", (False, True), False, "scale by (e + 2) / (2 pi)"),),
    scale="rho_s",
    shape=_shape,
    shape_grad=_shape_grad,
    doc="Phong lobe rho_s cos^e(alpha), optionally energy-normalised.",
    mitsuba=_mitsuba,
)

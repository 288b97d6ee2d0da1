"""Lambertian diffuse lobe, f = rho_d / pi.

Reference: Teschner, *Materials 1*, "BRDF for diffuse reflecting material".
"""

import jax.numpy as jnp

from .base import Lobe, Param


def _shape(p, opts, c):
    return jnp.full_like(c.cos_i, 1.0 / jnp.pi)


def _mitsuba(p, opts):
    """Mitsuba's ``diffuse`` is exactly rho_d / pi."""
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(x) for x in p["rho_d"]]}}


LOBE = Lobe(
    name="lambert",
    kind="brdf",
    params=(
        Param("rho_d", 3, 0.5, 0.0, 1.0, "logit", "diffuse (bihemispherical) reflectance, RGB"),
    ),
    scale="rho_d",
    shape=_shape,
    doc="Lambert: f = rho_d / pi.",
    mitsuba=_mitsuba,
)

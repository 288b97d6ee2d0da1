"""Lambertian diffuse lobe, f = rho_d / pi.

Mitsuba's ``diffuse`` is exactly rho_d / pi.

Reference: Teschner, *Materials 1*, "BRDF for diffuse reflecting material".
"""

from .._lazy import jnp
from .base import Hints, Lobe, Param, Point
from .mitsuba_map import MitsubaMapping, rgb


def _uniform(p, opts):
    return 1.0 / jnp.pi


def _shape(p, opts, c):
    return jnp.full_like(c.cos_i, _uniform(p, opts))


def _mitsuba(p, opts):
    return {"type": "diffuse", "reflectance": rgb(p["rho_d"])}


LOBE = Lobe(
    name="lambert",
    kind="brdf",
    params=(
        Param("rho_d", 3, 0.5, 0.0, 1.0, "logit", "diffuse (bihemispherical) reflectance"),
    ),
    scale="rho_d",
    shape=_shape,
    uniform=_uniform,
    doc="ρ_d/π",
    mitsuba=MitsubaMapping(_mitsuba),
    hints=Hints(points=(Point("lambert", {"rho_d": (1.0, 1.0, 1.0)}),),
                example={"rho_d": (0.6, 0.4, 0.2)}),
)

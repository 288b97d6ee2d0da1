"""Perfect mirror: L_o = rho_m L_i(r), r the mirror direction.

It only reflects the environment (a delta BRDF sees delta lights with
probability zero, as in Mitsuba).

Reference: Teschner, *Materials 2*, "Example - mirror reflection".
"""

from .._math import reflect
from .base import Lobe, Param


def _radiance(p, opts, hit, env):
    return p["rho_m"] * env(reflect(hit.ray_dir, hit.normal))


def _mitsuba(p, opts):
    """Mitsuba's ``conductor`` with material ``none`` has Fresnel = 1, so f = rho_m."""
    return {"type": "conductor", "material": "none", "specular_reflectance": {"type": "rgb", "value": [float(x) for x in p["rho_m"]]}}


LOBE = Lobe(
    name="mirror",
    kind="specular",
    params=(Param("rho_m", 3, 1.0, 0.0, 1.0, "logit", "mirror reflectance, RGB"),),
    radiance=_radiance,
    doc="Perfect mirror reflecting the environment.",
    mitsuba=_mitsuba,
)

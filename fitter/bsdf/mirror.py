"""Perfect mirror: L_o = rho_m L_i(r), r the mirror direction.

It only reflects the environment (a delta BRDF sees delta lights with
probability zero, as in Mitsuba). Mitsuba's ``conductor`` with material
``none`` has Fresnel = 1, so f = rho_m there too.

Reference: Teschner, *Materials 2*, "Example - mirror reflection".
"""

from .._math import reflect
from .base import Lobe, Param
from .mitsuba_map import MitsubaMapping, rgb

#: Mitsuba ``path`` depth for a mirror, also when summed with an opaque lobe.
MITSUBA_DEPTH = 4


def _radiance(p, opts, hit, env):
    return p["rho_m"] * env(reflect(hit.ray_dir, hit.normal))


def _mitsuba(p, opts):
    return {"type": "conductor", "material": "none", "specular_reflectance": rgb(p["rho_m"])}


LOBE = Lobe(
    name="mirror",
    kind="specular",
    params=(Param("rho_m", 3, 1.0, 0.0, 1.0, "logit", "mirror reflectance"),),
    scale="rho_m",  # the radiance is linear in it (the exposure check's reflectance scale)
    radiance=_radiance,
    doc="ρ_m L_env(reflected direction)",
    single_precision=False,  # reflected rays into the map, as the dielectric's: not measured
    mitsuba=MitsubaMapping(_mitsuba, max_depth=lambda opts: MITSUBA_DEPTH),
)

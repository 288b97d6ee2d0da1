"""Perfect mirror: L_o = rho_m L_i(r), r the mirror direction.

It only reflects the environment (a delta BRDF sees delta lights with
probability zero, as in Mitsuba).

Reference: Teschner, *Materials 2*, "Example - mirror reflection".
"""

from .._math import reflect
from .base import Lobe, Param


def _radiance(p, opts, hit, env):
    return p["rho_m"] * env(reflect(hit.ray_dir, hit.normal))


LOBE = Lobe(
    name="mirror",
    kind="specular",
    params=(Param("rho_m", 3, 1.0, 0.0, 1.0, "logit", "mirror reflectance, RGB"),),
    radiance=_radiance,
    doc="Perfect mirror reflecting the environment.",
)

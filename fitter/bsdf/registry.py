"""The lobe registry: name -> Lobe. Adding a lobe is one module + one line here."""

from . import dielectric, lambert, mirror, oren_nayar, phong, torrance_sparrow
from .base import Lobe

LOBES: dict[str, Lobe] = {
    m.LOBE.name: m.LOBE
    for m in (lambert, oren_nayar, phong, torrance_sparrow, mirror, dielectric)
}

"""BSDF lobes of the lecture, each in its own module, found through ``LOBES``."""

from .base import Lobe as Lobe, Option as Option, Param as Param, SurfaceHit as SurfaceHit
from .registry import LOBES as LOBES

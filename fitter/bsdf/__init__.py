"""BSDF lobes of the lecture, each in its own module, found through ``LOBES``."""

from .base import Hints as Hints
from .base import Lobe as Lobe
from .base import Option as Option
from .base import Param as Param
from .base import Point as Point
from .base import Quadrature as Quadrature
from .base import SurfaceHit as SurfaceHit
from .mitsuba_map import MitsubaMapping as MitsubaMapping
from .registry import LOBES as LOBES
from .registry import registered as registered

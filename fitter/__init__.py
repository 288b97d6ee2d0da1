"""fitter: recover sphere material parameters from images, with a JAX forward model.

Importing ``fitter`` enables JAX float64 (fits default to float64); Mitsuba
and OpenImageIO are imported only by the code paths that need them.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from .bsdf import LOBES as LOBES  # noqa: E402
from .material import Material as Material, MaterialError as MaterialError  # noqa: E402
from .render import Renderer as Renderer, render as render  # noqa: E402
from . import fit as fit  # noqa: E402  (callable: fitter.fit(target, scene, material, ...))
from .fit import FitResult as FitResult, fit_batch as fit_batch  # noqa: E402
from .scene import (  # noqa: E402
    Camera as Camera,
    DirectionalLight as DirectionalLight,
    Environment as Environment,
    PointLight as PointLight,
    Scene as Scene,
    Sphere as Sphere,
)

__version__ = "0.1.0"

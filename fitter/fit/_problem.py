"""The least-squares problem of a fit: coordinates, residuals, robust losses.

Everything the jitted solver needs is split into hashable static structure
(``Spec``) and array data (``Data``), so one compiled solver serves every fit
of the same shapes (and the persistent compilation cache can reuse it).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from .. import transforms
from .._math import single as to_single
from ..environment import EnvData
from ..geometry import Geometry
from ..material import Material
from ..render import render_active
from ._names import LOSSES

#: A fitted value within this fraction of its range from a box edge is "at bound".
AT_BOUND = 1e-4


@dataclasses.dataclass(frozen=True)
class Block:
    """One free parameter: its key, size (1 or 3) and transform box."""

    key: str
    size: int
    transform: str
    lower: float
    upper: float


@dataclasses.dataclass(frozen=True)
class Spec:
    """Static structure of a fit (a jit cache key)."""

    material: Material
    env_type: str
    blocks: tuple[Block, ...]
    loss: str = "l2"
    loss_scale: float = 1.0

    @property
    def n(self) -> int:
        return sum(b.size for b in self.blocks)

    def slices(self):
        start = 0
        for b in self.blocks:
            yield b, slice(start, start + b.size)
            start += b.size

    def coordinates(self) -> list[str]:
        """Names of the coordinates in order: 'torrance_sparrow.m', 'lambert.rho_d[0]', ..."""
        return [c for b in self.blocks
                for c in ([b.key] if b.size == 1 else [f"{b.key}[{i}]" for i in range(3)])]


class Data(NamedTuple):
    """Arrays of a fit: geometry of the fitted pixels, target, weights, fixed values."""

    geometry: Geometry
    env: EnvData
    sphere: Any
    target: jnp.ndarray  # (P, 3)
    weights: jnp.ndarray  # (P, 3); 0 drops a value
    fixed: dict


def params_from_z(spec: Spec, z, fixed: dict) -> dict:
    """Complete user-unit parameters from coordinates ``z`` (n,) and fixed values."""
    params = dict(fixed)
    for b, sl in spec.slices():
        x = transforms.to_user(b.transform, z[sl], b.lower, b.upper)
        params[b.key] = x if b.size == 3 else x[0]
    return params


def z_from_params(spec: Spec, params: dict, margin: float = transforms.EDGE):
    """Coordinates (n,) of user values; values nearer than ``margin`` (fraction of
    the range) to a box edge are moved inside."""
    return np.concatenate([
        np.atleast_1d(transforms.to_unconstrained(b.transform, params[b.key], b.lower, b.upper,
                                                  margin))
        for b in spec.blocks]) if spec.blocks else np.zeros(0)


def _huber_factor(u2):
    """2 rho(u) / u^2 of Huber: rho = u^2/2 for |u| <= 1, |u| - 1/2 beyond."""
    au = jnp.sqrt(u2)
    return jnp.where(au <= 1.0, 1.0, (2.0 * au - 1.0) / u2)


def _cauchy_factor(u2):
    """2 rho(u) / u^2 of Cauchy: rho = log(1 + u^2) / 2."""
    return jnp.log1p(u2) / u2


#: Robust losses by name: 2 rho(u) / u^2 of the scaled residual u = r / c.
_ROBUST_FACTORS = {"huber": _huber_factor, "cauchy": _cauchy_factor}

# The registry implements exactly the names the config reader accepts.
assert ("l2", *_ROBUST_FACTORS) == LOSSES, "fitter.fit._names.LOSSES lists the losses"


def user_values(spec: Spec, z, fixed: dict) -> dict:
    """User values (NumPy float64) of coordinates ``z`` plus the ``fixed`` values."""
    p = params_from_z(spec, np.asarray(z, dtype=np.float64),
                      {k: np.asarray(v, dtype=np.float64) for k, v in fixed.items()})
    return {k: np.asarray(v) for k, v in p.items()}


def format_value(v) -> str:
    """A scalar or (3,) user value for messages, 6 significant digits."""
    a = np.asarray(v)
    return f"{float(a):.6g}" if a.ndim == 0 else "[" + ", ".join(f"{x:.6g}" for x in a) + "]"


def frame(spec: Spec, z):
    """Per coordinate at ``z``, float64 (n,) each: the user value x, dx/dz, the
    natural scale (``transforms.natural_scale``) and whether x is at a bound
    (within ``AT_BOUND`` of its box's edge, in log for a log box)."""
    z = np.asarray(z, dtype=np.float64)
    parts = []
    for b, sl in spec.slices():
        x = transforms.to_user(b.transform, z[sl], b.lower, b.upper)
        u = transforms.box_fraction(b.transform, x, b.lower, b.upper)
        parts.append((x, transforms.derivative(b.transform, z[sl], b.lower, b.upper),
                      transforms.natural_scale(b.transform, x, b.lower, b.upper),
                      (u < AT_BOUND) | (u > 1.0 - AT_BOUND)))
    return tuple(np.concatenate([np.atleast_1d(p[i]) for p in parts]) for i in range(4))


def single_coordinates(spec: Spec, zs) -> np.ndarray:
    """Coordinates (k, n) of the points ``zs`` (k, n) whose user values are
    theirs rounded to float32 (``residuals``' ``single``), to first order:
    z + (x32 - x) / (dx/dz); unchanged where dx/dz is 0 (a saturated z)."""
    zs = np.array(zs, dtype=np.float64)
    for b, sl in spec.slices():
        x = transforms.to_user(b.transform, zs[:, sl], b.lower, b.upper)
        d = transforms.derivative(b.transform, zs[:, sl], b.lower, b.upper)
        dx = x.astype(np.float32).astype(np.float64) - x
        zs[:, sl] += np.where(d > 0, dx / np.where(d > 0, d, 1.0), 0.0)
    return zs


def blocks_of(spec: Spec, flags: np.ndarray) -> list[str]:
    """Keys of the blocks with any of their coordinates flagged in ``flags`` (n,)."""
    return [b.key for b, sl in spec.slices() if np.any(flags[sl])]


def robust(r, loss: str, scale: float):
    """Residuals whose squares sum to 2 * sum rho(r): least squares with a robust loss.

    huber: rho = r^2/2 for |r| <= c, c(|r| - c/2) beyond; cauchy:
    rho = c^2/2 log(1 + (r/c)^2). Written as r * sqrt(2 rho(r) / r^2), which
    is smooth through r = 0 (Triggs et al. 2000, "Bundle adjustment",
    sec. 4.3, square-rooted robust cost).
    """
    if loss == "l2":
        return r
    if loss not in _ROBUST_FACTORS:
        raise ValueError(f"unknown loss {loss!r}; known: {LOSSES}")
    u = r / scale
    u2 = u * u
    small = u2 < 1e-12
    factor = _ROBUST_FACTORS[loss](jnp.where(small, 1.0, u2))
    return r * jnp.sqrt(jnp.where(small, 1.0, factor))


def residuals(z, data: Data, spec: Spec, single: bool = False):
    """Weighted (robust) residuals (model - target), flattened to (P*3,).

    ``single``: the model rendered in float32 from the parameters' values
    rounded to float32 (``single_coordinates`` says where that puts z), the
    rest as ``data``'s dtype."""
    params = params_from_z(spec, z, data.fixed)
    scene = (params, data.geometry, data.env, data.sphere)
    if single:
        scene = to_single(scene)
    model = render_active(*scene, material=spec.material, env_type=spec.env_type)
    r = (model.astype(data.target.dtype) - data.target) * data.weights
    return robust(r, spec.loss, spec.loss_scale).reshape(-1)

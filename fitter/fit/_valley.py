"""Solver coordinates along a complex index's valley of equal F0.

A conductor channel's index eta + i k has the normal-incidence reflectance
F0 = ((eta - 1)^2 + k^2) / ((eta + 1)^2 + k^2); the points of one F0 lie on
the circle (eta - R)^2 + k^2 = R^2 - 1, R = (1 + F0) / (1 - F0) (radius
2 sqrt(F0) / (1 - F0)), of which k >= 0 is an arc. One image fixes F0 and
only weakly the place on the arc, and Levenberg-Marquardt in the fit's
(log eta, log k) creeps along that curved valley (gold under a one-texel sun,
64^2: 278 and 114 steps). The solver here moves per channel in F0 and the
arc's angle phi (eta = R + rho cos phi, k = rho sin phi), each a logit of its
interval inside the parameters' boxes, so the valley is a coordinate line, as
in Gulbrandsen's edge tint (JCGT 3(4), 2014: 16-17 steps to the same minimum
there, ``benchmarks/conductor_coordinates.py``). The angle, not eta along the
arc: near k = 0 the arc runs across eta, where eta would pack k's decade from
1e-3 to 1e-2 into 1e-5 of its interval.
Only the solve uses them: its result goes back to the fit's own coordinates z
(``to_z``), where every check works as before.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import transforms
from ..bsdf.fresnel import conductor_f0
from ._problem import Spec

#: asin and acos arguments are kept this far inside [-1, 1] (their derivatives
#: are infinite at the ends).
_SAFE = 1e-12


class Chart(NamedTuple):
    """One complex index's blocks: slices of z (3 channels each) and boxes."""

    real: slice
    imag: slice
    real_box: tuple
    imag_box: tuple


def charts(spec: Spec) -> tuple[Chart, ...]:
    """The complex indices (``Lobe.complex_index``) of ``spec`` whose two RGB
    parameters are both fitted in log boxes whose arcs ``_angles`` covers
    (``_one_side``); () where there is none."""
    blocks = {b.key: (b, sl) for b, sl in spec.slices()}
    out = []
    for lobe in spec.material.lobe_objects:
        pair = lobe.complex_index(spec.material.options_of(lobe.name)) \
            if lobe.complex_index else None
        if not pair:
            continue
        (re, s_re), (im, s_im) = (blocks.get(f"{lobe.name}.{n}", (None, None)) for n in pair)
        if re is None or im is None or not (re.size == im.size == 3) or not (
                re.transform == im.transform == "log"):
            continue
        chart = Chart(s_re, s_im, (re.lower, re.upper), (im.lower, im.upper))
        if _one_side(chart):
            out.append(chart)
    return tuple(out)


def _f0_box(c: Chart):
    """F0's range over the boxes: F0 rises with k, and in eta falls to its least at
    eta = sqrt(1 + k^2) and rises beyond it; so the least k at the eta nearest that
    point, the most k at an end of eta's box."""
    (a, b), (kc, kd) = c.real_box, c.imag_box
    least = conductor_f0(min(max((1.0 + kc * kc) ** 0.5, a), b), kc)
    return float(least), float(max(conductor_f0(a, kd), conductor_f0(b, kd)))


def _circle(r):
    return (1.0 + r) / (1.0 - r), 2.0 * jnp.sqrt(r) / (1.0 - r)


def _bounds(c: Chart, big_r, rho, xp=jnp):
    """(lo, hi) of phi where k >= its least and eta lies in its box, and the cut
    of k <= its most (phi <= cut or phi >= pi - cut where it limits: kd < rho)."""
    (a, b), (kc, kd) = c.real_box, c.imag_box
    asin = lambda x: xp.arcsin(xp.clip(x, -1.0 + _SAFE, 1.0 - _SAFE))  # noqa: E731
    acos = lambda x: xp.arccos(xp.clip(x, -1.0 + _SAFE, 1.0 - _SAFE))  # noqa: E731
    lo = xp.maximum(asin(kc / rho), acos((b - big_r) / rho))
    hi = xp.minimum(xp.pi - asin(kc / rho), acos((a - big_r) / rho))
    return lo, hi, asin(kd / rho), kd < rho


def _angles(c: Chart, big_r, rho):
    """The interval (lo, hi) of phi (3,) whose points of the arc lie in the boxes,
    on the arc's side of small eta where k's most cuts the arc in two (``charts``
    makes sure the other side then lies outside eta's box)."""
    lo, hi, cut, limited = _bounds(c, big_r, rho)
    upper = jnp.maximum(lo, jnp.pi - cut)
    small_eta = upper <= hi
    lo = jnp.where(limited & small_eta, upper, lo)
    hi = jnp.where(limited & ~small_eta, jnp.minimum(hi, cut), hi)
    return lo, jnp.maximum(hi, lo)


def _one_side(c: Chart) -> bool:
    """Whether, for every F0 of the boxes (a dense grid), the points of its arc in
    the boxes are one interval of phi (so ``_angles`` reaches them all): true for
    the lobe's own boxes; narrower ``bounds`` can leave two."""
    r_lo, r_hi = _f0_box(c)
    r = np.unique(np.concatenate([np.geomspace(max(r_lo, 1e-300), r_hi, 2000),
                                  np.linspace(r_lo, r_hi, 2000)]))
    big_r, rho = (1.0 + r) / (1.0 - r), 2.0 * np.sqrt(r) / (1.0 - r)
    lo, hi, cut, limited = _bounds(c, big_r, rho, np)
    both = (np.maximum(lo, np.pi - cut) <= hi) & (lo <= np.minimum(hi, cut))
    return not np.any(limited & both)


def to_z(w, chs: tuple[Chart, ...]):
    """The fit's coordinates z (n,) of solver coordinates w (n,)."""
    for c in chs:
        r = transforms.to_user("box", w[c.real], *_f0_box(c))
        big_r, rho = _circle(r)
        lo, hi = _angles(c, big_r, rho)
        phi = lo + (hi - lo) * jax.nn.sigmoid(w[c.imag])
        n, k = big_r + rho * jnp.cos(phi), rho * jnp.sin(phi)
        w = w.at[c.real].set(transforms.to_unconstrained("log", n, *c.real_box)).at[
            c.imag].set(transforms.to_unconstrained("log", k, *c.imag_box))
    return w


def to_w(z, chs: tuple[Chart, ...]):
    """Solver coordinates w (n,) of the fit's coordinates z (n,) (``to_z``'s inverse
    inside the boxes; a point on an interval's edge moved ``transforms.EDGE`` inside)."""
    for c in chs:
        n = transforms.to_user("log", z[c.real], *c.real_box)
        k = transforms.to_user("log", z[c.imag], *c.imag_box)
        r_lo, r_hi = _f0_box(c)
        r = jnp.clip(conductor_f0(n, k), r_lo, r_hi)
        big_r, rho = _circle(r)
        lo, hi = _angles(c, big_r, rho)
        u = (jnp.arctan2(k, n - big_r) - lo) / jnp.maximum(hi - lo, 1e-300)  # (may be 0)
        z = z.at[c.real].set(transforms.to_unconstrained("box", r, r_lo, r_hi)).at[
            c.imag].set(transforms.logit(jnp.clip(u, transforms.EDGE, 1.0 - transforms.EDGE)))
    return z

"""A best fit stopped in a corner of its box that its lobe's valley leads out of.

Some parameters trade along a valley of nearly equal images whose branch ends
on the box's edge: a conductor's eta and k along the curve of equal F0, whose
dielectric-like branch ends at eta = 10, k = 1e-3, where F0 cannot rise. A
solve that wanders down such a branch stops there, converged, at a wrong
value of what the image does determine (gold, m = 0.05, under a sky with a
one-texel sun, 64^2, Mitsuba: F0 6-8 stated errors off, cost 312 against 9.2
at the truth). ``leave``: where the best fit has such a lobe's parameters on
the edge, the solve is run again from the lobe's ``interior`` point (the same
valley, inside the box); the lower cost is kept, and the second solve is
listed as one more start.
"""

from __future__ import annotations

import numpy as np

from ..material import lobe_params
from ._compile import best_start
from ._problem import Spec, frame, user_values, z_from_params


def interior_start(spec: Spec, z, fixed: dict):
    """(coordinates (n,) of the lobes' ``interior`` point for the fit at ``z``
    (``Lobe.interior``), the keys it moves), or None where no free parameter of
    such a lobe lies on its box's edge (``_problem.AT_BOUND``)."""
    at = frame(spec, z)[3]
    edge = {blk.key: at[sl] for blk, sl in spec.slices()}
    values = user_values(spec, z, fixed)
    moved = {}
    for lobe in spec.material.lobe_objects:
        prefix = lobe.name + "."
        flags = {k[len(prefix):]: v for k, v in edge.items() if k.startswith(prefix)}
        if lobe.interior is None or not any(np.any(v) for v in flags.values()):
            continue
        point = lobe.interior(lobe_params(values, lobe.name),
                              spec.material.options_of(lobe.name), flags) or {}
        moved.update({prefix + name: v for name, v in point.items() if prefix + name in edge})
    if not moved:
        return None
    return z_from_params(spec, {**values, **moved}), sorted(moved)


def leave(problem, first, data, solve_starts, say):
    """(``first``, ``_drivers.solve_starts``' tuple, with one more start, the
    lobes' interior point of its best fit, where that fit lies in such a
    corner; the best of all kept (``best_start``); a note saying so, or None)."""
    zs, codes, steps, costs, best, jr, t_compile = first
    found = interior_start(problem.spec, zs[best], data.fixed)
    if found is None:
        return first, None
    z1, keys = found
    zs1, codes1, steps1, costs1, _, jr1, tc = solve_starts(
        problem, z1[None], data, say, "off the box's edge: ")
    note = (f"{', '.join(keys)} stopped on the box's edge (cost {float(costs[best]):.4g}); "
            f"solved again from inside the box along the same valley: cost "
            f"{float(costs1[0]):.4g}, ")
    zs, codes, steps, costs = (np.concatenate([a, b]) for a, b in
                               ((zs, zs1), (codes, codes1), (steps, steps1), (costs, costs1)))
    new = int(best_start(costs, zs))
    note += "kept" if new == len(costs) - 1 else "the first fit kept"
    return (zs, codes, steps, costs, new, (jr1 if new == len(costs) - 1 else jr),
            t_compile + tc), note

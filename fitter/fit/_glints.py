"""A parameter that rests on a glint: refit it from the other pixels.

A coordinate whose information sits in a pixel or two (``_adequacy.few_pixels``:
a sun's glint on a glass or mirror sphere, a highlight smaller than a pixel)
takes its error from those pixels' own residuals, which cannot measure their
noise; where that noise is far above the rest of the image's (the Monte Carlo
noise of a glint, the shot noise of a bright highlight) the fit is confidently
wrong. Without a known noise level the fit is solved once more with those
pixels weighted 0 (``Problem.without``: the same shapes, the same compiled
solve). The refit is kept if it converges and leaves no parameter without
information in the other pixels; otherwise the first fit stands and such a
parameter is listed unidentifiable (``_verdict.report``).

Measured (64^2, a sky with a one-texel sun ~2000 times it, Mitsuba 2048-4096
spp): a mirror's rho_m rested on the sun's glint (1.1 effective pixels) and
came out 0.011 off, now within 1e-5; a glass sphere's eta on it (1.09)
0.0105 off, 7 stated errors, now 1.5011 +- 0.0013 (truth 1.5). A Phong
e = 500 highlight of two pixels there is left out too: e 464 +- 33 instead of
497 +- 7 (truth 500), the price of errors that hold whatever those pixels'
noise.
"""

from __future__ import annotations

import numpy as np

from . import _adequacy
from ._compile import jac_full, r_factor, remember_jacobian
from ._covariance import residual_variance
from ._identify import unidentifiable_at
from ._verdict import start_status


#: Pixels around each one a coordinate rests on that are left out with it (a glint
#: spills into its neighbours: the glass sphere's eta rested next on the pixel below
#: the glint's, 1.3 effective pixels).
REACH = 1
#: Rounds of leaving out and refitting.
ROUNDS = 2


def refit(problem, b, z, solve_starts, say):
    """(problem, z, code, cost, steps, (R, r), compile seconds) of the fit of target
    ``b`` solved again from ``z`` without the pixels a coordinate rests on and
    their neighbours (``REACH``), up to ``ROUNDS`` times, or None (no such
    coordinate, or no refit kept: one is kept if it converges and leaves every
    parameter constrained). ``solve_starts``: ``_drivers.solve_starts``."""
    if problem.noise_sigma is not None:  # (the pixels' noise is known: V_stat holds)
        return None
    spec = problem.spec
    index = np.asarray(problem.renderer.pixel_index)[problem.rows]
    width = problem.renderer.scene.width
    rows, cols = index // width, index % width
    kept, steps_all, t_all = None, 0, 0.0
    for _ in range(ROUNDS):
        data = problem.data(b)
        J, r, tc = jac_full(spec, z, data)
        remember_jacobian(spec, z, data, J, r)  # (the report's, if this fit stands)
        t_all += tc
        few = _adequacy.few_pixels(J, problem.weights.shape[1])
        if not few:
            break
        centres = sorted({p for _, ps in few.values() for p in ps})
        near = np.zeros(len(index), dtype=bool)
        for p in centres:
            near |= (np.abs(rows - rows[p]) <= REACH) & (np.abs(cols - cols[p]) <= REACH)
        where = "; ".join(f"row {rows[p]}, column {cols[p]}" for p in centres)
        rests = ", ".join(f"{spec.coordinates()[j]} ({n_eff:.2g} effective pixels)"
                          for j, (n_eff, _) in few.items())
        without = problem.without(b, np.nonzero(near)[0], [
            f"left out the pixel(s) at {where} and their neighbours: {rests} rested on "
            "them (a glint or a sub-pixel highlight), whose noise the image cannot "
            "measure; refit from the others"])
        data2 = without.data(b)
        zs, codes, steps, costs, best, (R2, r2), tc2 = solve_starts(
            without, np.asarray(z)[None], data2, say, "refit without the glint: ")
        z2, code, cost = zs[best], int(codes[best]), float(costs[best])
        R2, r2 = r_factor(R2), np.asarray(r2, dtype=np.float64)
        steps_all, t_all = steps_all + int(steps[best]), t_all + tc2
        if (start_status(code, z2, cost) != "converged"
                or unidentifiable_at(spec, z2, R2, residual_variance(None, data2, r2, spec))):
            remember_jacobian(spec, z, data, J, r)  # (solve_starts kept the refit's)
            break
        problem, z, kept = without, z2, (without, z2, code, cost, (R2, r2))
    return None if kept is None else (*kept[:4], steps_all, kept[4], t_all)

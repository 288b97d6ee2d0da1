"""Coarse-to-fine first solve of a large image: converge on the image averaged
2 x 2 with half the sub-pixel samples per axis (1/16 of the work per step),
then finish at full size with undamped Gauss-Newton steps.

The full-size finish is checked, not trusted: each step must lower the cost,
and the finish ends when the next Gauss-Newton step is within the solver's
tolerances (|dz| <= atol + rtol |z|, optimistix's own test). That next step
is the chord step (the last linearisation's J, the residuals after the step:
a forward render, a third of a linearisation's cost), taken with the residuals
linearised there; the stated errors come from that J, a step before the
optimum (they differ from the direct fit's by ~0.03 % at 256^2, a seventh of
their own statistical precision). Where the target's noise would not hide
that J's age (``chord_step``, ``CHORD_RTOL``: a noise-free target), the
finish linearises again instead.
If a step raises the cost or the steps do not settle in ``MAX_FINE_STEPS``,
the caller solves at full size from the original start as if this module did
not exist (measured on 256^2 plastic from the far start: 8 coarse steps and
1 full-size linearisation and 1 forward render against 12 full-size
linearisations).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ._compile import compile_ahead, compiled, remember_jacobian, residuals_at_points
from ._setup import Problem

#: Fits of at least this many pixels start coarse (smaller ones are cheap
#: already, and a coarse stage adds two executables to load).
MIN_PIXELS = 160 * 160
#: Full-size Gauss-Newton linearisations before giving up on the coarse start.
MAX_FINE_STEPS = 4
#: Off switch (benchmarks compare both ways).
ENABLED = True
#: A chord step settles the finish only where the residuals it linearises with
#: a J one step old are off by at most this fraction of their norm at the
#: optimum (``chord_step``): the noise then hides it. On a noise-free target
#: those residuals are rounding and the finish linearises again.
CHORD_RTOL = 1e-4


def settled(z, dz, rtol: float, atol: float) -> bool:
    """Whether the step ``dz`` from ``z`` is within the solver's tolerances
    (|dz| <= atol + rtol |z|, optimistix's own test)."""
    return bool(np.all(np.abs(dz) <= atol + rtol * np.abs(z)))


def chord_step(R, J, r0, r1, z1, dz, cost: float, rtol: float, atol: float):
    """The chord step dz1 (n,) from z1 = z0 + dz, the Gauss-Newton step ``dz``
    taken from z0 with J (N, n), its R factor and residuals ``r0``, cost
    ``cost``; ``r1`` the residuals at z1 (Kelley, *Solving Nonlinear Equations
    with Newton's Method*, SIAM 2003, sec. 2.3.3, the chord method). None
    unless it settles the finish: the cost fell, dz1 is within tolerance and
    the residuals linearised with this J at z1 + dz1 are off by at most
    ``CHORD_RTOL`` of their norm. That error is estimated from the step's
    second-order remainder a = r1 - r0 - J dz (= dz^T H dz / 2): J changes by
    ~2 |a| / |dz| per unit step, so r1 + J dz1 is off by ~2 |a| |dz1| / |dz|."""
    dz1 = -np.linalg.solve(R.T @ R, J.T @ r1)
    if not (0.5 * float(r1 @ r1) <= cost and settled(z1, dz1, rtol, atol)):
        return None
    Jd = J @ np.stack([dz, dz1], axis=1)  # one pass over J for both
    age = 2.0 * float(np.linalg.norm(r1 - r0 - Jd[:, 0])) * float(np.linalg.norm(dz1))
    age /= max(float(np.linalg.norm(dz)), 1e-300)
    return dz1 if age <= CHORD_RTOL * float(np.linalg.norm(r1 + Jd[:, 1])) else None


def eligible(scene, *, mask, exclude, weights, saturation, loss, dtype, n_starts) -> bool:
    """Whether a fit of ``scene`` with these options starts coarse.

    Only the plain case: default pixel selection, l2 loss, float64, one start,
    an image that halves exactly, at least 2 x 2 samples per pixel.
    """
    return (ENABLED and n_starts == 1 and isinstance(mask, str) and mask == "interior"
            and exclude is None and weights is None and saturation is None and loss == "l2"
            and jnp.dtype(dtype) == jnp.float64 and scene.supersampling >= 2
            and scene.width % 2 == 0 and scene.height % 2 == 0
            and scene.width * scene.height >= MIN_PIXELS)


def solve(problem: Problem, target, z0s, data, solve_starts, say):
    """The first solve of ``fitter.fit`` from one start, coarse to fine.

    ``target``: the (H, W, 3) image; ``solve_starts``: the drivers' solver,
    run on the coarse problem. Returns ``solve_starts``'s tuple at full
    size, or None when the full-size finish did not settle (the caller then
    solves at full size from ``z0s``).
    """
    from ._solvers import outcome_table

    scene = problem.renderer.scene
    h, w = scene.height // 2, scene.width // 2
    t = np.asarray(target, dtype=np.float64)
    # (a mean over the 2 x 2 axes of a reshape: 2.3 ms at 256^2, this 0.5 ms)
    small = 0.25 * ((t[0::2, 0::2] + t[1::2, 0::2]) + (t[0::2, 1::2] + t[1::2, 1::2]))
    coarse_scene = scene.replace(width=w, height=h, supersampling=scene.supersampling // 2)
    try:
        coarse = Problem.make(small[None], coarse_scene, problem.material,
                              dtype=problem.dtype, base_dir=problem.base_dir, estimate=False)
    except Exception:  # noqa: BLE001 (e.g. no interior pixel at half size: solve directly)
        return None
    coarse = dataclasses.replace(coarse, init_full=problem.init_full, blocks=problem.blocks,
                                 loss=problem.loss, loss_scale=problem.loss_scale,
                                 static=problem.static)
    # The full-size finish's executables compiled on threads beside the coarse
    # solve's compile (a first run: each 0.1-0.5 s).
    compile_ahead("gauss_newton", problem.spec, (problem.cast(np.asarray(z0s[0])), data))
    compile_ahead("residuals", problem.spec, (problem.cast(np.asarray(z0s[:1])), data))
    zs, codes, steps, _, best, _, t_compile = solve_starts(
        coarse, z0s, coarse.data(0), say, f"coarse {w}x{h}: ")
    if outcome_table().get(int(codes[best]), ("",))[0] != "converged":
        return None
    z = np.asarray(zs[best], dtype=np.float64)
    step, tc = compiled("gauss_newton", problem.spec, (problem.cast(z), data))
    t_compile += tc
    rtol, atol = problem.static["rtol"], problem.static["atol"]
    prev = np.inf
    for k in range(1, MAX_FINE_STEPS + 1):
        R, r, J, dz, cost = jax.tree_util.tree_map(np.asarray, step(problem.cast(z), data))
        cost = float(cost)
        say(f"full size: Gauss-Newton step {k}, cost {cost:.4g}")
        if not (np.isfinite(cost) and np.all(np.isfinite(dz))) or cost > prev:
            return None
        if settled(z, dz, rtol, atol):
            break
        # Settled by the chord step after this one (one forward render), or
        # linearised again there.
        r1 = residuals_at_points(problem.spec, (z + dz)[None], data)[0]
        dz1 = chord_step(R, J, r, r1, z + dz, dz, cost, rtol, atol)
        if dz1 is not None:
            z, r, dz = z + dz, r1, dz1
            break
        prev, z = cost, z + dz
    else:
        return None
    # The last step is within tolerance: take it (Gauss-Newton converges
    # quadratically, so z + dz is the optimum to ~|dz|^2; a chord step's error
    # is ~|dz| times the step before it's) with the residuals linearised there
    # (r + J dz) and R from the last linearisation (J changes by ~|z - z_J|
    # relative, below any stated error's precision).
    z, r = z + dz, r + J @ dz
    cost = 0.5 * float(r @ r)
    remember_jacobian(problem.spec, z, data, J, r)
    return (z[None], np.asarray(codes[best:best + 1]), np.asarray([int(steps[best]) + k]),
            np.asarray([cost]), 0, (R, r), t_compile)


"""Solver choice: one name -> one optimistix solver, its step budget, and
what its result codes mean."""

from __future__ import annotations

import jax
import lineax as lx
import numpy as np
import optax
import optimistix as optx

from ._names import SOLVERS

#: Adam's learning rate in the unconstrained coordinates (all O(1)).
ADAM_LEARNING_RATE = 0.05
#: Step budget of a solver without its own entry in ``MAX_STEPS``.
DEFAULT_MAX_STEPS = 200


def _normal():
    """Normal equations (J^T J, p x p) by Cholesky.

    With N ~ 1e5 residuals and p <= 10 well-scaled coordinates, forming the
    p x p normal matrix is far cheaper than the default QR of the tall N x p
    Jacobian (measured 3.5x faster per LM fit at 256^2); the squared
    condition number is harmless in float64 for O(1) coordinates.
    """
    return lx.Normal(lx.Cholesky())


#: name -> (rtol, atol) -> solver. ``gauss_newton`` is undamped and can diverge
#: from far starts (measured: NaN within 3 steps on a sphere problem);
#: divergence is reported as a failed fit, never returned as a result.
#: ``bfgs`` and ``adam`` minimise 0.5 * sum(r^2) as a scalar; ``adam`` is a
#: first-order baseline for the benchmarks and needs many more steps.
_MAKERS = {
    "levenberg_marquardt": lambda rtol, atol: optx.LevenbergMarquardt(
        rtol=rtol, atol=atol, linear_solver=_normal()),
    "dogleg": lambda rtol, atol: optx.Dogleg(rtol=rtol, atol=atol, linear_solver=_normal()),
    "gauss_newton": lambda rtol, atol: optx.GaussNewton(
        rtol=rtol, atol=atol, linear_solver=_normal()),
    "bfgs": lambda rtol, atol: optx.BFGS(rtol=rtol, atol=atol),
    "adam": lambda rtol, atol: optx.OptaxMinimiser(optax.adam(ADAM_LEARNING_RATE),
                                                   rtol=rtol, atol=atol),
}

# The registry implements exactly the names the config reader accepts.
assert tuple(_MAKERS) == SOLVERS, "fitter.fit._names.SOLVERS lists the solvers"

#: Default step budgets of the solvers that need more than ``DEFAULT_MAX_STEPS``.
MAX_STEPS = {"adam": 5000, "bfgs": 1000}


def make_solver(name: str, rtol: float, atol: float):
    """The optimistix solver for ``name`` (one of ``SOLVERS``)."""
    if name not in _MAKERS:
        raise ValueError(f"unknown solver {name!r}; known: {', '.join(SOLVERS)}")
    return _MAKERS[name](rtol, atol)


def default_max_steps(name: str) -> int:
    """The step budget of solver ``name`` when the caller gives none."""
    return MAX_STEPS.get(name, DEFAULT_MAX_STEPS)


def result_code(result):
    """An ``optx.RESULTS`` item as its int32 code (traceable).

    A compiled solve returns the code, not the item: the item's pytree class
    has no ``jax.export`` serialisation, so the on-disk trace cache
    (``_cache``) could not store it. ``result_item`` maps the code back.
    """
    (code,) = jax.tree_util.tree_leaves(result)
    return code


def result_item(code: int):
    """The ``optx.RESULTS`` item of a code from ``result_code``, or None.

    optimistix has no public constructor from a code; an item is a pytree
    whose one leaf is its code, so it is rebuilt from that structure. None if
    a later optimistix changes it (callers then say only "failed").
    """
    try:
        tree = jax.tree_util.tree_structure(optx.RESULTS.successful)
        item = jax.tree_util.tree_unflatten(tree, [np.asarray(code, dtype=np.int32)])
        optx.RESULTS[item]  # a code out of range raises here
        return item
    except Exception:  # noqa: BLE001 (any change of that structure)
        return None


def solver_outcome(code: int) -> tuple[str, str]:
    """(status, message) of a solver code: status ``"converged"``,
    ``"max_steps"`` or ``"failed"``; the message is optimistix's."""
    item = result_item(code)
    if item is None:
        return "failed", f"optimistix result code {code}"
    if bool(item == optx.RESULTS.successful):
        return "converged", optx.RESULTS[item]
    if bool(item == optx.RESULTS.nonlinear_max_steps_reached):
        return "max_steps", optx.RESULTS[item]
    return "failed", optx.RESULTS[item]

"""Solver choice: one name -> one optimistix solver, its step budget, and
what its result codes mean."""

from __future__ import annotations

import json
import os

import jax
import numpy as np

from ..compilation_cache import active_dir, store_atomically
from ._names import SOLVERS

# optimistix, lineax and optax (0.5 s to import with equinox and jaxtyping) are
# imported only to trace a solve: a fit whose trace is on disk (``_cache``) and
# whose outcome table is stored (``outcome_table``) never loads them.

#: Adam's learning rate in the unconstrained coordinates (all O(1)).
ADAM_LEARNING_RATE = 0.05
#: Default tolerances (optimistix's Cauchy test: a step stops the solve when
#: every coordinate moved by less than ATOL + RTOL |z| and every residual
#: changed by less than ATOL + RTOL |r|). Residuals are in image units (or
#: noise units with ``noise_sigma``), so ATOL = 1e-7 is 1/5000 of a half-float
#: EXR's step at 1 and far below any noise; with 1e-8 the residual test alone
#: asked one more step of env_plastic (7 -> 6) and two of env_phong (9 -> 7),
#: which moved no parameter by more than 3.4e-6 of its statistical error.
RTOL, ATOL = 1e-6, 1e-7
#: Step budget of a solver without its own entry in ``MAX_STEPS``.
DEFAULT_MAX_STEPS = 200


def _normal():
    """Normal equations (J^T J, p x p) by Cholesky.

    With N ~ 1e5 residuals and p <= 10 well-scaled coordinates, forming the
    p x p normal matrix is far cheaper than the default QR of the tall N x p
    Jacobian (measured 3.5x faster per LM fit at 256^2); the squared
    condition number is harmless in float64 for O(1) coordinates.
    """
    import lineax as lx

    return lx.Normal(lx.Cholesky())


#: name -> (rtol, atol) -> solver. ``gauss_newton`` is undamped and can diverge
#: from far starts (measured: NaN within 3 steps on a sphere problem);
#: divergence is reported as a failed fit, never returned as a result.
#: ``bfgs`` and ``adam`` minimise 0.5 * sum(r^2) as a scalar; ``adam`` is a
#: first-order baseline for the benchmarks and needs many more steps.
def _optx():
    import optimistix

    return optimistix


def _adam(rtol, atol):
    import optax

    return _optx().OptaxMinimiser(optax.adam(ADAM_LEARNING_RATE), rtol=rtol, atol=atol)


_MAKERS = {
    "levenberg_marquardt": lambda rtol, atol: _optx().LevenbergMarquardt(
        rtol=rtol, atol=atol, linear_solver=_normal()),
    "dogleg": lambda rtol, atol: _optx().Dogleg(rtol=rtol, atol=atol, linear_solver=_normal()),
    "gauss_newton": lambda rtol, atol: _optx().GaussNewton(
        rtol=rtol, atol=atol, linear_solver=_normal()),
    "bfgs": lambda rtol, atol: _optx().BFGS(rtol=rtol, atol=atol),
    "adam": _adam,
}

# The registry implements exactly the names the config reader accepts.
assert tuple(_MAKERS) == SOLVERS, "fitter.fit._names.SOLVERS lists the solvers"

#: Default step budgets of the solvers that need more than ``DEFAULT_MAX_STEPS``.
MAX_STEPS = {"adam": 5000, "bfgs": 1000}


#: The message of a fit that ran out of steps (optimistix's names a root-find).
MAX_STEPS_MESSAGE = ("the solver used its whole step budget (max_steps) without meeting its "
                     "tolerances; raise fit.max_steps, or start closer to the answer")


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


def library_versions() -> str:
    """Versions of the solver libraries, which fix what a result code means."""
    from importlib import metadata

    out = []
    for name in ("optimistix", "lineax", "equinox", "optax"):
        try:
            out.append(f"{name}={metadata.version(name)}")
        except metadata.PackageNotFoundError:
            out.append(f"{name}=?")
    return ",".join(out)


_TABLE: dict = {}


def outcome_table() -> dict[int, tuple[str, str]]:
    """code -> (status, optimistix's message) of this optimistix, read from a small
    JSON file next to the trace cache when there is one (importing optimistix
    only to name a code costs 0.5 s); written on the first use."""
    if _TABLE:
        return _TABLE
    folder = active_dir()
    path = None
    if folder:
        import hashlib

        tag = hashlib.sha256(library_versions().encode()).hexdigest()[:16]
        path = os.path.join(folder, f"fitter-outcomes-{tag}.json")
        try:
            with open(path, encoding="utf-8") as fh:
                _TABLE.update({int(k): tuple(v) for k, v in json.load(fh).items()})
            return _TABLE
        except (OSError, ValueError, TypeError):
            pass
    optx = _optx()
    code = 0
    while (item := result_item(code)) is not None:
        if bool(item == optx.RESULTS.successful):
            status = "converged"
        elif bool(item == optx.RESULTS.nonlinear_max_steps_reached):
            status = "max_steps"
        else:
            status = "failed"
        _TABLE[code] = (status, optx.RESULTS[item])
        code += 1
    if path:
        try:
            table = json.dumps({str(k): v for k, v in _TABLE.items()})
            store_atomically(folder, path, table.encode())
        except OSError:
            pass
    return _TABLE


def result_item(code: int):
    """The ``optx.RESULTS`` item of a code from ``result_code``, or None.

    optimistix has no public constructor from a code; an item is a pytree
    whose one leaf is its code, so it is rebuilt from that structure. None if
    a later optimistix changes it (callers then say only "failed").
    """
    optx = _optx()
    try:
        tree = jax.tree_util.tree_structure(optx.RESULTS.successful)
        item = jax.tree_util.tree_unflatten(tree, [np.asarray(code, dtype=np.int32)])
        optx.RESULTS[item]  # a code out of range raises here
        return item
    except Exception:  # noqa: BLE001 (any change of that structure)
        return None


def solver_outcome(code: int) -> tuple[str, str]:
    """(status, message) of a solver code: status ``"converged"``,
    ``"max_steps"`` or ``"failed"``; the message is optimistix's, except the
    product's own ``MAX_STEPS_MESSAGE``."""
    found = outcome_table().get(int(code))
    if found is None:
        return "failed", f"optimistix result code {code}"
    if found[0] == "max_steps":  # optimistix's text speaks of root-finds
        return "max_steps", MAX_STEPS_MESSAGE
    return found

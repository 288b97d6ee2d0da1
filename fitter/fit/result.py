"""What a fit returns: values, uncertainties, diagnostics, all as plain data."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .._math import floats


@dataclasses.dataclass
class FitResult:
    """Outcome of ``fitter.fit``.

    Attributes:
        params: every parameter of the material in user units,
            ``{"lobe.param": float or (3,) array}`` (fixed ones included).
        stderr: one-sigma stated errors of the free, identifiable
            parameters, same shapes: half the width of the +-1 sigma interval
            of the total covariance (statistical + systematic, below), mapped
            through the parameter transform and clipped to the box (the delta
            method when small; see ``fitter.fit._covariance.covariance``).
        stderr_stat: the statistical part alone: the Gauss-Newton covariance
            s^2 (J^T J)^-1 (the Cramer-Rao bound for white pixel noise of one
            level), or, where the residual's scatter differs from pixel to
            pixel beyond chance (shot noise at a bright highlight), the pixel
            sandwich (``fitter.fit._adequacy.heteroscedastic``).
        stderr_sys: the systematic part, sqrt(stderr^2 - stderr_stat^2): what
            spatially structured residuals (a model that cannot follow the
            image, its discretisation) add, from a spatial-block sandwich
            covariance; 0 where the residuals look white
            (``fitter.fit._adequacy``); it includes ``stderr_disc``.
        stderr_disc: the part of ``stderr_sys`` from the forward model's own
            discretisation: the shift of the parameters that rendering the
            fit with 2k x 2k sub-pixel samples (and, under an environment,
            finer sun cells) instead of k x k implies through the fit's
            linearisation (``fitter.fit._discretisation``).
        adequacy: what the residual says about the model: ``noise_ratio``
            (residual RMSE / noise level), ``regions`` (per region of the
            sphere -- body, highlight, rim --: pixels, RMSE / noise, share of
            the residual energy), ``neighbour_correlation`` (lag-1, ~0 for
            white residuals) and ``blocks`` (the sandwich's block count and
            largest sqrt(V_hac / V_stat)).
        free: names of the parameters that were fitted.
        unidentifiable: parameters the data cannot constrain; they have no
            stderr. Held at their initial value, except those only found
            ambiguous by the multi-start check (another start as good,
            elsewhere), which keep the best start's value.
        correlation: (n, n) correlation matrix of the free scalar
            coordinates named in ``coordinates`` (``"lambert.rho_d[0]"``, ...);
            a value refit on the edge of its box (``fitter.fit._edge``) has
            none: it is free, but held on the edge in the final solve.
        coordinates: names of the rows of ``correlation``.
        status: ``"converged"``, ``"max_steps"`` or ``"failed"``; only
            ``"converged"`` means the solver met its tolerances *and* the fit
            passed the goodness-of-fit check.
        message: the solver's or the checker's reason, human readable.
        iterations: solver steps of the kept start.
        cost: 0.5 * sum of squared (weighted) residuals at the solution.
        image_rmse: (3,) per-channel RMSE over the fitted pixels.
        n_pixels: pixels used; n_excluded: pixels dropped (NaN/Inf, saturated,
            outside the mask).
        time_compile, time_run: seconds spent compiling and running.
        warnings: human-readable warnings (unidentifiable parameters, bounds).
        starts: one dict per start: ``{"params": ..., "cost": c, "status": s}``.
        derived: quantities the image determines better than the
            parameters they combine, ``{"lobe.name": {"value", "stderr"}}``
            (a conductor's F0; ``fitter.bsdf.derived``); in ``to_dict``
            under ``"derived"`` when there are any.
        fitted: (H, W) bool, the pixels of this target the fit used (selected
            and with a weight > 0); not part of ``to_dict``.
    """

    params: dict[str, Any]
    stderr: dict[str, Any]
    free: list[str]
    unidentifiable: list[str]
    correlation: np.ndarray
    coordinates: list[str]
    status: str
    message: str
    iterations: int
    cost: float
    image_rmse: np.ndarray
    n_pixels: int
    n_excluded: int
    time_compile: float
    time_run: float
    warnings: list[str] = dataclasses.field(default_factory=list)
    starts: list[dict] = dataclasses.field(default_factory=list)
    fitted: np.ndarray | None = dataclasses.field(default=None, repr=False)
    stderr_stat: dict[str, Any] = dataclasses.field(default_factory=dict)
    stderr_sys: dict[str, Any] = dataclasses.field(default_factory=dict)
    adequacy: dict = dataclasses.field(default_factory=dict)
    stderr_disc: dict[str, Any] = dataclasses.field(default_factory=dict)
    derived: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    @property
    def rmse(self) -> float:
        """RMSE over the fitted pixels and the three channels."""
        return float(np.sqrt(np.mean(np.square(self.image_rmse))))

    def to_dict(self) -> dict:
        """JSON-ready dict in the result contract of the CLI (README, configs/README.md)."""
        return {
            "params": {k: floats(v) for k, v in self.params.items()},
            "stderr": {k: floats(v) for k, v in self.stderr.items()},
            "stderr_stat": {k: floats(v) for k, v in self.stderr_stat.items()},
            "stderr_sys": {k: floats(v) for k, v in self.stderr_sys.items()},
            "stderr_disc": {k: floats(v) for k, v in self.stderr_disc.items()},
            "adequacy": self.adequacy,
            "unidentifiable": list(self.unidentifiable),
            "status": self.status,
            "message": self.message,
            "iterations": int(self.iterations),
            "cost": float(self.cost),
            "time_s": {"compile": float(self.time_compile), "run": float(self.time_run),
                       "total": float(self.time_compile + self.time_run)},
            "image_rmse": self.rmse,
            "image_rmse_rgb": floats(self.image_rmse),
            "n_pixels": int(self.n_pixels),
            "n_excluded": int(self.n_excluded),
            "warnings": list(self.warnings),
            **({"derived": self.derived} if self.derived else {}),
        }


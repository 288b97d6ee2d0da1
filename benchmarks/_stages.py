"""Where the time of a ``fitter.fit`` call goes: the functions that make each
stage are wrapped (the product untouched) and each stage gets its own wall
time (nested stages are subtracted from their parent) and the XLA work done
inside it (tracing, lowering and compiling, from ``jax.monitoring``).

Used by ``coarse_to_fine.py`` and ``dielectric.py``.
"""

from __future__ import annotations

import collections
import functools
import time

#: (module, function, stage). A call nested in a "solve" stage counts to it,
#: except the coarse solve's own Levenberg-Marquardt run.
WRAPPED = (
    ("_setup", "Problem.make", "set-up (pixels, geometry, noise)"),
    ("_drivers", "searched", "start search and lobe options"),
    ("_drivers", "cheapened", "start search and lobe options"),
    ("_drivers", "compile_ahead", "solve: traced ahead (compiled on a thread)"),
    ("_drivers", "_hold_dead_columns", "start check (dead columns)"),
    ("_coarse", "solve", "solve: coarse set-up and full-size Gauss-Newton steps"),
    ("_drivers", "solve_starts", "solve: Levenberg-Marquardt"),
    ("_drivers", "weak_direction", "cost profile (_identify)"),
    ("_drivers", "weak_profile", "cost profile (_identify)"),
    ("_drivers", "_finish", "other checks after the fit (covariance, sandwich, adequacy)"),
    ("_discretisation", "sample_rows", "discretisation term (_discretisation)"),
    ("_discretisation", "sky_terms", "discretisation term (_discretisation)"),
    ("_discretisation", "finer_values", "discretisation term (_discretisation)"),
    ("_discretisation", "ring_error", "discretisation term (_discretisation)"),
    ("_discretisation", "shift", "discretisation term (_discretisation)"),
)
COARSE = "solve: coarse set-up and full-size Gauss-Newton steps"
COARSE_LM = "solve: coarse Levenberg-Marquardt"
XLA_EVENTS = ("backend_compile_duration", "jaxpr_trace_duration",
              "jaxpr_to_mlir_module_duration")


class Stages:
    """``with stages.call() as out:`` fills ``out`` with {stage: (seconds, XLA seconds)},
    the rest of the call under "rest"."""

    def __init__(self):
        import importlib

        import jax.monitoring

        mods = {}
        for name in ("_setup", "_drivers", "_coarse", "_discretisation"):
            try:  # an older tree may lack one
                mods[name] = importlib.import_module(f"fitter.fit.{name}")
            except ImportError:
                pass
        self.stack: list = []
        self.wall = collections.defaultdict(float)
        self.xla = collections.defaultdict(float)
        for mod, name, stage in WRAPPED:
            if mod not in mods:
                continue
            if name == "Problem.make":
                self._wrap_make(mods[mod].Problem, stage)
            elif hasattr(mods[mod], name):  # an older tree may lack one
                setattr(mods[mod], name, self._timed(getattr(mods[mod], name), stage))
        jax.monitoring.register_event_duration_secs_listener(self._event)

    def _event(self, name, seconds, **_):
        if name.rsplit("/", 1)[-1] in XLA_EVENTS:
            self.xla[self.stack[-1][0] if self.stack else "rest"] += seconds

    def _stage_of(self, stage):
        parent = self.stack[-1][0] if self.stack else None
        if parent == COARSE and stage == "solve: Levenberg-Marquardt":
            return COARSE_LM
        if parent and parent.startswith("solve"):
            return None  # counted in the solve
        return stage

    def _timed(self, f, stage):
        @functools.wraps(f)
        def g(*a, **k):
            label = self._stage_of(stage)
            if label is None:
                return f(*a, **k)
            self.stack.append([label, 0.0])
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                dt = time.perf_counter() - t0
                _, nested = self.stack.pop()
                self.wall[label] += dt - nested
                if self.stack:
                    self.stack[-1][1] += dt
        return g

    def _wrap_make(self, cls, stage):
        make = cls.make.__func__
        timed = self._timed(lambda *a, **k: make(cls, *a, **k), stage)
        cls.make = classmethod(lambda _cls, *a, **k: timed(*a, **k))

    def run(self, fn):
        """(result of ``fn()``, wall seconds, {stage: (seconds, XLA seconds)})."""
        self.wall.clear()
        self.xla.clear()
        t0 = time.perf_counter()
        out = fn()
        total = time.perf_counter() - t0
        stages = {k: (v, self.xla.get(k, 0.0)) for k, v in self.wall.items()}
        stages["rest"] = (total - sum(self.wall.values()), self.xla.get("rest", 0.0))
        return out, total, stages


def solver_alone(stages: dict) -> float:
    """Seconds of the solve stages (the first solve and any re-solve)."""
    return sum(v[0] for k, v in stages.items() if k.startswith("solve"))

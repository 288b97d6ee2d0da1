"""Typed checks of user-given values, with one wording for every message.

Each check returns the value in canonical form (``float``, ``int``, a tuple
of 3 floats) or raises ``Problem`` saying what is wrong with it; the caller
names the key (``fitter.scene.check_scene``) and the file
(``fitter.serialize.Reader``).
"""

from __future__ import annotations

import math
import numbers

import numpy as np


class Problem(ValueError):
    """What is wrong with one value; a caller turns it into a user error naming the key."""


def show(value) -> str:
    """``repr(value)`` on one line, cut to 60 characters (an array: its shape and dtype)."""
    if isinstance(value, np.ndarray) and value.size > 3:
        return f"an array of shape {value.shape} and dtype {value.dtype}"
    text = " ".join(repr(value).split())
    return text if len(text) <= 60 else text[:57] + "..."


def number(value, lo=None, hi=None, lo_open=False) -> float:
    """A finite real in [lo, hi] (``lo_open``: lo excluded)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise Problem(f"expected a number, got {show(value)}")
    x = float(value)
    if not math.isfinite(x):
        raise Problem(f"expected a finite number, got {show(value)}")
    below = lo is not None and (x <= lo if lo_open else x < lo)
    if below or (hi is not None and x > hi):
        left = "(" if lo_open else "["
        raise Problem(f"{show(value)} is outside the allowed range {left}"
                      f"{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]")
    return x


def integer(value, lo=None) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise Problem(f"expected an integer, got {show(value)}")
    if lo is not None and value < lo:
        raise Problem(f"expected an integer >= {lo}, got {value}")
    return int(value)


def vec3(value, nonneg=False, nonzero=False) -> tuple[float, float, float]:
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != 3:
        raise Problem(f"expected a list of 3 numbers, got {show(value)}")
    out = tuple(number(v, lo=0.0 if nonneg else None) for v in value)
    if nonzero and not any(out):
        raise Problem("must not be the zero vector")
    return out


def choice(value, choices) -> str:
    if not isinstance(value, str) or value not in choices:
        raise Problem(f"{show(value)} is not allowed; allowed values: "
                      + ", ".join(repr(c) for c in choices))
    return value


def boolean(value) -> bool:
    if not isinstance(value, bool):
        raise Problem(f"expected true or false, got {show(value)}")
    return value


def string(value) -> str:
    if not isinstance(value, str) or not value:
        raise Problem(f"expected a non-empty string, got {show(value)}")
    return value


#: Floating-point types of the forward model and the fit (``fit.dtype``).
FIT_DTYPES = ("float64", "float32")

#: The rules of the fit engine's scalar options, shared by a config's ``[fit]``
#: table and the keywords of ``fitter.fit`` / ``fitter.fit_batch``:
#: name -> (check, its keyword arguments). ``fit_option`` applies one.
FIT_RULES = {
    "n_starts": (integer, {"lo": 1}),
    "max_steps": (integer, {"lo": 1}),
    "rtol": (number, {"lo": 0.0, "lo_open": True}),
    "atol": (number, {"lo": 0.0, "lo_open": True}),
    "noise_sigma": (number, {"lo": 0.0, "lo_open": True}),
    "saturation": (number, {"lo": 0.0, "lo_open": True}),
    "loss_scale": (number, {"lo": 0.0, "lo_open": True}),
    "validate_spp": (integer, {"lo": 1}),
    "validate": (boolean, {}),
    "identifiability": (boolean, {}),
    "dtype": (choice, {"choices": FIT_DTYPES}),
}


def fit_option(name: str, value):
    """``value`` checked by the rule of fit option ``name`` (``FIT_RULES``)."""
    check, kwargs = FIT_RULES[name]
    return check(value, **kwargs)

"""Quantities an image determines better than the parameters they combine.

A lobe may name such quantities (``Lobe.derived``): ``derived(p, opts) ->
{name: value}`` from its own parameters, e.g. a conductor's normal-incidence
reflectance F0 = ((eta - 1)^2 + k^2) / ((eta + 1)^2 + k^2) per channel, which
one image pins while eta and k trade along a curve of equal F0.
``derive(material, result, variance)`` evaluates them at a fit, takes their
standard errors from the fit's ``variance`` (the delta method, var(Q) =
g^T C g with g = dQ/dz, by the stated errors' rules along g:
``fitter.fit._covariance.along``) or, without it, from the parameters'
standard errors and the fit's correlation matrix, and writes a warning
where the parameters themselves are far less certain than the quantity.

Reference: the delta method, e.g. Casella, Berger, *Statistical Inference*
(2nd ed.), sec. 5.5.4.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._math import floats
from ..material import Material, lobe_params

#: A fitted input whose relative standard error exceeds this (and is this many
#: times the derived quantity's) is reported as not determined on its own.
LOOSE_REL = 0.02
LOOSE_RATIO = 5.0
#: Smallest eigenvalue of the correlation matrix of a derived quantity's
#: inputs below which they trade along its curve (the fit's
#: ``_identify.WEAK_EIG``; a conductor's eta/k on the shipped gold: 1.3e-5).
WEAK_EIG = 1e-3
#: Relative step of the central differences of dQ/dx.
STEP = 1e-6


def _cov(result, keys: list[str]):
    """Covariance of the scalar coordinates of ``keys`` (user units), and their names;
    None where a key has no standard error (fixed or unidentifiable)."""
    coords = list(getattr(result, "coordinates", []) or [])
    corr = np.asarray(getattr(result, "correlation", np.zeros((0, 0))), dtype=float)
    names, sd = [], []
    for key in keys:
        s = result.stderr.get(key)
        if s is None:
            return None
        s = np.atleast_1d(np.asarray(s, dtype=float))
        sub = [key] if s.size == 1 else [f"{key}[{i}]" for i in range(s.size)]
        names += sub
        sd += list(s)
    idx = [coords.index(n) if n in coords else -1 for n in names]
    sd = np.asarray(sd)
    c = np.diag(sd * sd)
    for a, ia in enumerate(idx):
        for b, ib in enumerate(idx):
            if a != b and ia >= 0 and ib >= 0:
                c[a, b] = corr[ia, ib] * sd[a] * sd[b]
    return c, names


def derive(material: Material, result, variance=None) -> tuple[dict[str, Any], list[str]]:
    """``({"lobe.name": {"value": v, "stderr": s}}, warnings)`` at a fit's parameters.

    ``stderr`` is None where an input is fixed or unidentifiable (then the
    quantity is as certain as the others make it, which the fit cannot say).
    ``variance``: the fit's own ``variance(fun) -> stderr`` of a function of
    its ``{"lobe.param": value}`` (``fitter.fit._covariance.propagator``: the
    stated errors' rules along the quantity's gradient); without it, the
    delta method on ``result.stderr`` and ``result.correlation``.
    """
    out: dict[str, Any] = {}
    warnings: list[str] = []
    for lobe in material.lobe_objects:
        if lobe.derived is None:
            continue
        opts = material.options_of(lobe.name)
        p = {k: np.asarray(v, dtype=float) for k, v in lobe_params(result.params, lobe.name).items()
             if k not in opts}
        values = lobe.derived(p, opts)
        free = [k for k in p if f"{lobe.name}.{k}" in result.free
                and f"{lobe.name}.{k}" not in result.unidentifiable]
        # (an input without a standard error leaves the quantity without one)
        stated = bool(free) and all(result.stderr.get(f"{lobe.name}.{k}") is not None
                                    for k in free)
        cov = (_cov(result, [f"{lobe.name}.{k}" for k in free])
               if stated and variance is None else None)
        for name, value in values.items():
            value = np.asarray(value, dtype=float)
            stderr = None
            if stated and variance is not None:
                def q(full, name=name):
                    return lobe.derived({k: full.get(f"{lobe.name}.{k}", v)
                                         for k, v in p.items()}, opts)[name]

                stderr = np.asarray(variance(q), dtype=float).reshape(value.shape)
            elif cov is not None:
                grads = []
                for k in free:
                    x = np.atleast_1d(p[k])
                    for i in range(x.size):
                        h = STEP * max(abs(x[i]), 1e-3)
                        up, dn = dict(p), dict(p)
                        up[k] = (x + h * np.eye(x.size)[i]).reshape(np.shape(p[k]))
                        dn[k] = (x - h * np.eye(x.size)[i]).reshape(np.shape(p[k]))
                        grads.append((np.asarray(lobe.derived(up, opts)[name])
                                      - np.asarray(lobe.derived(dn, opts)[name])) / (2 * h))
                g = np.stack([np.atleast_1d(gr) for gr in grads])  # (n_coords, size)
                stderr = np.sqrt(np.maximum(np.einsum("ia,ij,ja->a", g, cov[0], g), 0.0))
                stderr = stderr.reshape(value.shape)
            key = f"{lobe.name}.{name}"
            out[key] = {"value": floats(value), "stderr": None if stderr is None
                        else floats(stderr)}
            warnings += _loose(lobe.name, key, value, stderr, free, result)
    return out, warnings


def settle(material: Material, result, variance=None) -> None:
    """Evaluate the derived quantities at a fit and mark inputs it determines
    only through them: ``result.derived`` is set (``derive``), and an input
    whose own error is far wider than the quantity's (``LOOSE_REL``,
    ``LOOSE_RATIO``) or that lies along a valley of the inputs' correlation
    (smallest eigenvalue below ``WEAK_EIG``) is moved to
    ``result.unidentifiable`` without a standard error. The quantity keeps its
    error, propagated from the whole covariance before the marking.
    """
    values, notes = derive(material, result, variance)
    result.derived = values
    for lobe in material.lobe_objects:
        keys = [k for k in values if k.startswith(lobe.name + ".")]
        if not keys:
            continue
        free = [k for k in result.free if k.startswith(lobe.name + ".")
                and k not in result.unidentifiable and k in result.stderr
                and k.split(".", 1)[1] in _inputs(lobe, material, result)]
        loose = set()
        for key in keys:
            se = values[key]["stderr"]
            if se is None:
                continue
            rel_q = np.max(np.abs(np.asarray(se)) / np.maximum(np.abs(
                np.asarray(values[key]["value"])), 1e-12))
            for k in free:
                x, s = (np.asarray(result.params[k], float), np.asarray(result.stderr[k], float))
                rel = float(np.max(s / np.maximum(np.abs(x), 1e-12)))
                if rel > LOOSE_REL and rel > LOOSE_RATIO * rel_q:
                    loose.add(k)
        cov = _cov(result, free) if len(free) > 1 else None
        if cov is not None:
            d = np.sqrt(np.maximum(np.diag(cov[0]), 1e-300))
            w, v = np.linalg.eigh(cov[0] / np.outer(d, d))
            if w[0] < WEAK_EIG:
                heavy = np.abs(v[:, 0]) >= 0.3 * np.abs(v[:, 0]).max()
                loose |= {n.split("[")[0] for n, h in zip(cov[1], heavy) if h}
        for k in free:
            if k in loose:
                for part in ("stderr", "stderr_stat", "stderr_sys", "stderr_disc"):
                    getattr(result, part, {}).pop(k, None)
                result.unidentifiable.append(k)
        if loose:
            q = ", ".join(f"{k} = {_fmt(values[k]['value'])} ± {_fmt(values[k]['stderr'])}"
                          for k in keys if values[k]["stderr"] is not None)
            names = ", ".join(k for k in free if k in loose)
            short = ", ".join(k.split(".", 1)[1] for k in keys)
            notes = [n for n in notes if "curve of equal" not in n]
            notes.append(f"{names} are not identifiable on their own: they trade along the "
                         f"curve of equal {short}, which is what this image determines ({q}); "
                         "their values are one point of that curve")
    result.warnings.extend(notes)


def _inputs(lobe, material, result) -> set[str]:
    """Names of the lobe's parameters its derived quantities depend on."""
    opts = material.options_of(lobe.name)
    return inputs(lobe, opts, lobe_params(result.params, lobe.name))


def inputs(lobe, opts, params) -> set[str]:
    """Names of ``lobe``'s parameters (options ``opts``) that its derived
    quantities depend on at ``params`` ({name: value}, the lobe's own); empty
    for a lobe without ``derived``."""
    if lobe.derived is None:
        return set()
    p = {k: np.asarray(v, dtype=float) for k, v in params.items() if k not in opts}
    base = lobe.derived(p, opts)
    out = set()
    for k, v in p.items():
        bumped = dict(p)
        bumped[k] = v * (1 + 1e-3) + 1e-3
        after = lobe.derived(bumped, opts)
        if any(not np.array_equal(after[n], base[n]) for n in base):
            out.add(k)
    return out


def _loose(lobe: str, key: str, value, stderr, free, result) -> list[str]:
    """The warning for inputs determined far worse than the quantity ``key``."""
    if stderr is None:
        held = [f"{lobe}.{k}" for k in free] + [k for k in result.unidentifiable
                                                if k.startswith(lobe + ".")]
        return [f"{key} = {_fmt(value)} (the quantity this image determines); "
                f"{', '.join(held) or 'its inputs'} are not all identifiable"] if held else []
    rel_q = np.max(np.abs(np.asarray(stderr)) / np.maximum(np.abs(value), 1e-12))
    loose = []
    for k in free:
        full = f"{lobe}.{k}"
        x, s = np.asarray(result.params[full], float), np.asarray(result.stderr[full], float)
        rel = float(np.max(s / np.maximum(np.abs(x), 1e-12)))
        if rel > LOOSE_REL and rel > LOOSE_RATIO * rel_q:
            loose.append(f"{full} (relative standard error up to {rel:.2g})")
    if not loose:
        return []
    return [f"{key} = {_fmt(value)} ± {_fmt(stderr)} is what this image determines; "
            f"{', '.join(loose)} only along the curve of equal {key.split('.')[-1]}, "
            "so read them as one point of that curve"]


def _fmt(v) -> str:
    a = np.atleast_1d(np.asarray(v, dtype=float))
    text = ", ".join(f"{x:.4g}" for x in a)
    return text if a.size == 1 else f"({text})"

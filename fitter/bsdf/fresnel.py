"""Fresnel reflectance of a smooth dielectric interface and Snell refraction.

References:
    Teschner, *Advanced Computer Graphics, Materials 3*, "Snell's law",
    "Total internal reflection", "Reflectance and transmittance" (the
    unpolarised Fresnel equations with eta = eta_t / eta_i).
    Pharr, Jakob, Humphreys, *pbrt-v4*, sec. 9.3 (``FrDielectric``).
"""

from __future__ import annotations

from .._lazy import jnp
from .._math import dot, safe_div, safe_sqrt


def cos_transmitted_sq(cos_i, eta):
    """cos^2 of the refracted angle, 1 - (1 - cos_i^2) / eta^2; < 0 means TIR."""
    return 1.0 - (1.0 - cos_i * cos_i) / (eta * eta)


def fresnel_dielectric(cos_i, eta):
    """Unpolarised Fresnel reflectance F_r.

    Args:
        cos_i: cosine of the incident angle, in [0, 1] (shape (...)).
        eta: relative index eta_t / eta_i (> 0); eta < 1 means leaving the
            denser medium, where total internal reflection gives F_r = 1.

    Returns:
        F_r in [0, 1], shape (...). F_t = 1 - F_r. At normal incidence
        F_r = ((eta - 1)/(eta + 1))^2 (0.04 for eta = 1.5); at grazing, 1.
    """
    ct2 = cos_transmitted_sq(cos_i, eta)
    ok = ct2 > 0
    cos_t = safe_sqrt(ct2)
    r_p = safe_div(eta * cos_i - cos_t, eta * cos_i + cos_t, ok)
    r_s = safe_div(cos_i - eta * cos_t, cos_i + eta * cos_t, ok)
    return jnp.where(ok, 0.5 * (r_p * r_p + r_s * r_s), 1.0)


def fresnel_dielectric_deta(cos_i, eta):
    """F_r (as ``fresnel_dielectric``) and its derivative dF_r/d eta, each (...).

    Differentiating r_p, r_s with d cos_t / d eta = sin^2(theta_i) /
    (eta^3 cos_t). Where total internal reflection holds (F_r = 1) the
    derivative is 0. The renderer uses it instead of forward-mode autodiff,
    which XLA fuses poorly on CPU (measured 5x slower for Torrance-Sparrow);
    ``tests/test_stability.py`` checks it (in Torrance-Sparrow's ``shape_grad``)
    against ``jax.jacfwd``.
    """
    sin2 = 1.0 - cos_i * cos_i
    ct2 = 1.0 - sin2 / (eta * eta)
    ok = ct2 > 0
    cos_t = safe_sqrt(ct2)
    dcos_t = safe_div(sin2, eta * eta * eta * cos_t, ok)
    b_p, b_s = eta * cos_i + cos_t, cos_i + eta * cos_t
    a_p, a_s = eta * cos_i - cos_t, cos_i - eta * cos_t
    r_p = safe_div(a_p, b_p, ok)
    r_s = safe_div(a_s, b_s, ok)
    # (a' b - a b') / b^2 simplified by hand, so the factor cos_i is explicit
    # (dF/deta -> 0 at grazing without cancellation).
    dr_p = safe_div(2.0 * cos_i * (cos_t - eta * dcos_t), b_p * b_p, ok)
    dr_s = safe_div(-2.0 * cos_i * (cos_t + eta * dcos_t), b_s * b_s, ok)
    f = jnp.where(ok, 0.5 * (r_p * r_p + r_s * r_s), 1.0)
    return f, jnp.where(ok, r_p * dr_p + r_s * dr_s, 0.0)


def refract(d, n, eta):
    """Snell refraction of the travelling direction ``d`` through normal ``n``.

    Args:
        d: unit direction of travel, (..., 3), with dot(d, n) < 0 (``n`` faces
            the side the ray comes from).
        n: unit normal, (..., 3).
        eta: eta_t / eta_i.

    Returns:
        (t, tir): the unit transmitted direction (lecture's
        t = w/eta - (cos_t - cos_i/eta) n with w = -d, here written for the
        travel direction) and a boolean total-internal-reflection mask; where
        ``tir`` is true, ``t`` is the mirror direction.
    """
    cos_i = -dot(d, n)
    ct2 = cos_transmitted_sq(cos_i, eta)
    tir = ct2 <= 0
    cos_t = safe_sqrt(ct2)
    t = d / jnp.asarray(eta)[..., None] + ((cos_i / eta) - cos_t)[..., None] * n
    mirror = d + 2.0 * cos_i[..., None] * n
    return jnp.where(tir[..., None], mirror, t), tir


def radiance_scale(eta):
    """Radiance change (eta_t / eta_i)^2 of light refracted into a medium.

    ``eta`` = eta_t / eta_i along the direction the light travels. Entering and
    leaving a sphere multiplies by eta^2 and 1/eta^2, which cancel on a full
    pass (Teschner, *Materials 3*, "Specular transmission").
    """
    return eta * eta

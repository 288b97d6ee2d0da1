"""Fresnel reflectance of smooth dielectric and conductor interfaces; Snell refraction.

References:
    Teschner, *Advanced Computer Graphics, Materials 3*, "Snell's law",
    "Total internal reflection", "Reflectance and transmittance" (the
    unpolarised Fresnel equations with eta = eta_t / eta_i).
    Pharr, Jakob, Humphreys, *pbrt-v4*, sec. 9.3 (``FrDielectric``,
    ``FrComplex``: the conductor case, a complex index eta + i k).
    Mitsuba 3, ``include/mitsuba/render/fresnel.h``, ``fresnel_conductor``
    (the same exact unpolarised formula in real arithmetic, used below).
"""

from __future__ import annotations

from .._lazy import jnp
from .._math import dot, safe_div, safe_sqrt


#: Within this of eta = 1 the Fresnel amplitudes are written without cancellation.
NEAR_ONE = 1e-2

# A scalar's reciprocal is taken once and multiplied per sample: the specular
# lobes' renders are bound by per-sample divisions (``microfacet``, same rule).


def cos_transmitted_sq(cos_i, eta):
    """cos^2 of the refracted angle, 1 - (1 - cos_i^2) / eta^2; < 0 means TIR."""
    return 1.0 - (1.0 - cos_i * cos_i) * (1.0 / (eta * eta))


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
    r_p, r_s = _amplitudes(cos_i, eta, safe_sqrt(ct2), ok)
    return jnp.where(ok, 0.5 * (r_p * r_p + r_s * r_s), 1.0)


def _amplitudes(cos_i, eta, cos_t, ok):
    """r_p = (eta c_i - c_t)/(eta c_i + c_t), r_s = (c_i - eta c_t)/(c_i + eta c_t),
    with the numerators multiplied out so that no near-equal numbers are
    subtracted near eta = 1 (where F ~ (eta - 1)^2): using eta^2 c_t^2 =
    eta^2 - s^2, r_s = (1 - eta^2)/(c_i + eta c_t)^2 and r_p = (eta^2 - 1)
    (c_i^2 - s^2/eta^2)/(eta c_i + c_t)^2, s^2 = 1 - c_i^2. Used within
    ``NEAR_ONE`` of eta = 1 only; elsewhere the direct numerators (times b, over
    b^2) are exact at grazing (r = -1, F = 1 exactly)."""
    e2m1 = (eta - 1.0) * (eta + 1.0)
    b_p = jnp.where(ok, eta * cos_i + cos_t, 1.0)  # > 0 where ok
    b_s = jnp.where(ok, cos_i + eta * cos_t, 1.0)
    near = jnp.abs(eta - 1.0) < NEAR_ONE
    # Both forms over b^2, so each amplitude costs one division (the renders are
    # bound by them); (eta c_i - c_t) b_p is the far form's numerator times b_p.
    # The floor only meets b ~ 0: eta = 1 at c_i < 1e-150, where the numerator is 0.
    num_p = jnp.where(near, e2m1 * (cos_i * cos_i - (1.0 - cos_i * cos_i) * (1.0 / (eta * eta))),
                      (eta * cos_i - cos_t) * b_p)
    num_s = jnp.where(near, -e2m1, (cos_i - eta * cos_t) * b_s)
    return (safe_div(num_p, jnp.maximum(b_p * b_p, 1e-300), ok),
            safe_div(num_s, jnp.maximum(b_s * b_s, 1e-300), ok))


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
    ct2 = 1.0 - sin2 * (1.0 / (eta * eta))
    ok = ct2 > 0
    cos_t = safe_sqrt(ct2)
    dcos_t = safe_div(sin2 * (1.0 / (eta * eta * eta)), cos_t, ok)
    b_p, b_s = eta * cos_i + cos_t, cos_i + eta * cos_t
    r_p, r_s = _amplitudes(cos_i, eta, cos_t, ok)
    # (a' b - a b') / b^2 simplified by hand, so the factor cos_i is explicit
    # (dF/deta -> 0 at grazing without cancellation).
    dr_p = safe_div(2.0 * cos_i * (cos_t - eta * dcos_t), b_p * b_p, ok)
    dr_s = safe_div(-2.0 * cos_i * (cos_t + eta * dcos_t), b_s * b_s, ok)
    f = jnp.where(ok, 0.5 * (r_p * r_p + r_s * r_s), 1.0)
    return f, jnp.where(ok, r_p * dr_p + r_s * dr_s, 0.0)


def _conductor_terms(cos_i, eta, k):
    """Shared intermediate values of the conductor Fresnel formula, each (...).

    With s2 = sin^2(theta_i) and the complex index eta + i k, Mitsuba's real
    form writes t1 = eta^2 - k^2 - s2, A = |(eta + i k)^2 - s2| =
    sqrt(t1^2 + 4 eta^2 k^2) and a^2 = (A + t1)/2 (a = Re sqrt((eta + ik)^2 - s2)).
    a^2 is taken as 2 eta^2 k^2 / (A - t1) where t1 < 0, which is the same
    number without the cancellation of A + t1 (metals at grazing, k -> 0).
    """
    c2 = cos_i * cos_i
    s2 = 1.0 - c2
    t1 = eta * eta - k * k - s2
    big = jnp.sqrt(t1 * t1 + 4.0 * eta * eta * k * k)
    neg = t1 < 0
    a2 = jnp.where(neg, 2.0 * eta * eta * k * k / jnp.where(neg, big - t1, 1.0),
                   0.5 * (big + t1))
    return c2, s2, big, a2


def fresnel_conductor(cos_i, eta, k):
    """Unpolarised Fresnel reflectance of a conductor with complex index eta + i k.

    Args:
        cos_i: cosine of the incident angle, in [0, 1] (shape (...)).
        eta, k: real and imaginary parts of the relative index (> 0), shape
            (...) broadcastable against ``cos_i`` (one value per RGB channel
            when given as (..., 3) against cos_i (..., 1)).

    Returns:
        F_r in [0, 1]. r_s = (T1 - T2)/(T1 + T2) with T1 = A + cos^2,
        T2 = 2 a cos; r_p = r_s (A cos^2 + s2^2 - T2 s2)/(A cos^2 + s2^2 + T2 s2);
        F = (r_s + r_p)/2 (pbrt-v3 ``FrConductor``, Mitsuba ``fresnel_conductor``).
        At normal incidence F = ((eta - 1)^2 + k^2)/((eta + 1)^2 + k^2)
        (``conductor_f0``); k = 0 gives the dielectric F for eta >= 1.
    """
    return fresnel_conductor_grad(cos_i, eta, k)[0]


def fresnel_conductor_grad(cos_i, eta, k):
    """F_r (as ``fresnel_conductor``) and its derivatives (F, dF/d eta, dF/d k).

    Chain rule through the terms of ``_conductor_terms``: dA/d eta =
    2 eta (t1 + 2 k^2)/A, dA/dk = 2 k (2 eta^2 - t1)/A, and, using A + t1 =
    2 a^2 so that no difference of near-equal numbers is formed,
    d a^2/d eta = 2 eta (a^2 + k^2)/A, d a^2/dk = 2 k (eta^2 - a^2)/A with
    eta^2 - a^2 = 2 eta^2 s2 / (eta^2 + k^2 + s2 + A).
    Requires eta > 0 and k > 0 or eta >= 1 (a > 0); the lobe's box keeps
    both positive. ``tests/test_conductor.py`` checks them against
    ``jax.jacfwd`` and the value against complex arithmetic.
    """
    c2, s2, big, a2 = _conductor_terms(cos_i, eta, k)
    a = jnp.sqrt(a2)
    t1 = eta * eta - k * k - s2
    d_big = (2.0 * eta * (t1 + 2.0 * k * k) / big, 2.0 * k * (2.0 * eta * eta - t1) / big)
    # eta^2 - a^2 = (P - A)/2 with P = eta^2 + k^2 + s2, and P^2 - A^2 = 4 eta^2 s2:
    # written as 2 eta^2 s2 / (P + A), it keeps its digits near normal incidence.
    e2_a2 = 2.0 * eta * eta * s2 / (eta * eta + k * k + s2 + big)
    d_a = (eta * (a2 + k * k) / (big * a), k * e2_a2 / (big * a))
    t_1 = big + c2
    t_2 = 2.0 * cos_i * a
    r_s = (t_1 - t_2) / (t_1 + t_2)
    t_3 = big * c2 + s2 * s2
    t_4 = t_2 * s2
    q = (t_3 - t_4) / (t_3 + t_4)
    f = 0.5 * (r_s + r_s * q)
    grads = []
    for db, da in zip(d_big, d_a):
        dt_2 = 2.0 * cos_i * da
        dr_s = 2.0 * (t_2 * db - t_1 * dt_2) / ((t_1 + t_2) ** 2)
        dq = 2.0 * (t_4 * c2 * db - t_3 * s2 * dt_2) / ((t_3 + t_4) ** 2)
        grads.append(0.5 * (dr_s * (1.0 + q) + r_s * dq))
    return f, grads[0], grads[1]


def conductor_f0(eta, k):
    """Normal-incidence reflectance ((eta - 1)^2 + k^2) / ((eta + 1)^2 + k^2)
    of a conductor (NumPy or JAX arrays); what one image pins best."""
    return ((eta - 1.0) ** 2 + k * k) / ((eta + 1.0) ** 2 + k * k)


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

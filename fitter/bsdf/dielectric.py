"""Smooth dielectric sphere: Fresnel reflection plus refraction through it.

Camera ray d hits the sphere at p (normal n). The outgoing radiance is

    L = F(cos_i) L_env(r0)
      + sum_k T_in T_out,k (prod_{j<k} F_j) prod_{j<=k} c^{s_j} eta^2 eta^-2 L_env(t_k)

where r0 is the mirror direction, the ray refracts in (Snell), crosses chords
of length s_j (world units, Beer-Lambert attenuation c^s per RGB channel),
and at each internal hit leaves with transmittance 1 - F_j towards t_k or
reflects internally with F_j (F_j = 1 under total internal reflection). The
eta^2 radiance gain on entering and 1/eta^2 on leaving cancel on a full pass.
On a sphere all chords of one path are equal and all internal angles too, so
s_j = s and F_j = F_1: the series is evaluated from the first crossing, and
the exit directions t_k by a fixed rotation (agrees with explicit tracing to
~1e-13 and is 3-7x cheaper to differentiate).
``bounces`` internal reflections are followed; the default 8 leaves < 1e-3
of the image mean untraced for eta <= 2 (checked in tests).

Mitsuba: the smooth ``dielectric`` (air outside: ext_ior = 1); the
Beer-Lambert attenuation is a medium, not a BSDF: the sphere's interior
``homogeneous`` medium with sigma_t = -ln(attenuation), albedo 0, rendered by
``volpathmis``.

References:
    Teschner, *Materials 3*, "Snell's law", "Total internal reflection",
        "Specular transmission", "Reflectance and transmittance",
        "Light attenuation" (Beer-Lambert L_a = c^d L_b).
"""

from .._lazy import jax, jnp
from .._math import dot, normalize, reflect, safe_pow
from .base import Lobe, Option, Param
from .fresnel import fresnel_dielectric, radiance_scale, refract
from .mitsuba_map import MitsubaMapping, absorbing_medium

#: Path vertices beyond the internal reflections traced here (camera hit,
#: entry, exit): Mitsuba's max_depth for the same truncation is bounces + this.
MITSUBA_EXTRA_DEPTH = 3


def _series(eta, att, opts, hit, env, with_att_grad=False):
    """Radiance (..., 3) and, if ``with_att_grad``, its derivative in each
    attenuation channel (the diagonal, (..., 3)); else None."""
    d, n = hit.ray_dir, hit.normal
    cos_i = jnp.clip(-dot(d, n), 0.0, 1.0)
    f0 = fresnel_dielectric(cos_i, eta)
    out = f0[..., None] * env(reflect(d, n))

    # The first crossing; by the sphere's symmetry every later one repeats it:
    # the same chord s, the same internal angle (so the same Fresnel F_1 and
    # attenuation c^s), and each exit direction is the previous one rotated
    # about n x n_1 by the angle between the two hit normals.
    t, _ = refract(d, n, eta)
    chord = jnp.maximum(-2.0 * dot(hit.position - hit.center, t), 0.0)
    n1 = normalize(hit.position + chord[..., None] * t - hit.center)
    f1 = fresnel_dielectric(jnp.clip(dot(t, n1), 0.0, 1.0), 1.0 / eta)
    t_out, _ = refract(t, -n1, 1.0 / eta)
    transmit = safe_pow(att, chord[..., None])  # Beer-Lambert over one chord
    scale = radiance_scale(eta) * radiance_scale(1.0 / eta)  # in and out: cancels
    first = ((1.0 - f0) * (1.0 - f1) * scale)[..., None]
    step = f1[..., None] * transmit
    cos_phi = dot(n, n1)[..., None]
    axis = jnp.cross(n, n1)  # |axis| = sin(phi); exits lie in the plane normal to it
    rotate = lambda v: v * cos_phi + jnp.cross(axis, v)  # noqa: E731

    if not with_att_grad:
        def crossing(carry, _):
            out, weight, v = carry
            return (out + weight * env(v), weight * step, rotate(v)), None

        # A scan, not a Python loop: compile time does not grow with ``bounces``.
        (out, _, _), _ = jax.lax.scan(crossing, (out, first * transmit, t_out), None,
                                      length=opts["bounces"] + 1)
        return out, None

    # d c^s / dc = s c^s / c (0 at c = 0, the box edge, where it is s c^(s-1)).
    pos = att > 0
    d_transmit = jnp.where(pos, chord[..., None] * transmit / jnp.where(pos, att, 1.0), 0.0)
    d_step = f1[..., None] * d_transmit

    def crossing_grad(carry, _):
        out, d_out, weight, d_weight, v = carry
        e = env(v)
        return (out + weight * e, d_out + d_weight * e, weight * step,
                d_weight * step + weight * d_step, rotate(v)), None

    (out, d_out, _, _, _), _ = jax.lax.scan(
        crossing_grad, (out, jnp.zeros_like(out), first * transmit, first * d_transmit, t_out),
        None, length=opts["bounces"] + 1)
    return out, d_out


def _radiance(p, opts, hit, env):
    return _series(p["eta"], p["attenuation"], opts, hit, env)[0]


def _radiance_grad(p, opts, hit, env):
    """Radiance and its derivatives {eta: (..., 3), attenuation: diagonal (..., 3)}.

    The attenuation enters only the path weights, so its derivatives are
    summed alongside the series; eta moves every direction and is one
    forward-mode tangent. Autodiff of the whole lobe pushed four tangents
    (eta and three channels) through every environment lookup: 5x the
    cost of the value; this is ~2x (``tests/test_stability.py`` checks it
    against ``jax.jacfwd``).
    """
    eta = jnp.asarray(p["eta"])
    (out, d_att), (d_eta, _) = jax.jvp(
        lambda e: _series(e, p["attenuation"], opts, hit, env, with_att_grad=True),
        (eta,), (jnp.ones_like(eta),))
    return out, {"eta": d_eta, "attenuation": d_att}


def _mitsuba(p, opts):
    return {"type": "dielectric", "int_ior": float(p["eta"]), "ext_ior": 1.0}


LOBE = Lobe(
    name="dielectric",
    kind="specular",
    params=(
        Param("eta", 1, 1.5, 1.0, 4.0, "eta", "index of refraction inside / outside"),
        Param("attenuation", 3, 1.0, 0.0, 1.0, "logit",
              "Beer-Lambert transmittance c per world unit of path inside (L_a = c^d L_b), "
              "not a surface reflectance"),
    ),
    # Each bounce is one more pass over the samples; 64 (8x the default) bounds
    # the work a config may ask for (1e8 bounces once ran for 10 minutes).
    options=(Option("bounces", None, 8, "internal reflections followed", most=64),),
    radiance=_radiance,
    radiance_grad=_radiance_grad,
    doc="Fresnel reflection + Snell refraction through the sphere, total internal reflection, "
        "η² radiance scaling (cancels on a full pass), Beer-Lambert c^d with d in world units",
    transmissive=True,
    mitsuba=MitsubaMapping(
        _mitsuba,
        interior=lambda p, opts: absorbing_medium(p["attenuation"]),
        max_depth=lambda opts: opts["bounces"] + MITSUBA_EXTRA_DEPTH),
)

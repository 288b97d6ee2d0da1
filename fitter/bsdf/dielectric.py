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
of the image mean untraced for eta <= 2 (checked in tests). A fit follows
fewer where the closed-form bound on the rest (``untraced_bound``: a
geometric series in F c^s, times the brightest environment radiance) stays
below a tenth of the noise in every fitted pixel (``_cheapest``). A fit
starts from a coarse search (``_search_rounds``): eta - 1 on a log grid and
each attenuation channel on a logit grid, so that eta near 1 is found from
the default start.

Mitsuba: the smooth ``dielectric`` (air outside: ext_ior = 1); the
Beer-Lambert attenuation is a medium, not a BSDF: the sphere's interior
``homogeneous`` medium with sigma_t = -ln(attenuation), albedo 0, rendered by
``volpathmis``.

References:
    Teschner, *Materials 3*, "Snell's law", "Total internal reflection",
        "Specular transmission", "Reflectance and transmittance",
        "Light attenuation" (Beer-Lambert L_a = c^d L_b).
"""

import numpy as np

from .._lazy import jax, jnp
from .._math import dot, normalize, reflect, safe_pow
from .base import Lobe, Option, Param, StartSearch
from .fresnel import fresnel_dielectric, fresnel_dielectric_deta, refract
from .mitsuba_map import MitsubaMapping, absorbing_medium

#: Path vertices beyond the internal reflections traced here (camera hit,
#: entry, exit): Mitsuba's max_depth for the same truncation is bounces + this.
MITSUBA_EXTRA_DEPTH = 3


def _directions(eta, hit):
    """The first exit direction, the rotation (cos phi (..., 1), axis) taking
    each exit to the next, and the chord s (...) of the refracted ray.

    By the sphere's symmetry every crossing repeats the first: the same chord
    s, the same internal angle (so the same Fresnel F_1 and attenuation c^s),
    and each exit direction is the previous one rotated about n x n_1 by the
    angle between the two hit normals (|axis| = sin phi)."""
    d, n = hit.ray_dir, hit.normal
    t, _ = refract(d, n, eta)
    chord = jnp.maximum(-2.0 * dot(hit.position - hit.center, t), 0.0)
    n1 = normalize(hit.position + chord[..., None] * t - hit.center)
    t_out, _ = refract(t, -n1, 1.0 / eta)
    return t_out, dot(n, n1)[..., None], jnp.cross(n, n1), chord


def _crossing(eta, att, hit):
    """What the first crossing fixes for every later one, each (...[, 3]): the
    front reflectance F_0, the first exit's weight, the per-bounce factor
    F_1 c^s, the first exit direction, the rotation (cos phi, axis) taking
    each exit to the next, and the chord s."""
    cos_i = jnp.clip(-dot(hit.ray_dir, hit.normal), 0.0, 1.0)
    f0 = fresnel_dielectric(cos_i, eta)
    t_out, cos_phi, axis, chord = _directions(eta, hit)
    # Inside, the ray meets the surface at the refraction angle, where the
    # reflectance from inside equals F_0 (Fresnel is symmetric under reversal:
    # F(cos_t, 1/eta) = F(cos_i, eta); no total internal reflection on a
    # sphere). The radiance gains eta^2 going in and 1/eta^2 going out: a
    # factor 1 on every exit.
    transmit = safe_pow(att, chord[..., None])  # Beer-Lambert over one chord
    first = ((1.0 - f0) ** 2)[..., None] * transmit
    return f0, first, f0[..., None] * transmit, t_out, cos_phi, axis, chord


def _radiance(p, opts, hit, env):
    f0, weight, step, v, cos_phi, axis, _ = _crossing(p["eta"], p["attenuation"], hit)
    out = f0[..., None] * env(reflect(hit.ray_dir, hit.normal))

    def crossing(carry, _):
        out, weight, v = carry
        return (out + weight * env(v), weight * step,
                v * cos_phi + jnp.cross(axis, v)), None

    # A scan, not a Python loop: compile time does not grow with ``bounces``.
    (out, _, _), _ = jax.lax.scan(crossing, (out, weight, v), None, length=opts["bounces"] + 1)
    return out


def _radiance_grad(p, opts, hit, env):
    """Radiance and its derivatives {eta: (..., 3), attenuation: diagonal (..., 3)}.

    The directions and chord of the first crossing and their eta derivatives
    come from one forward-mode tangent, the Fresnel factor's from
    ``fresnel_dielectric_deta``; the series then carries d/d eta (through
    each exit direction's environment lookup) and d/dc beside the value.
    Autodiff of the whole lobe pushed four tangents (eta and three channels)
    through every lookup. ``tests/test_dielectric_fit.py`` checks this
    against ``jax.jacfwd``.
    """
    eta, att = jnp.asarray(p["eta"]), p["attenuation"]
    cos_i = jnp.clip(-dot(hit.ray_dir, hit.normal), 0.0, 1.0)
    f0, df0 = fresnel_dielectric_deta(cos_i, eta)
    (v, cos_phi, axis, chord), (dv, dcos_phi, daxis, dchord) = jax.jvp(
        lambda e: _directions(e, hit), (eta,), (jnp.ones_like(eta),))
    # c^s and its derivatives: s c^s / c in c (weight and step are each linear
    # in c^s) and c^s ln(c) ds in eta; at the box edge c = 0 both are 0.
    transmit = safe_pow(att, chord[..., None])
    pos = att > 0
    safe_att = jnp.where(pos, att, 1.0)
    s_over_c = jnp.where(pos, chord[..., None] / safe_att, 0.0)
    dtransmit = transmit * jnp.log(safe_att) * dchord[..., None]
    g0, dg0 = (1.0 - f0)[..., None], -df0[..., None]
    weight, step = g0 * g0 * transmit, f0[..., None] * transmit
    dweight = 2.0 * g0 * dg0 * transmit + g0 * g0 * dtransmit
    dstep = df0[..., None] * transmit + f0[..., None] * dtransmit
    aweight, astep = weight * s_over_c, step * s_over_c
    e_r = env(reflect(hit.ray_dir, hit.normal))
    f0, df0 = f0[..., None], df0[..., None]

    def crossing(carry, _):
        out, d_eta, d_att, w, dw, aw, v, dv = carry
        e, de = jax.jvp(env, (v,), (dv,))
        carry = (out + w * e, d_eta + dw * e + w * de, d_att + aw * e,
                 w * step, dw * step + w * dstep, aw * step + w * astep,
                 v * cos_phi + jnp.cross(axis, v),
                 dv * cos_phi + v * dcos_phi + jnp.cross(daxis, v) + jnp.cross(axis, dv))
        return carry, None

    init = (f0 * e_r, df0 * e_r, jnp.zeros_like(e_r), weight, dweight, aweight, v, dv)
    (out, d_eta, d_att, *_), _ = jax.lax.scan(crossing, init, None, length=opts["bounces"] + 1)
    return out, {"eta": d_eta, "attenuation": d_att}


#: The start search's grid sizes (``_search_rounds``). Measured (128^2 envmap):
#: eta = 1.001 has a basin ~0.005 wide, i.e. a factor ~5 in eta - 1, and 40
#: points over 4.5 decades of eta - 1 are a factor 1.3 apart.
ETA_POINTS = 40
ETA_MIN_EXCESS = 1e-4
ATT_POINTS = 24


def _models(eta, atts, opts, hit, env):
    """Radiance (A, ..., 3) at one eta for each row of ``atts`` (A, 3): the
    environment is looked up once for all of them (the exits do not depend
    on the attenuation)."""
    f0, first, f1, v, cos_phi, axis, chord = _crossing(eta, jnp.ones(3, hit.position.dtype), hit)

    def crossing(v, _):
        return v * cos_phi + jnp.cross(axis, v), env(v)

    _, exits = jax.lax.scan(crossing, v, None, length=opts["bounces"] + 1)  # (B, ..., 3)
    base = f0[..., None] * env(reflect(hit.ray_dir, hit.normal))
    # Exit k carries (1 - F0)(1 - F1) F1^k c^((k + 1) s) (``first``, ``f1``: at c = 1).
    terms = first * exits * f1 ** jnp.arange(exits.shape[0], dtype=chord.dtype).reshape(
        (-1,) + (1,) * f1.ndim)

    def one(att):  # (3,): sum_k terms_k T^(k+1) by Horner's rule, T = c^s
        transmit = safe_pow(att, chord[..., None])
        horner, _ = jax.lax.scan(lambda h, t: (transmit * (t + h), None),
                                 jnp.zeros_like(base), terms, reverse=True)
        return base + horner

    return jax.vmap(one)(atts)


#: Logit of the attenuation grid's ends (0.005 and 0.998).
_ATT_LOGITS = (-5.3, 6.2)


def _search(p, opts, hit, env, cost):
    """The lowest ``cost`` over a grid: ``p["eta"]`` (G,) x ``p["attenuation"]``
    (A, 3), a column of candidates per channel.

    ``cost(model (..., 3)) -> (3,)`` per channel; the channels of the
    attenuation are independent given eta, so each takes its best candidate.
    Returns the best {eta, attenuation} and the cost's largest relative
    change along eta (at some attenuation row) and along each channel's
    attenuation (at some eta): ``StartSearch``'s spread.
    """
    atts = p["attenuation"]
    costs = jax.lax.map(lambda e: jax.vmap(cost)(_models(e, atts, opts, hit, env)),
                        p["eta"])  # (G, A, 3)
    per_eta = jnp.sum(jnp.min(costs, axis=1), axis=-1)  # each channel's best attenuation
    i = jnp.argmin(per_eta)
    best = {"eta": p["eta"][i], "attenuation": atts[jnp.argmin(costs[i], axis=0), jnp.arange(3)]}
    total = jnp.sum(costs, axis=-1)  # (G, A)
    tiny = jnp.finfo(costs.dtype).tiny
    spread = {"eta": jnp.max(jnp.ptp(total, axis=0)) / jnp.maximum(jnp.max(total), tiny),
              "attenuation": jnp.max(jnp.ptp(costs, axis=1), axis=0)
              / jnp.maximum(jnp.max(costs, axis=(0, 1)), tiny)}
    return best, spread


def _grid(lo, hi, n, fixed):
    """(coarse, fine): functions (best, in the grid's coordinate) -> n
    coordinates: ``best`` first (so a tie keeps it), then ``n - 1`` over
    [lo, hi], or over one coarse cell around ``best``; n copies of ``best``
    if ``fixed``."""
    cell = (hi - lo) / (n - 2)
    if fixed:
        return (lambda b: np.full(n, b),) * 2
    return (lambda b: np.insert(np.linspace(lo, hi, n - 1), 0, b),
            lambda b: np.insert(np.clip(b + np.linspace(-cell, cell, n - 1), lo, hi), 0, b))


def _search_rounds(p, free, box):
    """Two rounds, each (best so far) -> grid: eta - 1 log-spaced over the box
    (from ``ETA_MIN_EXCESS``) and the attenuation logit-spaced over [0.005,
    0.998]; then each over one cell of the first grid around the best. The
    best so far is the first candidate of every round (kept on a tie: a
    black environment leaves the start where it was)."""
    e_lo, e_hi = box.get("eta", (1.0, 4.0))
    x_lo, x_hi = np.log(max(e_lo - 1.0, ETA_MIN_EXCESS)), np.log(e_hi - 1.0)
    etas = _grid(x_lo, x_hi, ETA_POINTS + 1, "eta" not in free)
    a_lo, a_hi = box.get("attenuation", (0.0, 1.0))
    logit = lambda c: np.log(c) - np.log1p(-c)  # noqa: E731
    clip = lambda c: np.clip(c, max(a_lo, 1e-12), min(a_hi, 1.0 - 1e-12))  # noqa: E731
    u_lo, u_hi = max(_ATT_LOGITS[0], logit(clip(a_lo))), min(_ATT_LOGITS[1], logit(clip(a_hi)))
    atts = _grid(u_lo, u_hi, ATT_POINTS + 1, "attenuation" not in free)

    def round_(i):
        def grid(best):
            x = np.log(max(float(best["eta"]) - 1.0, ETA_MIN_EXCESS))
            eta = 1.0 + np.exp(etas[i](x))
            eta[0] = float(best["eta"])  # exactly, also below ETA_MIN_EXCESS
            c = np.broadcast_to(np.asarray(best["attenuation"], dtype=np.float64), (3,))
            u = np.stack([atts[i](logit(clip(cj))) for cj in c], axis=-1)  # (A, 3)
            att = 1.0 / (1.0 + np.exp(-u))
            att[0] = c  # exactly, also on the box edge
            return {"eta": eta, "attenuation": att}
        return grid

    return round_(0), round_(1)


#: The bounce count is chosen at the start point with this much margin: the
#: attenuation as if half as absorbing (c -> sqrt(c)) and eta - 1 larger by
#: ``BOUNCE_ETA_MARGIN`` (the untraced part grows with both), so the fit's
#: path to its solution stays within the bound.
BOUNCE_ETA_MARGIN = 1.2


def _series_factors(eta, att, cos_i, chord):
    """(F (..., 1), T (..., 3)) of the path series: Fresnel reflectance and
    one chord's transmittance c^s (NumPy, float64)."""
    c = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    ct = np.sqrt(np.maximum(1.0 - (1.0 - c * c) / (eta * eta), 0.0))
    den_s, den_p = c + eta * ct, eta * c + ct
    ok = (den_s > 0) & (den_p > 0)
    r_s = np.where(ok, (c - eta * ct) / np.where(ok, den_s, 1.0), -1.0)
    r_p = np.where(ok, (eta * c - ct) / np.where(ok, den_p, 1.0), -1.0)
    f = (0.5 * (r_s * r_s + r_p * r_p))[..., None]
    return f, np.power(np.asarray(att, dtype=np.float64), np.asarray(chord)[..., None])


def untraced_bound(eta, att, cos_i, chord, bounces):
    """Upper bound (..., 3) on the weight of the internal paths after exit
    ``bounces``, per unit environment radiance: the geometric series
    sum_{k > K} (1 - F)^2 F^k T^(k+1) = (1 - F)^2 T (F T)^(K+1) / (1 - F T)
    with T = c^s; on a sphere the internal reflectance F_1 equals the outer
    F_0 = F(cos_i, eta) (reciprocity: the internal angle is the refraction
    angle). NumPy, float64."""
    f, transmit = _series_factors(eta, att, cos_i, chord)
    ft = f * transmit
    den = 1.0 - ft  # 0 only where F = 1 (grazing), where (1 - F)^2 = 0 too
    return np.where(den > 0, (1.0 - f) ** 2 * transmit * ft ** (bounces + 1)
                    / np.where(den > 0, den, 1.0), 0.0)


def _cheapest(p, opts, hit, weight, env_max, tolerance):
    """{"bounces": K}: the fewest internal reflections (at most the option's
    value) for which every pixel's untraced radiance is bounded by
    ``tolerance`` (3,): sum over its samples of ``weight`` (P, K) *
    ``untraced_bound`` * ``env_max`` (3,, the brightest the environment is)."""
    eta = 1.0 + BOUNCE_ETA_MARGIN * (float(p["eta"]) - 1.0)
    att = np.sqrt(np.broadcast_to(np.asarray(p["attenuation"], dtype=np.float64), (3,)))
    d, n = np.asarray(hit.ray_dir), np.asarray(hit.normal)
    cos_i = np.clip(-np.sum(d * n, axis=-1), 0.0, 1.0)
    cos_t = np.sqrt(np.maximum(1.0 - (1.0 - cos_i ** 2) / eta ** 2, 0.0))
    chord = 2.0 * float(hit.radius) * cos_t
    tail = untraced_bound(eta, att, cos_i, chord, 0) * np.asarray(weight)[..., None]
    f, transmit = _series_factors(eta, att, cos_i, chord)
    ft = f * transmit
    for k in range(opts["bounces"]):
        if np.all(np.sum(tail, axis=1) * env_max <= tolerance):
            return {"bounces": k}
        tail *= ft  # the bound after one more exit
    return {"bounces": opts["bounces"]}


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
    options=(Option("bounces", None, 8, "internal reflections followed at most (a fit follows "
                          "fewer where the rest is below a tenth of the noise)", most=64),),
    radiance=_radiance,
    radiance_grad=_radiance_grad,
    start_search=StartSearch(_search_rounds, _search),
    cheapest_options=_cheapest,
    doc="Fresnel reflection + Snell refraction through the sphere, total internal reflection, "
        "η² radiance scaling (cancels on a full pass), Beer-Lambert c^d with d in world units",
    transmissive=True,
    single_precision=False,  # 16 of 30 profile points to float64 (benchmarks/profile_subset.py)
    mitsuba=MitsubaMapping(
        _mitsuba,
        interior=lambda p, opts: absorbing_medium(p["attenuation"]),
        max_depth=lambda opts: opts["bounces"] + MITSUBA_EXTRA_DEPTH),
)

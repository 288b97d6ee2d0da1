"""Oren-Nayar rough diffuse lobe, the lecture's qualitative A/B model.

f = rho_d / pi * (A + B max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta)),
A = 1 - sigma^2 / (2 (sigma^2 + 0.33)), B = 0.45 sigma^2 / (sigma^2 + 0.09),
alpha = max(theta_i, theta_o), beta = min(theta_i, theta_o).

``sigma`` is the standard deviation, in radians, of the angle between the
facet normals and the surface normal (sigma^2 its variance). sigma = 0 gives
A = 1, B = 0: exactly Lambert.

No angles are formed (arccos has an infinite derivative at 1): with
sin(theta_i) sin(theta_o) cos(phi_i - phi_o) = wi.wo - cos_i cos_o and
sin(alpha) sin(beta) = sin(theta_i) sin(theta_o), cos(beta) = max(cos_i, cos_o),

    max(0, cos dphi) sin(alpha) tan(beta) = max(0, wi.wo - cos_i cos_o) / max(cos_i, cos_o).

Mitsuba has no Oren-Nayar: the ``fitter_oren_nayar`` plugin here evaluates
the same A/B form in drjit (``reflectance`` rgb, ``sigma`` radians).

References:
    Teschner, *Materials 3*, "Oren-Nayar diffuse material".
    Oren, Nayar (1994), "Generalization of Lambert's reflectance model",
        SIGGRAPH, eq. 30 (qualitative model).
"""

from .._lazy import jnp
from .._math import safe_div
from .base import Hints, Lobe, Param, Point
from .mitsuba_map import MitsubaMapping, cosine_sampled, props_rgb, rgb


def coefficients(sigma):
    """(A, B) of the qualitative Oren-Nayar model for facet slope std-dev sigma."""
    s2 = sigma * sigma
    return 1.0 - s2 / (2.0 * (s2 + 0.33)), 0.45 * s2 / (s2 + 0.09)


def _term(c):
    """max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta) from the cosines (above)."""
    cmax = jnp.maximum(c.cos_i, c.cos_o)
    return safe_div(jnp.maximum(c.cos_io - c.cos_i * c.cos_o, 0.0), cmax, cmax > 0)


def _uniform(p, opts):
    """A / pi: the part of the shape the same for every pair of directions."""
    return coefficients(p["sigma"])[0] / jnp.pi


def _kernel_factor(p, opts):
    """B / pi: the factor of the angular term (``_term``)."""
    return coefficients(p["sigma"])[1] / jnp.pi


def _shape(p, opts, c):
    return _uniform(p, opts) + _kernel_factor(p, opts) * _term(c)


def _shape_grad(p, opts, c):
    """Shape and d shape / d sigma (``Lobe.shape_grad``): dA/dsigma =
    -0.33 sigma / (sigma^2 + 0.33)^2, dB/dsigma = 0.081 sigma / (sigma^2 + 0.09)^2."""
    sigma = p["sigma"]
    s2 = sigma * sigma
    (a, b), term = coefficients(sigma), _term(c)
    da = -0.33 * sigma / ((s2 + 0.33) * (s2 + 0.33))
    db = 0.081 * sigma / ((s2 + 0.09) * (s2 + 0.09))
    return (a + b * term) / jnp.pi, {"sigma": (da + db * term) / jnp.pi}


def _mitsuba(p, opts):
    return {"type": "fitter_oren_nayar", "reflectance": rgb(p["rho_d"]), "sigma": float(p["sigma"])}


def _plugin(mi):
    import drjit as dr

    base = cosine_sampled(mi)

    class OrenNayar(base):
        """The lecture's angle form, written from angles (not ``_shape``'s dot
        products, so the Mitsuba cross-check stays independent):
        rho/pi (A + B max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta)),
        theta = atan2(|w_xy|, w_z) (accurate in float32, unlike acos near 1)."""

        def __init__(self, props):
            base.__init__(self, props)
            self.rho = props_rgb(mi, props, "reflectance", 0.5)
            s2 = float(props.get("sigma", 0.3)) ** 2
            self.a = mi.Float(1.0 - s2 / (2.0 * (s2 + 0.33)))
            self.b = mi.Float(0.45 * s2 / (s2 + 0.09))

        def _value(self, wi, wo):
            ti = dr.atan2(dr.sqrt(wi.x * wi.x + wi.y * wi.y), wi.z)
            to = dr.atan2(dr.sqrt(wo.x * wo.x + wo.y * wo.y), wo.z)
            cos_dphi = dr.cos(dr.atan2(wi.y, wi.x) - dr.atan2(wo.y, wo.x))
            alpha, beta = dr.maximum(ti, to), dr.minimum(ti, to)
            term = dr.maximum(cos_dphi, 0.0) * dr.sin(alpha) * dr.tan(beta)
            return self.rho * (dr.inv_pi * (self.a + self.b * term))

        def to_string(self):
            return f"fitter_oren_nayar[A={self.a}, B={self.b}]"

    return OrenNayar


LOBE = Lobe(
    name="oren_nayar",
    kind="brdf",
    params=(
        Param("rho_d", 3, 0.5, 0.0, 1.0, "logit",
              "albedo of the Lambertian facets; the surface's albedo at normal incidence is "
              "A ρ_d (A = 1 − σ²/(2(σ²+0.33)))"),
        Param("sigma", 1, 0.3, 0.0, 1.5, "box",
              "std-dev of the facet slope angle, radians (lecture: σ² ≤ 1)"),
    ),
    scale="rho_d",
    shape=_shape,
    shape_grad=_shape_grad,
    uniform=_uniform,
    kernel_factor=_kernel_factor,
    kernel=_term,
    doc="lecture's A/B form; σ = std-dev of the facet slope angle; σ = 0 is Lambert exactly",
    mitsuba=MitsubaMapping(_mitsuba, plugins={"fitter_oren_nayar": _plugin}),
    hints=Hints(
        points=tuple(Point(f"oren_nayar-s{s:g}", {"rho_d": (1.0, 1.0, 1.0), "sigma": s})
                     for s in (0.5, 1.5)),
        example={"rho_d": (0.6, 0.5, 0.4), "sigma": 0.7}),
)

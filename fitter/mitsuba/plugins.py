"""Python BSDF plugins for the lobes Mitsuba 3 lacks, and a sum of BSDFs.

Each plugin transcribes the lecture's formula (the same one as the lobe's
JAX ``eval``) in drjit, in the local shading frame (normal = +z). Mitsuba's
``eval`` returns f(wi, wo) cos(theta_o) and must vanish below either horizon.
Sampling is cosine-weighted over the hemisphere: under the project's point
and directional lights only ``eval`` enters the image (``direct`` with
emitter sampling only); the samplers just have to be valid.

Plugins (registered by ``register(mi)`` under these names):

=========================  ==============================================
``fitter_oren_nayar``      ``reflectance`` (rgb), ``sigma`` (radians)
``fitter_phong``           ``specular_reflectance`` (rgb), ``exponent``,
                           ``normalized`` (bool, (e + 2) / (2 pi))
``fitter_torrance_sparrow`` ``alpha`` (= m), ``eta``, ``specular_reflectance``;
                           Beckmann D, V-groove G, dielectric Fresnel
``fitter_sum``             any number of nested BSDFs, summed
=========================  ==============================================

``fitter_sum`` exists because the project's lobes *add* (the lecture's
linearity of BRDFs) while ``blendbsdf`` is a convex mix and ``roughplastic``
adds internal-scattering and Fresnel factors to its diffuse part. It samples
a child uniformly; a smooth sample is weighted by the summed eval over the
mean of the smooth children's pdfs (one-sample MIS, balance heuristic), a
delta sample by the child's weight times the number of children.

References:
    Teschner, *Materials 3*, "Oren-Nayar diffuse material",
        "Torrance-Sparrow specular material"; *Materials 2*, glossy Phong.
    Mitsuba 3 documentation, "Custom plugins in Python".
"""

from __future__ import annotations

import math

_REGISTERED: set[str] = set()


def register(mi) -> None:
    """Register the plugins for the current Mitsuba variant (idempotent)."""
    if mi.variant() in _REGISTERED:
        return
    for name, cls in _classes(mi).items():
        mi.register_bsdf(name, lambda props, cls=cls: cls(props))
    _REGISTERED.add(mi.variant())


def _classes(mi):
    import drjit as dr

    def rgb(props, name, default):
        if name in props:
            v = props[name]  # a float, a colour, or a texture
            if isinstance(v, (int, float)):
                return mi.Color3f(float(v))
            if hasattr(v, "eval"):
                return mi.Color3f(v.eval(dr.zeros(mi.SurfaceInteraction3f)))
            return mi.Color3f(v[0], v[1], v[2])
        return mi.Color3f(default)

    def positive(x):
        return dr.maximum(x, 0.0)

    class _CosineSampled(mi.BSDF):
        """Shared glossy-reflection flags, cosine sampling and pdf."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _value(self, wi, wo):  # f(wi, wo), both above the horizon
            raise NotImplementedError

        def eval(self, ctx, si, wo, active=True):
            ci = mi.Frame3f.cos_theta(si.wi)
            co = mi.Frame3f.cos_theta(wo)
            ok = active & (ci > 0) & (co > 0)
            return dr.select(ok, self._value(si.wi, wo) * co, mi.Color3f(0.0))

        def pdf(self, ctx, si, wo, active=True):
            ci = mi.Frame3f.cos_theta(si.wi)
            co = mi.Frame3f.cos_theta(wo)
            return dr.select(active & (ci > 0) & (co > 0),
                             mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            ci = mi.Frame3f.cos_theta(si.wi)
            active = active & (ci > 0)
            bs = mi.BSDFSample3f()
            bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(bs.wo)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            co = mi.Frame3f.cos_theta(bs.wo)
            ok = active & (co > 0) & (bs.pdf > 0)
            # f cos / pdf with pdf = cos / pi
            weight = dr.select(ok, self._value(si.wi, bs.wo) * math.pi, mi.Color3f(0.0))
            return bs, weight

        def traverse(self, cb):
            pass

        def parameters_changed(self, keys):
            pass

    class OrenNayar(_CosineSampled):
        """rho/pi (A + B max(0, wi.wo - ci co) / max(ci, co)) (see fitter.bsdf.oren_nayar)."""

        def __init__(self, props):
            _CosineSampled.__init__(self, props)
            self.rho = rgb(props, "reflectance", 0.5)
            s2 = float(props.get("sigma", 0.3)) ** 2
            self.a = mi.Float(1.0 - s2 / (2.0 * (s2 + 0.33)))
            self.b = mi.Float(0.45 * s2 / (s2 + 0.09))

        def _value(self, wi, wo):
            ci, co = wi.z, wo.z
            term = positive(dr.dot(wi, wo) - ci * co) / dr.maximum(dr.maximum(ci, co), 1e-12)
            return self.rho * (dr.inv_pi * (self.a + self.b * term))

        def to_string(self):
            return f"fitter_oren_nayar[A={self.a}, B={self.b}]"

    class Phong(_CosineSampled):
        """rho_s cos^e(alpha), cos(alpha) = 2 ci co - wi.wo, optionally (e+2)/(2 pi)."""

        def __init__(self, props):
            _CosineSampled.__init__(self, props)
            self.rho = rgb(props, "specular_reflectance", 0.5)
            e = float(props.get("exponent", 20.0))
            self.e = mi.Float(e)
            self.norm = mi.Float((e + 2.0) / (2.0 * math.pi)
                                 if props.get("normalized", False) else 1.0)

        def _value(self, wi, wo):
            c = 2.0 * wi.z * wo.z - dr.dot(wi, wo)
            lobe = dr.select(c > 0, dr.exp(self.e * dr.log(dr.maximum(c, 1e-30))), 0.0)
            return self.rho * (lobe * self.norm)

        def to_string(self):
            return f"fitter_phong[e={self.e}, norm={self.norm}]"

    class TorranceSparrow(_CosineSampled):
        """rho_s D_n G F / (4 ci co): normalised Beckmann D, V-groove G, dielectric F."""

        def __init__(self, props):
            _CosineSampled.__init__(self, props)
            self.rho = rgb(props, "specular_reflectance", 1.0)
            self.m = mi.Float(max(float(props.get("alpha", 0.2)), 1e-4))
            self.eta = mi.Float(float(props.get("eta", 1.5)))

        def _value(self, wi, wo):
            ci, co = wi.z, wo.z
            h = dr.normalize(wi + wo)
            ch = h.z
            tan2 = (h.x * h.x + h.y * h.y) / dr.maximum(ch * ch, 1e-30)
            m2 = self.m * self.m
            d = dr.exp(-tan2 / m2) / (dr.pi * m2 * dr.square(dr.square(ch)))
            woh = dr.dot(wo, h)
            g = dr.minimum(1.0, 2.0 * ch * dr.minimum(ci, co) / dr.maximum(woh, 1e-30))
            f = mi.fresnel(dr.clip(woh, 0.0, 1.0), self.eta)[0]
            val = d * positive(g) * f / (4.0 * ci * co)
            return self.rho * dr.select(ch > 0, val, 0.0)

        def to_string(self):
            return f"fitter_torrance_sparrow[alpha={self.m}, eta={self.eta}]"

    class Sum(mi.BSDF):
        """The sum of the nested BSDFs (see the module docstring)."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.children = [props[k] for k in sorted(props.keys())
                             if isinstance(props[k], mi.BSDF)]
            if not self.children:
                raise ValueError("fitter_sum needs at least one nested BSDF")
            comps, flags, self.offsets = [], 0, []
            for c in self.children:
                self.offsets.append(len(comps))
                for i in range(c.component_count()):
                    comps.append(c.flags(i))
                flags |= int(c.flags())
            self.m_components = comps
            self.m_flags = flags
            self.n = len(self.children)

        def eval(self, ctx, si, wo, active=True):
            out = mi.Color3f(0.0)
            for c in self.children:
                out += c.eval(ctx, si, wo, active)
            return out

        def pdf(self, ctx, si, wo, active=True):
            out = mi.Float(0.0)
            for c in self.children:
                out += c.pdf(ctx, si, wo, active)
            return out / self.n

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            idx = dr.minimum(mi.UInt32(sample1 * self.n), self.n - 1)
            s1 = sample1 * self.n - mi.Float(idx)
            bs, weight = dr.zeros(mi.BSDFSample3f), mi.Color3f(0.0)
            for i, c in enumerate(self.children):
                sel = active & (idx == i)
                bs_i, w_i = c.sample(ctx, si, s1, sample2, sel)
                bs_i.sampled_component = bs_i.sampled_component + self.offsets[i]
                for field in ("wo", "pdf", "eta", "sampled_type", "sampled_component"):
                    setattr(bs, field, dr.select(sel, getattr(bs_i, field), getattr(bs, field)))
                weight = dr.select(sel, w_i, weight)
            delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            value, pdf = self.eval_pdf(ctx, si, bs.wo, active & ~delta)
            smooth_w = dr.select(pdf > 0, value / pdf, 0.0)
            weight = dr.select(delta, weight * self.n, smooth_w)
            bs.pdf = dr.select(delta, bs.pdf / self.n, pdf)
            return bs, dr.select(active, weight, 0.0)

        def traverse(self, cb):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return f"fitter_sum[{', '.join(str(c) for c in self.children)}]"

    return {"fitter_oren_nayar": OrenNayar, "fitter_phong": Phong,
            "fitter_torrance_sparrow": TorranceSparrow, "fitter_sum": Sum}

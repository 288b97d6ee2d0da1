"""Registers the lobes' Python BSDF plugins with Mitsuba 3, and a sum of BSDFs.

The plugins for lobes Mitsuba lacks live beside their formulas, in the lobe
modules (``Lobe.mitsuba.plugins``: type name -> class factory taking ``mi``);
``register(mi)`` registers those of every lobe in ``fitter.bsdf.LOBES`` plus
``fitter_sum``, the only plugin that belongs to no lobe:

``fitter_sum`` exists because the project's lobes *add* (the lecture's
linearity of BRDFs) while ``blendbsdf`` is a convex mix and ``roughplastic``
adds internal-scattering and Fresnel factors to its diffuse part. It takes
any number of nested BSDFs and samples a child uniformly; a smooth sample is
weighted by the summed eval over the mean of the smooth children's pdfs
(one-sample MIS, balance heuristic), a delta sample by the child's weight
times the number of children.

References:
    Mitsuba 3 documentation, "Custom plugins in Python".
    Veach (1997), PhD thesis, ch. 9: one-sample MIS, balance heuristic.
"""

from __future__ import annotations

from ..bsdf import LOBES

#: (variant, plugin type name) -> the factory registered for it.
_REGISTERED: dict[tuple[str, str], object] = {}


def register(mi) -> None:
    """Register the plugins for the current Mitsuba variant (idempotent; picks up
    lobes registered since the last call)."""
    factories = {"fitter_sum": _sum_class}
    for lobe in LOBES.values():
        if lobe.mitsuba is not None:
            factories.update(lobe.mitsuba.plugins)
    for name, make in factories.items():
        key = (mi.variant(), name)
        if _REGISTERED.get(key) is not make:
            cls = make(mi)
            mi.register_bsdf(name, lambda props, cls=cls: cls(props))
            _REGISTERED[key] = make


def _sum_class(mi):
    import drjit as dr

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

    return Sum

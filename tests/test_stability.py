"""Finite values and finite gradients everywhere in the documented parameter box.

Hypothesis draws parameters from each lobe's box (``Param.lower``/``upper``),
with the exact edges (m = 1e-3, e = 1e4, eta = 1 and 4, sigma = 0, rho = 0
and 1, attenuation 0 and 1) drawn often, and renders two scenes built to hit
the numerical traps of ``notes/numerics.md``: a camera sample exactly tangent
to the sphere (cos_o = 0), a light exactly grazing (n.l = 0 on a whole row),
a light behind the sphere, a point light at the camera (wi = wo), and an
envmap whose lookup the refracted rays differentiate through.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import fitter
from fitter.bsdf import LOBES
from fitter.camera import camera_rays

RENDER_EXAMPLES = 25
EVAL_EXAMPLES = 60

# One material per group of lobes: a NaN anywhere in a sum poisons every
# gradient, so the failure message names the parameters that are non-finite.
MATERIALS = {
    "brdfs-lecture": fitter.Material.make(
        ["lambert", "oren_nayar", "phong", "torrance_sparrow"],
        {"phong.normalized": False, "torrance_sparrow.geometry": "v_groove"}),
    "brdfs-alt": fitter.Material.make(
        ["oren_nayar", "phong", "torrance_sparrow"],
        {"phong.normalized": True, "torrance_sparrow.geometry": "smith"}),
    "specular": fitter.Material.make(["mirror", "dielectric"]),
}


def edge_scene():
    """Orthographic along -z; W = 16 (k = 1) puts a sample at x = 15/16 and
    H = 9 one at y = 0, both exact in binary, so with r = 15/16 that sample's
    ray is exactly tangent. Lights: from +y (n.l = 0 exactly on the middle
    row), from behind, and a point light at the camera."""
    return fitter.Scene(
        width=16, height=9, supersampling=1,
        camera=fitter.Camera(type="orthographic", origin=(0.0, 0.0, 4.0), half_width=1.0),
        sphere=fitter.Sphere(radius=15.0 / 16.0),
        lights=(fitter.DirectionalLight((0.0, -1.0, 0.0), (1.0, 1.0, 1.0)),
                fitter.DirectionalLight((0.0, 0.0, 1.0), (2.0, 2.0, 2.0)),
                fitter.PointLight((0.0, 0.0, 4.0), (10.0, 10.0, 10.0))),
        environment=fitter.Environment(type="constant", radiance=(1.0, 0.5, 0.25)))


def test_edge_scene_has_the_traps():
    scene = edge_scene()
    o, d = camera_rays(scene)
    oc = o - np.asarray(scene.sphere.center)
    b = np.sum(d * oc, -1)
    disc = b * b - (np.sum(oc * oc, -1) - scene.sphere.radius**2)
    assert np.any(disc == 0.0)  # an exactly tangent sample
    assert np.any(o[..., 1] == 0.0)  # the row where the +y light is at n.l = 0


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    from fitter.imageio import write_image

    path = str(tmp_path_factory.mktemp("env") / "sky.exr")
    j, i = np.meshgrid(np.linspace(0, 1, 8), np.linspace(0, 1, 16), indexing="ij")
    write_image(path, np.stack([1 + i, 0.5 + j, 2 - i * j], -1))
    persp = fitter.Scene(
        width=12, height=10, supersampling=2,
        lights=(fitter.PointLight((2.0, 3.0, 4.0), (30.0, 30.0, 30.0)),
                fitter.DirectionalLight((1.0, 0.0, 0.0), (1.0, 1.0, 1.0))),  # grazing/behind
        environment=fitter.Environment(type="envmap", file=path))
    return {"edge": edge_scene(), "perspective": persp}


def param_strategy(spec):
    """Edges of the box often, else uniform, else log-uniform for scale parameters."""
    lo, hi = spec.lower, spec.upper
    one = st.one_of(st.sampled_from([lo, hi]), st.floats(lo, hi))
    if lo > 0:
        one = st.one_of(one, st.floats(np.log(lo), np.log(hi)).map(
            lambda t: float(np.clip(np.exp(t), lo, hi))))
    if spec.size == 1:
        return one
    return st.lists(one, min_size=spec.size, max_size=spec.size)


def params_strategy(material):
    return st.fixed_dictionaries({k: param_strategy(s) for k, s in material.param_specs().items()})


@functools.lru_cache(maxsize=None)
def _value_and_grad(scene_name, material_name, scene):
    renderer = fitter.Renderer(scene, MATERIALS[material_name])
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (renderer.n_active, 3)))
    return jax.jit(jax.value_and_grad(lambda p: jnp.sum(renderer.active(p) * weights)))


def _check_finite(fn, params):
    p = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in params.items()}
    value, grad = fn(p)
    assert np.isfinite(float(value)), params
    bad = [k for k, g in grad.items() if not np.all(np.isfinite(np.asarray(g)))]
    assert not bad, f"non-finite gradient for {bad} at {params}"


@pytest.mark.parametrize("scene_name", ["edge", "perspective"])
@pytest.mark.parametrize("material_name", list(MATERIALS))
def test_render_value_and_gradient_finite(scenes, scene_name, material_name):
    fn = _value_and_grad(scene_name, material_name, scenes[scene_name])
    specs = MATERIALS[material_name].param_specs()
    # The box corners first (deterministic), then hypothesis.
    for corner in ("lower", "upper"):
        _check_finite(fn, {k: getattr(s, corner) * np.ones(s.shape) for k, s in specs.items()})

    @settings(max_examples=RENDER_EXAMPLES)
    @given(params_strategy(MATERIALS[material_name]))
    def check(params):
        _check_finite(fn, params)

    check()


# --- the lobe functions on their own -------------------------------------------

def unit_from_cos(c, phi):
    """Unit vector with z = c exactly (c = 0: in the tangent plane, c = 1: the normal)."""
    s = np.sqrt(max(0.0, 1.0 - c * c))
    return np.array([s * np.cos(phi), s * np.sin(phi), c])


#: Smallest non-zero |cos| drawn (exact 0 is drawn too). Below ~1e-154 the
#: product cos_i cos_o underflows to 0 and the Torrance-Sparrow value
#: D G F / (pi cos_i cos_o), which truly grows without bound as both
#: cosines -> 0 (retro-grazing pairs), overflows. Camera/light geometry never
#: yields such cosines except exactly 0.
MIN_COS = 1e-150
COS = st.one_of(st.sampled_from([0.0, 1.0, -0.0, MIN_COS, 1e-12, 1.0 - 1e-16, -1.0]),
                st.floats(-1.0, 1.0).filter(lambda c: c == 0.0 or abs(c) >= MIN_COS))
PHI = st.one_of(st.sampled_from([0.0, np.pi]), st.floats(0.0, 2 * np.pi))


@st.composite
def direction_pairs(draw, n=6):
    """Directions about n = +z, with degenerate pairs: wo = wi, wo = -wi, mirror."""
    wi, wo = [], []
    for _ in range(n):
        a = unit_from_cos(draw(COS), draw(PHI))
        kind = draw(st.sampled_from(["free", "same", "opposite", "mirror"]))
        if kind == "free":
            b = unit_from_cos(draw(COS), draw(PHI))
        else:
            b = {"same": a, "opposite": -a, "mirror": a * np.array([-1.0, -1.0, 1.0])}[kind]
        wi.append(a)
        wo.append(b)
    return np.array(wi), np.array(wo)


BRDF_VARIANTS = [(name, opts) for name, lobe in LOBES.items() if lobe.kind == "brdf"
                 for opts in ([{}] if not lobe.options else
                              [{o.name: c} for o in lobe.options for c in o.choices])]


@functools.lru_cache(maxsize=None)
def _eval_grad(name, opts_items):
    lobe, opts = LOBES[name], dict(opts_items)

    def total(p, wi, wo):
        n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), wi.shape)
        return jnp.sum(lobe.eval(p, opts, n, wi, wo))

    return jax.jit(jax.value_and_grad(total))


@pytest.mark.parametrize("name,opts", BRDF_VARIANTS,
                         ids=[f"{n}-{o}" for n, o in BRDF_VARIANTS])
def test_lobe_eval_gradient_finite(name, opts):
    lobe = LOBES[name]
    fn = _eval_grad(name, tuple(sorted(opts.items())))
    strategy = st.fixed_dictionaries({p.name: param_strategy(p) for p in lobe.params_for(opts)})

    @settings(max_examples=EVAL_EXAMPLES)
    @given(strategy, direction_pairs())
    def check(params, pairs):
        p = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in params.items()}
        value, grad = fn(p, jnp.asarray(pairs[0]), jnp.asarray(pairs[1]))
        assert np.isfinite(float(value)), (params, pairs)
        bad = [k for k, g in grad.items() if not np.all(np.isfinite(np.asarray(g)))]
        assert not bad, f"non-finite gradient for {bad} at {params}, {pairs}"

    check()


#: Agreement of a hand-written ``shape_grad`` with ``jax.jacfwd`` of ``shape``,
#: relative to the largest derivative of the draw (both are float64 closed forms
#: of the same function; they differ only by rounding).
SHAPE_GRAD_RTOL = 1e-9
#: Below this cosine (but not 0) autodiff of ``shape`` is itself rounding noise:
#: e.g. dF/deta ~ cos_i at grazing, which the unsimplified r_p, r_s of
#: ``fresnel_dielectric`` lose to cancellation, times 1/(cos_i cos_o) ~ 1e300.
#: Those pairs are checked for finiteness only.
COMPARE_MIN_COS = 1e-6

GRAD_VARIANTS = [(n, o) for n, o in BRDF_VARIANTS if LOBES[n].shape_grad is not None]


@functools.lru_cache(maxsize=None)
def _shape_grads(name, opts_items):
    lobe, opts = LOBES[name], dict(opts_items)
    names = [p.name for p in lobe.params_for(opts) if p.name != lobe.scale]

    def cos_of(wi, wo):
        n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), wi.shape)
        return fitter.bsdf.base.cosines(n, wi, wo)

    def by_hand(p, wi, wo):
        value, grads = lobe.shape_grad(p, opts, cos_of(wi, wo))
        return value, {k: jnp.broadcast_to(grads[k], value.shape) for k in names}

    def by_autodiff(p, wi, wo):
        c = cos_of(wi, wo)
        f = lambda q: lobe.shape({**p, **q}, opts, c)  # noqa: E731
        q = {k: p[k] for k in names}
        value, jac = f(q), jax.jacfwd(f)(q)
        # An RGB shape's derivative in an RGB parameter is diagonal (Lobe.shape_grad).
        return value, {k: (jnp.diagonal(j, axis1=-2, axis2=-1) if jnp.ndim(q[k]) else j)
                       for k, j in jac.items()}

    return jax.jit(by_hand), jax.jit(by_autodiff)


def test_every_shaped_lobe_with_parameters_has_shape_grad():
    """The renderer's fast Jacobian path covers every lecture BRDF with shape parameters."""
    missing = [n for n, lobe in LOBES.items() if lobe.kind == "brdf"
               and any(p.name != lobe.scale for p in lobe.params) and lobe.shape_grad is None]
    assert not missing


@pytest.mark.parametrize("name,opts", GRAD_VARIANTS, ids=[f"{n}-{o}" for n, o in GRAD_VARIANTS])
def test_shape_grad_matches_autodiff(name, opts):
    lobe = LOBES[name]
    by_hand, by_autodiff = _shape_grads(name, tuple(sorted(opts.items())))
    strategy = st.fixed_dictionaries({p.name: param_strategy(p) for p in lobe.params_for(opts)})

    @settings(max_examples=EVAL_EXAMPLES)
    @given(strategy, direction_pairs())
    def check(params, pairs):
        p = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in params.items()}
        wi, wo = jnp.asarray(pairs[0]), jnp.asarray(pairs[1])
        v1, g1 = by_hand(p, wi, wo)
        v2, g2 = by_autodiff(p, wi, wo)
        c = fitter.bsdf.base.cosines(np.array([0.0, 0.0, 1.0]), pairs[0], pairs[1])
        tiny = [(np.abs(x) > 0) & (np.abs(x) < COMPARE_MIN_COS) for x in (c.cos_i, c.cos_o,
                                                                       c.cos_d, c.cos_h)]
        keep = ~np.logical_or.reduce(tiny)
        np.testing.assert_allclose(np.asarray(v1)[keep], np.asarray(v2)[keep], rtol=1e-12, atol=0)
        for k in g1:
            a, b = np.asarray(g1[k]), np.asarray(g2[k])
            assert np.all(np.isfinite(a)), (k, params, pairs)
            a, b = a[keep], b[keep]
            scale = max(np.abs(b).max(initial=0.0), np.abs(a).max(initial=0.0), 1e-300)
            np.testing.assert_allclose(a, b, rtol=0, atol=SHAPE_GRAD_RTOL * scale,
                                       err_msg=f"d shape / d {k} at {params}")

    check()


UNIFORM_LOBES = [n for n, lobe in LOBES.items() if lobe.uniform is not None]


@pytest.mark.parametrize("name", UNIFORM_LOBES)
def test_a_uniform_part_and_its_kernel_add_up_to_the_shape(name):
    """shape = uniform + kernel_factor x kernel (``Lobe.uniform``: the sky lights the
    parts through sums over the map), the kernel reads cos_i, cos_o and cos_io only
    (``irradiance.kernel_sums`` forms no other field), and the kernel's part vanishes
    where the lecture says the lobe is uniform: Lambert has none, Oren-Nayar's B is 0
    at sigma = 0."""
    lobe = LOBES[name]
    assert UNIFORM_LOBES == ["lambert", "oren_nayar"]
    strategy = st.fixed_dictionaries({p.name: param_strategy(p) for p in lobe.params})
    n = np.array([0.0, 0.0, 1.0])

    @settings(max_examples=EVAL_EXAMPLES)
    @given(strategy, direction_pairs())
    def check(params, pairs):
        p = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in params.items()}
        c = fitter.bsdf.base.cosines(np.broadcast_to(n, pairs[0].shape), *pairs)
        rest = 0.0 if lobe.kernel is None else lobe.kernel_factor(p, {}) * lobe.kernel(c)
        np.testing.assert_allclose(lobe.uniform(p, {}) + rest, lobe.shape(p, {}, c),
                                   rtol=1e-14, atol=1e-16)
        if lobe.kernel is not None:
            assert np.all(np.isfinite(lobe.kernel(c)))
            three = type(c)(c.cos_i, c.cos_o, c.cos_io, *(None,) * (len(c) - 3))
            np.testing.assert_array_equal(lobe.kernel(three), lobe.kernel(c))
            assert lobe.kernel_factor({**p, "sigma": jnp.asarray(0.0)}, {}) == 0.0

    check()


@pytest.mark.parametrize("fresnel", ["dielectric", "conductor"])
@pytest.mark.parametrize("geometry", ["v_groove", "smith"])
def test_torrance_sparrow_gradient_finite_at_retro_grazing(fresnel, geometry):
    # Found by hypothesis: light and view 1e-150 above opposite horizons, m = 1e-3,
    # made the value ~2e305 and its m-derivative overflow to NaN.
    opts = {"fresnel": fresnel, "geometry": geometry}
    params = {p.name: (0.001 if p.name == "m" else p.lower) for p in
              LOBES["torrance_sparrow"].params_for(opts)}
    params["rho_s"] = 1.0
    pairs = (np.array([[1.0, 0.0, 1e-150]]), np.array([[-1.0, 0.0, 1e-150]]))
    fn = _eval_grad("torrance_sparrow", tuple(sorted(opts.items())))
    p = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in params.items()}
    value, grad = fn(p, jnp.asarray(pairs[0]), jnp.asarray(pairs[1]))
    assert np.isfinite(float(value))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grad.values()), grad

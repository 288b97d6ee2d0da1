"""The JAX forward model and Mitsuba 3 render the same physics.

For each lobe alone (and a sum, and the dielectric), the same 64 x 64 scene is
rendered by ``fitter.render`` (16 x 16 midpoint sub-pixel samples) and by
``fitter.mitsuba.render`` (stratified, two seeds). Reference: the Mitsuba
render; the expected difference is its Monte Carlo error, estimated from the
two seeds.

* Interior pixels (every sub-pixel sample on the sphere): a per-pixel
  Student-t test of the mean of the two Mitsuba renders against the model.
  The noise variance is pooled over 5 x 5 pixels from the seed difference
  (about 25 degrees of freedom); the critical value is Sidak-corrected for
  the number of pixels at family-wise error ALPHA. Plus the mean relative
  difference over the interior < MEAN_REL_TOL.
* Silhouette pixels: the model's k x k midpoint rule misclassifies at most
  the ~2k sub-cells an edge crosses, so |difference| <= 2/k of the image peak
  per pixel (and within SIL_PEAK_TOL, the measured level with a margin), and the
  silhouette's total flux agrees within SIL_FLUX_TOL.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats
from scipy.ndimage import uniform_filter

import fitter
import fitter.mitsuba as fm
from fitter.mitsuba.synth import make_envmap

pytestmark = pytest.mark.mitsuba

K = 16  # model sub-pixel samples per axis
SIZE = 64
ALPHA = 1e-3  # family-wise false-alarm rate of the per-pixel test
POOL = 5  # pixels per side over which the noise variance is pooled
POOL_DOF = 25
#: Interior mean relative difference. Measured (64^2, 1024-4096 spp, seeds 1+2):
#: 1.3e-6 (mirror) to 1.43e-4 (Phong); the bound keeps a margin of 2 over the
#: worst (the renders are deterministic per seed; the margin is for versions).
MEAN_REL_TOL = 3e-4
#: Silhouette total flux relative difference. Measured: 1.2e-4 (mirror) to
#: 7.8e-3 (Torrance-Sparrow V-groove at a grazing light): the 16^2 midpoint
#: rule's coverage error; bound 1e-2 (margin 1.3).
SIL_FLUX_TOL = 0.01
#: Largest silhouette pixel difference / image peak. The midpoint rule's bound is
#: 2/k = 0.125; measured 1e-26 (Phong: dark rim) to 2.4e-2 (dielectric,
#: Lambert); bound 5e-2 (margin 2).
SIL_PEAK_TOL = 0.05
#: Floors on the per-pixel noise: Mitsuba renders in float32 (relative
#: rounding ~1e-7 per operation, ~1e-5 after a chain of them), so a pixel whose
#: Monte Carlo noise vanishes is still compared only up to this relative
#: precision; and cancellations such as cos(alpha) = 2 ci co - wi.wo are
#: absolute (~1e-7), which FLOAT32_ABS (times the image peak) covers where a
#: lobe's tail is ~1e-12.
FLOAT32_REL = 1e-4
FLOAT32_ABS = 1e-6

L2 = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
      fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0)))
#: A point light plus a directional light at grazing incidence on the right limb.
L_GRAZE = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
           fitter.DirectionalLight((-1.0, 0.0, 0.1), (2.0, 2.0, 2.0)))
BASE = fitter.Scene(width=SIZE, height=SIZE, supersampling=K, lights=L2)
ORTHO = fitter.Camera(type="orthographic", origin=(1.0, 1.5, 4.0), half_width=1.3)


@pytest.fixture(scope="module")
def envmap(tmp_path_factory):
    path = tmp_path_factory.mktemp("env") / "envmap.exr"
    make_envmap(str(path))
    return str(path)


CASES = {
    "lambert": (BASE, "lambert", {}, {"lambert.rho_d": [0.6, 0.4, 0.2]}, 1024),
    "oren_nayar_ortho_directional": (
        BASE.replace(camera=ORTHO, lights=L_GRAZE), "oren_nayar", {},
        {"oren_nayar.rho_d": [0.6, 0.5, 0.4], "oren_nayar.sigma": 0.6}, 1024),
    "phong": (BASE, "phong", {}, {"phong.rho_s": [0.5, 0.4, 0.3], "phong.e": 30.0}, 1024),
    "phong_normalized": (BASE, "phong", {"phong.normalized": True},
                         {"phong.rho_s": [0.5, 0.4, 0.3], "phong.e": 30.0}, 1024),
    "torrance_sparrow_smith": (
        BASE.replace(lights=L_GRAZE), "torrance_sparrow", {"torrance_sparrow.geometry": "smith"},
        {"torrance_sparrow.m": 0.25, "torrance_sparrow.eta": 1.5}, 1024),
    "torrance_sparrow_v_groove": (
        BASE.replace(lights=L_GRAZE), "torrance_sparrow", {"torrance_sparrow.geometry": "v_groove"},
        {"torrance_sparrow.m": 0.25, "torrance_sparrow.eta": 1.5}, 1024),
    "lambert+torrance_sparrow": (
        BASE, "lambert+torrance_sparrow", {},
        {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15}, 1024),
    # A sum with a delta lobe: the ``path`` integrator samples fitter_sum.
    "lambert+mirror_path": (BASE, "lambert+mirror", {},
                            {"lambert.rho_d": [0.6, 0.4, 0.2], "mirror.rho_m": 0.5}, 1024),
    "mirror_envmap": (BASE.replace(lights=()), "mirror", {}, {"mirror.rho_m": [0.9, 0.8, 0.7]},
                      1024),
    "dielectric_envmap": (BASE.replace(lights=()), "dielectric", {},
                          {"dielectric.eta": 1.5, "dielectric.attenuation": [0.9, 0.7, 0.5]},
                          4096),
}


def _pixel_classes(scene, material):
    r = fitter.Renderer(scene, material)
    frac = np.zeros(scene.width * scene.height)
    frac[r.pixel_index] = np.asarray(r.geometry.hit).mean(axis=1)
    frac = frac.reshape(scene.height, scene.width)
    return frac == 1.0, (frac > 0.0) & (frac < 1.0)


@pytest.mark.parametrize("name", list(CASES))
def test_model_matches_mitsuba(name, envmap):
    scene, lobes, options, params, spp = CASES[name]
    if scene.lights == ():
        scene = scene.replace(environment=fitter.Environment(type="envmap", file=envmap))
    material = fitter.Material.make(lobes, options)
    a1 = fm.render(scene, material, params, spp=spp, seed=1)
    a2 = fm.render(scene, material, params, spp=spp, seed=2)
    model = np.asarray(fitter.render(params, scene, material))
    interior, silhouette = _pixel_classes(scene, material)
    mitsuba = 0.5 * (a1 + a2)

    # Interior: per-pixel t-test against the pooled Monte Carlo noise.
    var_mean = np.maximum(uniform_filter(np.mean((a1 - a2) ** 2 / 2.0, axis=-1), POOL), 0.0) / 2.0
    lum = model.mean(axis=-1)
    peak = float(max(model.max(), mitsuba.max()))
    floor = (FLOAT32_REL * lum) ** 2 + (FLOAT32_ABS * peak) ** 2
    t = (mitsuba - model).mean(axis=-1) / np.sqrt(var_mean + floor)
    n = int(interior.sum())
    t_crit = stats.t.isf(0.5 * (1.0 - (1.0 - ALPHA) ** (1.0 / n)), POOL_DOF)
    worst = float(np.abs(t[interior]).max())
    assert worst < t_crit, f"{name}: interior |t| = {worst:.2f} >= {t_crit:.2f}"
    rel = abs(float((mitsuba - model)[interior].sum())) / float(model[interior].sum())
    assert rel < MEAN_REL_TOL, f"{name}: interior mean relative difference {rel:.2e}"

    # Silhouette: the midpoint rule's coverage error bound, and total flux.
    sil_err = float(np.abs(mitsuba - model)[silhouette].max())
    assert sil_err <= 2.0 / K * peak, f"{name}: silhouette error {sil_err:.3g} > 2/k peak"
    assert sil_err <= SIL_PEAK_TOL * peak, f"{name}: silhouette error {sil_err / peak:.3g} peak"
    sil_flux = float(model[silhouette].sum())
    if sil_flux > 1e-3 * float(model.sum()):
        sil_rel = abs(float((mitsuba - model)[silhouette].sum())) / sil_flux
        assert sil_rel < SIL_FLUX_TOL, f"{name}: silhouette flux differs by {sil_rel:.2e}"


def test_envmap_lookup_matches_mitsuba_emitter(envmap):
    """fitter.environment's lat-long mapping = Mitsuba's ``envmap`` (identity to_world).

    Reference: Mitsuba's emitter ``eval`` for 2000 random directions on the
    asymmetric procedural envmap; agreement to float32 rounding of the texels.
    """
    import drjit as dr
    import jax.numpy as jnp

    from fitter import environment
    from fitter.mitsuba import variant

    mi, _ = variant.load(None)
    emitter = mi.load_dict({"type": "scene", "env": {"type": "envmap", "filename": envmap}}
                           ).emitters()[0]
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.wi = mi.Vector3f(*(-d.T).astype(np.float32))  # eval looks along -wi
    theirs = np.array(emitter.eval(si), dtype=np.float64)
    theirs = theirs.reshape(len(d), 3) if theirs.shape == (len(d), 3) else theirs.T
    data = environment.load_environment(fitter.Environment(type="envmap", file=envmap))
    ours = np.asarray(environment.lookup("envmap", data, jnp.asarray(d)))
    np.testing.assert_allclose(ours, theirs, rtol=FLOAT32_REL, atol=FLOAT32_ABS * ours.max())

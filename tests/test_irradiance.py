"""A sky's irradiance and a lobe kernel's sums over its map (``fitter.irradiance``),
and the sky light they give Lambert and Oren-Nayar (``Lobe.uniform``, ``Lobe.kernel``).

References are closed forms of E(n) = int L(w) max(n . w, 0) dw (a constant sky:
pi L; a sky over the upper hemisphere only: pi L (1 + n_y) / 2; radiance linear in
the direction, a + b . w: pi a + 2 pi / 3 b . n) and, for a map of no closed form,
a brute-force quadrature of Mitsuba's bilinear map through ``environment.lookup``
(the JAX lookup the background uses, not the NumPy one the sum resamples with).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import fitter
from fitter import envlight
from fitter.environment import EnvData, lookup
from fitter.irradiance import irradiance, irradiance_grid
from fitter.render import render
from fitter.scene import Environment, Scene

#: The sum's relative error, measured against the brute-force quadrature on the
#: shipped probe's sky (400 random normals): at most 2.8e-4; a map's smooth parts
#: within ~5e-5.
SUM_RTOL = 5e-4
#: Oren-Nayar (sigma = 0.6) under the probe's sky against the brute-force integral,
#: at every 7th interior pixel of a 24^2 sphere: at most 7.0e-5 (rms 3.3e-5); its B
#: term through the sky stencil had been 2.8e-3, the whole lobe through it 7.2e-3.
OREN_NAYAR_RTOL = 3e-4
#: A sharp step (the horizon of a hemisphere sky) is bilinear over one row of the
#: map, which the closed form for a sharp step does not have: 257 rows, 1.4e-4 measured.
STEP_RTOL = 1e-3


def _normals(n=200, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _map(fn, h=65, w=128):
    """(h, w, 3) radiance ``fn(direction)`` at Mitsuba's texel nodes."""
    u = (np.arange(w) + 0.5) / w
    v = np.arange(h) / (h - 1)
    return fn(envlight.uv_to_dir(*np.meshgrid(u, v)))


def _grid(img):
    return irradiance_grid(envlight.Pyramid(img).levels)


def test_a_constant_sky_gives_pi_times_its_radiance():
    rad = np.array([0.5, 1.0, 2.0])
    got = irradiance(_grid(np.broadcast_to(rad, (4, 8, 3)).copy()), _normals())
    np.testing.assert_allclose(got, np.pi * rad * np.ones((200, 1)), rtol=1e-15)
    # and the sum itself: a map 1e-12 from constant in one texel takes the general path
    img = np.broadcast_to(rad, (65, 128, 3)).copy()
    img[-1, 0] *= 1.0 + 1e-12
    np.testing.assert_allclose(irradiance(_grid(img), _normals()),
                               np.pi * rad * np.ones((200, 1)), rtol=1e-4)


def test_a_sky_over_the_upper_hemisphere_gives_the_dome_formula():
    img = _map(lambda d: np.where(d[..., 1:2] > 1e-9, 1.0, np.where(
        np.abs(d[..., 1:2]) <= 1e-9, 0.5, 0.0)) * np.ones(3), h=257, w=512)
    n = _normals()
    np.testing.assert_allclose(irradiance(_grid(img), n)[:, 0],
                               np.pi * (1.0 + n[:, 1]) / 2.0, rtol=STEP_RTOL, atol=1e-3)


def test_a_radiance_linear_in_the_direction_gives_its_closed_form():
    a, b = np.array([1.0, 1.5, 2.0]), np.array([[0.3, -0.2, 0.5], [0.1, 0.4, -0.3],
                                                [-0.5, 0.2, 0.1]])  # (channel, xyz)
    img = _map(lambda d: a + d @ b.T)
    n = _normals()
    np.testing.assert_allclose(irradiance(_grid(img), n), np.pi * a + 2 * np.pi / 3 * n @ b.T,
                               rtol=SUM_RTOL)


def _brute(img, n, rows=1024, cols=2048):
    """E at normals ``n`` by a midpoint quadrature over the sphere of the JAX lookup."""
    env = EnvData(jnp.asarray(img), jnp.zeros(3))
    th = np.pi * (np.arange(rows) + 0.5) / rows
    d = envlight.uv_to_dir(*np.meshgrid((np.arange(cols) + 0.5) / cols,
                                        (np.arange(rows) + 0.5) / rows)).reshape(-1, 3)
    dw = np.repeat(np.sin(th) * (np.pi / rows) * (2 * np.pi / cols), cols)
    rad = np.asarray(lookup("envmap", env, jnp.asarray(d))) * dw[:, None]
    return np.maximum(n @ d.T, 0.0) @ rad


@pytest.fixture(scope="module")
def probe_sky():
    from fitter.imageio import read_image
    from pathlib import Path

    img = read_image(str(Path(__file__).parents[1] / "data_synthetic" / "probe.exr"))
    return envlight.env_lights("envmap", np.asarray(img, np.float64)[..., :3], np.zeros(3)).sky


def test_the_probes_sky_matches_a_brute_force_quadrature(probe_sky):
    n = _normals(60, seed=1)
    np.testing.assert_allclose(irradiance(irradiance_grid(probe_sky.levels), n),
                               _brute(probe_sky.levels[0], n), rtol=SUM_RTOL)


def _interior(scene):
    """(flat pixel indices, centre normals, directions to the camera) of pixels far
    inside the sphere's disc, whose sky term is their centre sample's."""
    from fitter.camera import camera_rays
    from fitter.geometry import intersect_sphere

    o, d = camera_rays(scene.replace(supersampling=1, pixel_rule="midpoint"))
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t = intersect_sphere(o, d, np.zeros(3), 1.0)
    ok = np.isfinite(t)
    n = o + np.where(ok, t, 0.0)[:, None] * d
    inner = ok & (-np.sum(n * d, -1) > 0.6)
    pick = np.nonzero(inner)[0][::7]
    return pick, n[pick], -d[pick]


def test_lamberts_sky_term_is_its_albedo_over_pi_times_the_irradiance(tmp_path, probe_sky):
    # The renderer's Lambert under the probe's sky (no sun: a map without one) against
    # rho / pi x the brute-force irradiance at the pixel centres' normals.
    from fitter.imageio import write_image

    write_image(str(tmp_path / "sky.exr"), np.asarray(probe_sky.levels[0], np.float32))
    scene = Scene(width=24, height=24, supersampling=1,
                  environment=Environment(type="envmap", file=str(tmp_path / "sky.exr")))
    rho = np.array([0.6, 0.4, 0.2])
    img = np.asarray(render({"lambert.rho_d": rho}, scene)).reshape(-1, 3)
    pick, n, _ = _interior(scene)
    sky32 = np.asarray(probe_sky.levels[0], np.float32).astype(np.float64)
    np.testing.assert_allclose(img[pick], rho / np.pi * _brute(sky32, n), rtol=SUM_RTOL)


def _oren_nayar(sigma):
    """The qualitative Oren-Nayar BRDF / rho from its angles (Oren & Nayar 1994, eq. 30)."""
    s2 = sigma * sigma
    a, b = 1 - s2 / (2 * (s2 + 0.33)), 0.45 * s2 / (s2 + 0.09)

    def f(wi, wo, n):
        ti, to = np.arccos(np.clip(wi @ n, -1, 1)), np.arccos(np.clip(wo @ n, -1, 1))
        pi_, po = wi - (wi @ n)[:, None] * n, wo - (wo @ n) * n
        den = np.linalg.norm(pi_, axis=-1) * np.linalg.norm(po)
        cdphi = np.where(den > 1e-12, pi_ @ po / np.maximum(den, 1e-300), 0.0)
        al, be = np.maximum(ti, to), np.minimum(ti, to)
        return (a + b * np.maximum(cdphi, 0.0) * np.sin(al) * np.tan(be)) / np.pi
    return f


def test_oren_nayars_sky_term_matches_a_brute_force_integral(tmp_path, probe_sky):
    # A/pi lit by the summed irradiance, B/pi by the sum of its angular term per sample
    # (``irradiance.kernel_sums``): within OREN_NAYAR_RTOL of a brute-force integral of
    # the BRDF written from its angles over the sky's bilinear map.
    from fitter.imageio import write_image

    write_image(str(tmp_path / "sky.exr"), np.asarray(probe_sky.levels[0], np.float32))
    scene = Scene(width=24, height=24, supersampling=1,
                  environment=Environment(type="envmap", file=str(tmp_path / "sky.exr")))
    sigma = 0.6
    img = np.asarray(render({"oren_nayar.rho_d": [1.0, 1.0, 1.0], "oren_nayar.sigma": sigma},
                            scene)).reshape(-1, 3)
    pick, normals, views = _interior(scene)
    sky32 = np.asarray(probe_sky.levels[0], np.float32).astype(np.float64)
    env = EnvData(jnp.asarray(sky32), jnp.zeros(3))
    rows, cols = 512, 1024
    th = np.pi * (np.arange(rows) + 0.5) / rows
    d = envlight.uv_to_dir(*np.meshgrid((np.arange(cols) + 0.5) / cols,
                                        (np.arange(rows) + 0.5) / rows)).reshape(-1, 3)
    dw = np.repeat(np.sin(th) * (np.pi / rows) * (2 * np.pi / cols), cols)
    rad = np.asarray(lookup("envmap", env, jnp.asarray(d))) * dw[:, None]
    f = _oren_nayar(sigma)
    for p, n, wo in zip(pick[::3], normals[::3], views[::3]):
        up = d @ n > 0
        ref = (f(d[up], wo, n) * (d[up] @ n)) @ rad[up]
        np.testing.assert_allclose(img[p], ref, rtol=OREN_NAYAR_RTOL)


def test_a_lobe_the_stencil_does_not_sum_gets_no_sky_table(tmp_path, probe_sky):
    """Lambert and Oren-Nayar alone need the sky's sums over the map only: their
    renderer's geometry is sky-lit without the stencil's table (the table is most of
    a first env fit's set-up), a Torrance-Sparrow material's has one; a point-lit
    scene has neither. The sums give the same Lambert image either way."""
    from fitter.imageio import write_image
    from fitter.render import cached_renderer

    write_image(str(tmp_path / "sky.exr"), np.asarray(probe_sky.levels[0], np.float32))
    lit = Scene(width=16, height=16, supersampling=2,
                environment=Environment(type="envmap", file=str(tmp_path / "sky.exr")))
    geo = {name: cached_renderer(scene, fitter.Material.make(name), jnp.dtype(jnp.float64),
                                 None).geometry
           for name, scene in (("lambert", lit), ("oren_nayar", lit),
                               ("lambert+torrance_sparrow", lit),
                               ("phong", Scene(width=16, height=16)))}
    for name in ("lambert", "oren_nayar"):
        assert geo[name].sky_lit and not geo[name].has_sky
    assert set(geo["oren_nayar"].env_kernels) == {"oren_nayar"}
    assert geo["lambert+torrance_sparrow"].sky_lit and geo["lambert+torrance_sparrow"].has_sky
    assert not geo["phong"].sky_lit and not geo["phong"].has_sky
    rho = {"lambert.rho_d": [0.6, 0.4, 0.2]}
    np.testing.assert_allclose(
        np.asarray(render(rho, lit)),
        np.asarray(render({**rho, "torrance_sparrow.rho_s": 0.0}, lit,
                          fitter.Material.make("lambert+torrance_sparrow"))), rtol=1e-12)


def test_the_stated_errors_sky_parts_are_multiplied_on_the_host(tmp_path, probe_sky, caplog):
    """``_sky.summed_parts`` (the stated errors' uniform and kernel parts) takes the
    geometry's device sums to the host before multiplying: no eager kernel is
    compiled (one was, on a first fit's main thread, per product), and the parts add
    up to the renderer's own sky term of the lobe, a sky-lit render without lights."""
    import jax

    from fitter.fit import _sky
    from fitter.imageio import write_image
    from fitter.material import Material
    from fitter.render import cached_renderer, render_active

    write_image(str(tmp_path / "sky.exr"), np.asarray(probe_sky.levels[0], np.float32))
    scene = Scene(width=16, height=16, supersampling=2, lights=(),
                  environment=Environment(type="envmap", file=str(tmp_path / "sky.exr")))
    mat = Material.make("oren_nayar")
    r = cached_renderer(scene, mat, jnp.dtype(jnp.float64), None)
    params = mat.full_params({"oren_nayar.rho_d": [0.5, 0.4, 0.3], "oren_nayar.sigma": 0.4})
    host = {k: np.asarray(v, np.float64) for k, v in params.items()}
    with jax.log_compiles(True), caplog.at_level("DEBUG"):
        uniform, kernel = _sky.summed_parts(r.geometry, host, mat, mat.lobe_objects[0])
    assert not [rec for rec in caplog.records if "Compiling" in rec.getMessage()]
    assert isinstance(uniform, np.ndarray) and isinstance(kernel, np.ndarray)
    assert np.all(kernel > 0)
    own = render_active(r.params(params), _sky.dark(r.geometry), r.env, r.sphere,
                        material=mat, env_type=r.env_type)
    np.testing.assert_allclose(uniform + kernel, np.asarray(own), rtol=1e-12)


def test_kernel_sums_compile_their_sum_alone(probe_sky, caplog):
    """``irradiance.kernel_sums`` puts its host arrays on the device without a copy
    kernel per shape (``jnp.asarray`` compiled three on a first Oren-Nayar sky fit):
    on shapes seen for the first time it compiles its chunked sum only."""
    import jax

    from fitter.bsdf import oren_nayar
    from fitter.irradiance import kernel_sums

    n = _normals(37, seed=5)
    view = _normals(37, seed=6)
    view = np.where(np.sum(n * view, -1, keepdims=True) < 0, -view, view)
    jax.clear_caches()  # (shapes other tests may have compiled for: all first seen here)
    with jax.log_compiles(True), caplog.at_level("DEBUG"):
        out = kernel_sums(probe_sky.levels, oren_nayar._term, np.arange(37) % 5, n, view,
                          np.ones(37), 5)
    compiled = [rec.getMessage().split()[1] for rec in caplog.records
                if rec.getMessage().startswith("Compiling")]
    assert compiled == ["jit(run)"], compiled
    assert out.shape == (5, 3) and np.all(out > 0)


def test_an_oren_nayar_fit_under_a_sky_needs_no_stencil(tmp_path, probe_sky, finer_builds):
    """Its stated errors take the sums' accuracy (no half-ring stencil geometry is
    built for a ring error it has not), and the model's own render (noise 1e-3) is
    recovered within 3 stated errors."""
    from fitter.imageio import write_image

    write_image(str(tmp_path / "sky.exr"), np.asarray(probe_sky.levels[0], np.float32))
    scene = Scene(width=24, height=24, supersampling=2, lights=(),
                  environment=Environment(type="envmap", file=str(tmp_path / "sky.exr")))
    truth = {"oren_nayar.rho_d": [0.5, 0.4, 0.3], "oren_nayar.sigma": 0.4}
    clean = np.asarray(render(truth, scene))
    target = clean + np.random.default_rng(0).normal(0.0, 1e-3, clean.shape)
    res = fitter.fit(target, scene, "oren_nayar")
    assert res.status == "converged", res.message
    assert len(finer_builds) == 1  # the finer pixel sampling's only: no sun, no half rings
    for key, t in truth.items():
        err = np.abs(np.asarray(res.params[key]) - np.asarray(t))
        assert np.all(err <= 3 * np.asarray(res.stderr[key])), (key, err, res.stderr[key])


def test_oren_nayar_under_a_constant_sky_matches_its_brute_force_albedo():
    """A constant sky's map is 2 x 4 texels: its kernel sum is taken over nodes of at
    least ``KERNEL_ROWS`` x ``KERNEL_COLUMNS`` on that (constant) surface, within
    OREN_NAYAR_RTOL of a brute-force integral of the BRDF from its angles (the
    texels alone as nodes: 7 % rms, 11 % at most)."""
    scene = Scene(width=24, height=24, supersampling=1,
                  environment=Environment(type="constant", radiance=(1.0, 0.5, 0.25)))
    sigma = 0.6
    img = np.asarray(render({"oren_nayar.rho_d": [1.0, 1.0, 1.0], "oren_nayar.sigma": sigma},
                            scene)).reshape(-1, 3)
    pick, normals, views = _interior(scene)
    rows, cols = 512, 1024
    th = np.pi * (np.arange(rows) + 0.5) / rows
    d = envlight.uv_to_dir(*np.meshgrid((np.arange(cols) + 0.5) / cols,
                                        (np.arange(rows) + 0.5) / rows)).reshape(-1, 3)
    dw = np.repeat(np.sin(th) * (np.pi / rows) * (2 * np.pi / cols), cols)
    f = _oren_nayar(sigma)
    for p, n, wo in zip(pick[::3], normals[::3], views[::3]):
        up = d @ n > 0
        albedo = np.sum(f(d[up], wo, n) * (d[up] @ n) * dw[up])
        np.testing.assert_allclose(img[p], albedo * np.array([1.0, 0.5, 0.25]),
                                   rtol=OREN_NAYAR_RTOL)

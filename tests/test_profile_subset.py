"""The post-fit cost profile on a pixel subset (``fitter.fit._profile``).

References: for linear residuals, the closed form 0.5 |r + J dz|^2 (the
subset's estimate must equal it to round-off); on fits, the same profile
evaluated on every pixel (``_compile.costs_at``, the code the subset replaces).
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from scipy.special import chdtri

import fitter
from fitter.fit import _compile, _drivers, _identify, _profile
from fitter.fit._covariance import residual_variance
from fitter.fit._problem import single_coordinates

LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
          fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0)))


def test_estimate_is_exact_for_linear_residuals():
    """Residuals linear in z: the remainder is zero on every pixel, so the
    subset's estimated rise is the whole image's and its error estimate 0,
    whichever pixels the subset holds."""
    rng = np.random.default_rng(1)
    P, n, k = 400, 4, 12
    J, r = rng.normal(size=(3 * P, n)), rng.normal(size=3 * P)
    dzs = rng.normal(size=(k, n)) * np.array([0.1, 1.0, 3.0, 10.0])
    labels = np.where(rng.random(P) < 0.1, 1, 0)
    rows, weight = _profile.subset_rows(labels, stride=8)
    assert len(rows) < P // 2
    full = r[None] + dzs @ J.T  # (k, 3P): the residuals at each point
    idx = (3 * rows[:, None] + np.arange(3)).reshape(-1)
    rise, se = _profile.estimated_rises(J, r, dzs, full[:, idx], rows, weight, s2=0.7)
    exact = (np.sum(full * full, axis=1) - r @ r) / 0.7
    np.testing.assert_allclose(rise, exact, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(se, 0.0, atol=1e-8 * np.abs(exact).max())


def test_strides_weight_each_pick_by_its_stratum():
    """Every 16th body, 2nd highlight and 4th rim pixel (labels 0, 1, 2), each
    standing for its stratum's pixels per pick; standing-out pixels (3) stay
    whole. Reference: each stratum's pixel count (a Horvitz-Thompson sum of
    1s) and the picks counted by hand."""
    labels = np.array([0] * 200 + [1] * 30 + [2] * 101 + [3] * 5)
    rows, weight = _profile.subset_rows(labels, stride=16, highlight_stride=2, rim_stride=4)
    lab = labels[rows]
    for stratum, count, picked in ((0, 200, 13), (1, 30, 15), (2, 101, 26), (3, 5, 5)):
        real = (lab == stratum) & (weight > 0)
        assert real.sum() == picked, stratum
        np.testing.assert_allclose(weight[real].sum(), count, rtol=1e-12)
    np.testing.assert_array_equal(rows[(lab == 2) & (weight > 0)],
                                  np.arange(230, 331)[::4])


def test_a_body_pixel_standing_out_is_whole(monkeypatch):
    """A body pixel whose linear response is far above the mean (``STAND_OUT``)
    is stratum 3, taken whole; highlight and rim pixels keep their region
    (strided) whether they stand out or not. Reference: responses set by hand."""
    from fitter.fit import _adequacy

    regions = np.array([0, 0, 1, 1, 2, 2] * 10)
    monkeypatch.setattr(_adequacy, "pixel_regions", lambda geometry: regions)
    J = np.zeros((3 * regions.size, 1))
    J[::3] = 1.0
    J[3 * np.array([0, 2, 4]), 0] = 100.0  # one pixel of each region stands out
    labels = _profile.strata(None, J, np.ones((2, 1)))
    np.testing.assert_array_equal(labels[:6], [3, 0, 1, 1, 2, 2])
    np.testing.assert_array_equal(labels[6:], regions[6:])


def _profile_inputs(monkeypatch, eta: float):
    """Fit a 64^2 lambert + torrance_sparrow sphere (eta given) with the subset
    forced on; return the fit and the profile's inputs at its first solution,
    with the solver's Jacobian remembered as the drivers leave it."""
    monkeypatch.setattr(_profile, "MIN_PIXELS", 0)
    scene = fitter.Scene(width=64, height=64, supersampling=2, lights=LIGHTS)
    mat = fitter.Material.make("lambert+torrance_sparrow", {"torrance_sparrow.geometry": "smith"})
    truth = {"lambert.rho_d": [0.5] * 3, "torrance_sparrow.m": 0.2, "torrance_sparrow.eta": eta}
    clean = np.asarray(fitter.render(truth, scene, mat))
    target = clean + np.random.default_rng(0).normal(0.0, 0.01 * clean.mean(), clean.shape)
    seen = []
    real = _drivers.weak_profile

    def spy(*args, **kw):
        spec, data, z = args[:3]
        J, r, _ = _compile.jac_full(spec, z, data)
        _compile.remember_jacobian(spec, z, data, J, r)
        seen.append((args, J))
        return real(*args, **kw)

    monkeypatch.setattr(_drivers, "weak_profile", spy)
    res = fitter.fit(target, scene, mat)
    assert seen, res.message
    return res, seen[0]


@pytest.mark.parametrize("eta", [1.001, 1.5])
def test_subset_verdict_equals_every_pixels(monkeypatch, eta):
    """eta = 1.001 (m has no effect: a flat valley, ``test_fit_identifiability``)
    triggers the re-solve, eta = 1.5 does not; the subset (a third of the
    pixels here) gives the verdict the whole image gives, and on the smooth
    case chi^2 rises within 2 % (+ 0.5) of the whole image's."""
    res, ((spec, data, z, R, r, sigma), J) = _profile_inputs(monkeypatch, eta)
    s2 = residual_variance(sigma, data, r, spec)
    cost = 0.5 * float(r @ r)
    points = _identify.profile_points(spec, z, R, s2)
    zs = np.stack([zt for _, zt in points])
    whole = _compile.costs_at(spec, zs, data)
    picks = _profile.subset_rows(_profile.strata(data.geometry, J, zs - z))
    assert picks is not None and len(picks[0]) < 0.5 * np.shape(data.target)[0]
    level = chdtri(1, 0.05)  # the 95 % quantile of chi^2 with 1 dof
    sub = _profile.subset_costs(spec, data, z, J, r, s2, cost, points, level,
                                _identify.PROFILE_FLAT)
    assert sub is not None
    verdict = lambda c: _identify.profile_verdict(
        s2, cost, [(t, zt, float(ci)) for (t, zt), ci in zip(points, c)])[0]
    why_whole, why_sub = verdict(whole), verdict(sub)
    assert (why_whole is None) == (why_sub is None), (why_whole, why_sub)
    if eta < 1.01:
        assert "flat valley" in why_whole and "flat valley" in why_sub
        assert "torrance_sparrow.m" in res.unidentifiable, (res.params, res.stderr)
    else:
        assert why_whole is None and len(res.starts) == 1
        rise_whole, rise_sub = 2 * (whole - cost) / s2, 2 * (sub - cost) / s2
        np.testing.assert_allclose(rise_sub, rise_whole, rtol=0.02, atol=0.5)


def test_newton_step_is_the_least_squares_step():
    """Reference: NumPy's least squares on the whole Jacobian, min |r + J dz|."""
    rng = np.random.default_rng(2)
    J, r = rng.normal(size=(300, 4)) * [1.0, 1e-3, 10.0, 0.5], rng.normal(size=300)
    R = np.linalg.qr(J, mode="r")
    np.testing.assert_allclose(_identify.newton_step(R, J.T @ r),
                               np.linalg.lstsq(J, -r, rcond=None)[0], rtol=1e-10)
    assert np.all(_identify.newton_step(R, np.full(4, np.nan)) == 0.0)


@pytest.mark.parametrize("res, profiled, atol", [(32, [False], None), (64, [], 1e-8),
                                                 (64, [True], None)])
def test_noiseless_target_is_not_re_solved(monkeypatch, res, profiled, atol):
    """A target rendered by the model itself at the truth (no noise): the
    residuals at the solution are rounding (~1e-16), so a profile point's
    chi^2 rise against them says nothing. The fit must stay at its one start
    with no "weakly identified" note (it had re-solved from 6 starts, every
    point seeming to fall by chi^2 ~1e4), and recover the truth to 1e-9.

    32^2, the whole image's path (``profiled`` = [False]; residuals ~1e-12
    where the solver stopped): fails without the profile centred on the
    Gauss-Newton minimum (~40 stated errors away: rises -30 and +48 at -+3).
    64^2 with atol = 1e-8 (the solver goes on to residuals ~1e-16): the
    rounding estimate skips the profile (``rounding_rise``, ``profiled`` =
    []); with ``ROUNDING_ULPS`` = 0 the subset's points "fall" by chi^2 ~1e4
    and it fails. 64^2 with the default atol (1e-7: one step fewer, residuals
    ~1e-12): the subset's profile runs, centred on the Gauss-Newton minimum."""
    monkeypatch.setattr(_profile, "MIN_PIXELS", 0 if res == 64 else 10**9)
    used = []
    real = _profile.subset_costs

    def spy(*args, **kw):
        out = real(*args, **kw)
        used.append(out is not None)
        return out

    monkeypatch.setattr(_profile, "subset_costs", spy)
    scene = fitter.Scene(width=res, height=res, supersampling=2, lights=LIGHTS)
    mat = fitter.Material.make("lambert+torrance_sparrow", {"torrance_sparrow.geometry": "smith"})
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3], "torrance_sparrow.m": 0.2,
             "torrance_sparrow.eta": 1.5}
    target = np.asarray(fitter.render(truth, scene, mat))
    res_ = fitter.fit(target, scene, mat, init={"torrance_sparrow.m": 0.3,
                                                "torrance_sparrow.eta": 1.3},
                      **({} if atol is None else {"atol": atol}))
    assert used == profiled, used
    assert res_.status == "converged", res_.message
    assert len(res_.starts) == 1 and not res_.warnings, res_.warnings
    for k, v in truth.items():
        np.testing.assert_allclose(res_.params[k], v, rtol=1e-9, err_msg=k)


def test_rows_picked_in_the_executable_equal_the_host_subset():
    """The profile's residuals of a pixel subset picked inside the executable
    (``Geometry.take``) equal, bit for bit, those of the subset copied on the
    host (``Geometry.subset``, the reference); ``take`` refuses a geometry
    with env samples, whose rows only ``subset`` remaps."""
    import jax

    from fitter.fit import _setup

    scene = fitter.Scene(width=32, height=32, supersampling=2, lights=LIGHTS)
    mat = fitter.Material.make("lambert+torrance_sparrow", {"torrance_sparrow.geometry": "smith"})
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3], "torrance_sparrow.m": 0.2,
             "torrance_sparrow.eta": 1.5}
    target = np.asarray(fitter.render(truth, scene, mat))
    problem = _setup.Problem.make(target[None], scene, mat)
    data = problem.data(0)
    rows = np.arange(3, np.shape(data.target)[0], 7)
    zs = np.stack([problem.z_init(), problem.z_init() + 0.1])
    host = _compile.residuals_at_points(problem.spec, zs, _profile.subset_data(data, rows))
    inside = _compile.residuals_of_rows(problem.spec, zs, data, rows)
    assert host.shape == inside.shape == (2, 3 * len(rows))
    np.testing.assert_array_equal(inside, host)
    geo = jax.tree_util.tree_map(np.asarray, data.geometry)
    env = geo._replace(env_index=np.zeros(4, np.int64))
    with pytest.raises(ValueError, match="subset"):
        env.take(rows)


def test_under_a_sky_the_profile_is_compiled_ahead_and_states_the_same(tmp_path, monkeypatch):
    """Under a sky (env samples: the subset's evaluation is compiled for its own
    shapes) ``_profile.ahead`` picks the pixels the profile picks where none stands
    out, and compiles their evaluation on the compile-ahead thread while the solve
    runs: the profile then compiles nothing on the main thread, and the fit equals
    one whose profile made its subset in line."""
    from fitter.fit import _compile
    from fitter.imageio import write_image

    img = np.full((16, 32, 3), 0.3)
    img[5, 9] = [3000.0, 2900.0, 2500.0]  # a sun
    write_image(str(tmp_path / "sun.exr"), img)
    scene = fitter.Scene(width=96, height=96, supersampling=1, environment=fitter.Environment(
        type="envmap", file=str(tmp_path / "sun.exr")))
    truth = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
             "torrance_sparrow.eta": 1.5}
    clean = np.asarray(fitter.render(truth, scene))
    target = clean + np.random.default_rng(0).normal(0.0, 2e-3, clean.shape)
    built = []
    build = _compile._build

    def build_rec(kind, *args):
        built.append((kind, threading.current_thread().name))
        return build(kind, *args)

    monkeypatch.setattr(_compile, "_build", build_rec)
    monkeypatch.setattr(_compile, "_COMPILED", {})
    used = []
    made = _profile._made_ahead
    monkeypatch.setattr(_profile, "_made_ahead", lambda d, r: used.append(made(d, r)) or used[-1])
    first = fitter.fit(target, scene, "lambert+torrance_sparrow")
    assert first.status == "converged"
    assert used and used[0] is not None  # the profile ran on the subset made ahead
    assert ("residuals", threading.main_thread().name) not in built
    assert not _profile._AHEAD  # nothing kept after the fit

    monkeypatch.setattr(_profile, "ahead", lambda *a: None)
    used.clear()
    again = fitter.fit(target, scene, "lambert+torrance_sparrow")
    assert used == [None]  # made in line
    for part in ("params", "stderr", "stderr_sys", "stderr_disc"):
        for key in truth:
            np.testing.assert_array_equal(getattr(first, part)[key], getattr(again, part)[key])


def test_float32_error_measured_at_z_is_taken_off():
    """Linear residuals whose subset values carry a fixed error d per residual
    (float32's, the same at every point): measured at the centre (``centre``:
    the residuals at z + dz_c and dz_c) and taken off, the estimated rises are
    the closed form 0.5 |r + J dz|^2 again; the standard errors then hold only
    what may be left of d, so they are 0 without it and double with 2 d."""
    rng = np.random.default_rng(3)
    P, n, k = 300, 3, 9
    J, r = rng.normal(size=(3 * P, n)), rng.normal(size=3 * P)
    dzs = rng.normal(size=(k, n))
    rows, weight = _profile.subset_rows(np.where(rng.random(P) < 0.2, 1, 0), stride=4)
    idx = (3 * rows[:, None] + np.arange(3)).reshape(-1)
    full = r[None] + dzs @ J.T
    exact = (np.sum(full * full, axis=1) - r @ r) / 0.5
    dz_c = 1e-7 * rng.normal(size=n)  # the centre moved by its parameters' rounding
    d1, ses = 1e-6 * rng.normal(size=idx.size), []
    for scale in (0.0, 1.0, 2.0):
        d = scale * d1
        centre = (r[idx] + J[idx] @ dz_c + d, dz_c)
        rise, se = _profile.estimated_rises(J, r, dzs, full[:, idx] + d, rows, weight, 0.5,
                                            centre=centre)
        np.testing.assert_allclose(rise, exact, rtol=1e-9, atol=1e-9)
        ses.append(se)
    np.testing.assert_allclose(ses[0], 0.0, atol=1e-9 * np.abs(exact).max())
    assert np.all(ses[1] > 0)
    np.testing.assert_allclose(ses[2], 2.0 * ses[1], rtol=1e-6)


def test_single_coordinates_are_where_float32_puts_the_values():
    """Each point's coordinates moved so that its user values are the float32
    rounding of the original ones (reference: NumPy's float32 cast), to second
    order in the move (~1e-15 relative), for the logit, log and eta boxes."""
    from fitter import transforms
    from fitter.fit import _setup

    scene = fitter.Scene(width=16, height=16, supersampling=1, lights=LIGHTS)
    mat = fitter.Material.make("lambert+torrance_sparrow")
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3], "torrance_sparrow.m": 0.2,
             "torrance_sparrow.eta": 1.5}
    problem = _setup.Problem.make(np.asarray(fitter.render(truth, scene, mat))[None], scene, mat)
    spec = problem.spec
    zs = problem.z_init()[None] + np.random.default_rng(4).normal(0.0, 1.0, (5, spec.n))
    moved = single_coordinates(spec, zs)
    assert {b.transform for b in spec.blocks} >= {"logit", "log", "eta"}
    for b, sl in spec.slices():
        x = transforms.to_user(b.transform, zs[:, sl], b.lower, b.upper)
        x_moved = transforms.to_user(b.transform, moved[:, sl], b.lower, b.upper)
        np.testing.assert_allclose(x_moved, x.astype(np.float32).astype(np.float64),
                                   rtol=1e-14, atol=0, err_msg=b.key)
        assert np.any(x_moved != x)


@pytest.mark.parametrize("lobes, single", [("lambert+torrance_sparrow", True),
                                           ("lambert+phong", False)])
def test_subset_in_float32_only_for_single_precision_lobes(monkeypatch, lobes, single):
    """The subset's residuals are float32's for lobes with ``single_precision``
    (Torrance-Sparrow), float64's with Phong (whose cos^e float32 rounds by e
    times cos's error); either way the fit's profile states no re-solve on a
    smooth noisy target."""
    monkeypatch.setattr(_profile, "MIN_PIXELS", 0)
    seen = []
    real = _compile.residuals_of_rows
    def spy(*a, **k):
        seen.append(a[4] if len(a) > 4 else False)
        return real(*a, **k)

    monkeypatch.setattr(_compile, "residuals_of_rows", spy)
    scene = fitter.Scene(width=64, height=64, supersampling=2, lights=LIGHTS)
    mat = fitter.Material.make(lobes)
    truth = ({"lambert.rho_d": [0.5, 0.4, 0.3], "torrance_sparrow.m": 0.2}
             if "torrance" in lobes else {"lambert.rho_d": [0.5, 0.4, 0.3], "phong.e": 50.0})
    clean = np.asarray(fitter.render(truth, scene, mat))
    target = clean + np.random.default_rng(0).normal(0.0, 0.01 * clean.mean(), clean.shape)
    res = fitter.fit(target, scene, mat)
    assert res.status == "converged", res.message
    assert seen == [single], seen
    assert len(res.starts) == 1


def test_points_padded_to_whole_batches_are_each_points_residuals(monkeypatch):
    """7 points at 3 a batch are evaluated as 3 x 3 (the last padded: no second
    body for a remainder); each row equals that point evaluated alone
    (reference: ``residuals_at_points`` of one point)."""
    import jax

    from fitter.fit import _setup

    scene = fitter.Scene(width=24, height=24, supersampling=2, lights=LIGHTS)
    mat = fitter.Material.make("lambert+torrance_sparrow")
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3], "torrance_sparrow.m": 0.2}
    problem = _setup.Problem.make(np.asarray(fitter.render(truth, scene, mat))[None], scene, mat)
    data = problem.data(0)
    size = sum(np.size(a) for a in jax.tree_util.tree_leaves(data.geometry))
    monkeypatch.setattr(_compile, "MAP_BATCH_ELEMENTS", 3 * size + 1)
    zs = problem.z_init()[None] + np.linspace(-0.3, 0.3, 7)[:, None]
    batched = _compile.residuals_at_points(problem.spec, zs, data)
    assert batched.shape == (7, np.size(data.target))
    for z, row in zip(zs, batched):
        alone = _compile.residuals_at_points(problem.spec, z[None], data)[0]
        np.testing.assert_allclose(row, alone, rtol=1e-12, atol=1e-15)


def test_a_float32_fits_profile_rows_trace_without_64_bit_index_warnings():
    """The rows picked inside the profile's executable are int32: a float32 fit
    traces without 64-bit types, where int64 rows warned "truncated to dtype
    int32" on every first run (the shipped phong, dielectric, bright_phong and
    extreme_grazing cases in float32)."""
    import warnings

    import jax.numpy as jnp

    scene = fitter.Scene(width=96, height=96, supersampling=1, lights=LIGHTS)
    truth = {"phong.rho_s": [0.4, 0.4, 0.4], "phong.e": 50.0}
    target = np.asarray(fitter.render(truth, scene))
    target = target + np.random.default_rng(0).normal(0.0, 1e-3, target.shape)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*truncated to dtype int32.*")
        res = fitter.fit(target, scene, "phong", dtype=jnp.float32)
    assert res.status == "converged", res.message

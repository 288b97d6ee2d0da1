"""Honest answers on images the model did not make (issue 12).

* Stated errors = statistical (Gauss-Newton, the Cramer-Rao bound for white
  noise; the pixel sandwich where the noise differs over the pixels,
  ``tests/test_shot_noise.py``) + systematic (what spatially structured
  residuals add, from a spatial-block sandwich covariance): white residuals
  add nothing, block-wise structure does (White 1980; Conley 1999;
  ``fitter.fit._adequacy``).
* The verdict reads the residual by region and names the likely cause
  (model, exposure/light scale, start); the report's badges follow it.

The heavy mismatch cases (roughplastic, gold with a dielectric Fresnel,
sub-pixel highlight, eta near 1) are in ``benchmarks/honesty.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from skies import one_texel_sun

import fitter
from fitter.fit import _adequacy, _verdict
from fitter.report import fit_badge, mitsuba_badge

LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),)
SCENE = fitter.Scene(width=48, height=48, supersampling=2, lights=LIGHTS)
GLOSSY = {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
          "torrance_sparrow.eta": 1.5}
#: A fit of the model's own render (no noise, no model error) recovers its truth to this.
INVERSE_CRIME_RTOL = 1e-6


def test_sandwich_equals_gauss_newton_for_white_residuals_and_grows_with_structure():
    rng = np.random.default_rng(0)
    n_pix, n_blocks = 4096, 64
    ids = np.repeat(np.arange(n_blocks), n_pix // n_blocks)
    J = rng.normal(size=(3 * n_pix, 2)) + np.repeat(ids, 3)[:, None] * 0.01
    white = rng.normal(size=3 * n_pix)
    cov_stat = np.linalg.inv(J.T @ J) * np.mean(white**2)
    hac = _adequacy.sandwich(J, white, ids, n_blocks)
    ratio = np.diag(hac) / np.diag(cov_stat)
    assert np.all(np.abs(ratio - 1) < 3 * np.sqrt(2 / n_blocks)), ratio
    assert np.all(_adequacy.systematic(cov_stat, hac, n_blocks) == 0)
    # A residual constant within each block, shaped like J's first column:
    # every block pushes the parameters the same way its own size.
    shift = np.repeat(rng.normal(size=n_blocks), 3 * n_pix // n_blocks) * J[:, 0]
    structured = white + 0.5 * shift
    cov_stat2 = np.linalg.inv(J.T @ J) * np.mean(structured**2)
    hac2 = _adequacy.sandwich(J, structured, ids, n_blocks)
    sys2 = _adequacy.systematic(cov_stat2, hac2, n_blocks)
    assert hac2[0, 0] > 10 * cov_stat2[0, 0] and sys2[0, 0] > 0


def test_white_noise_target_has_no_systematic_part():
    truth = GLOSSY
    clean = np.asarray(fitter.render(truth, SCENE))
    target = clean + np.random.default_rng(1).normal(0.0, 0.01, clean.shape)
    r = fitter.fit(target, SCENE, "lambert+torrance_sparrow", noise_sigma=0.01)
    assert r.status == "converged", r.message
    for k, v in r.stderr.items():
        # No structured part: the systematic part is the discretisation's
        # alone (k = 2 vs 4 samples per axis), and small against the noise.
        np.testing.assert_allclose(r.stderr_sys[k], r.stderr_disc[k], rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(v, r.stderr_stat[k], rtol=0.02)
    assert abs(r.adequacy["neighbour_correlation"]) < 0.1
    assert set(r.adequacy["regions"]) == {"body", "highlight", "rim"}
    d = r.to_dict()
    assert set(d["stderr_stat"]) == set(d["stderr"]) == set(d["stderr_disc"])
    assert "adequacy" in d


def test_white_residual_with_a_large_discretisation_part_is_not_called_structured():
    # The model's own render with white noise 1e-4 (48^2, 2 x 2 samples): refined to
    # 4 x 4 the fit would move rho_d by ~11 statistical errors (stderr_disc), while
    # the residual is white (neighbour correlation ~0, no block excess). The warning
    # said "the residual is spatially structured (at the rim (0.64 times the noise
    # level ...))" and the report's badge "STRUCTURED RESIDUAL".
    clean = np.asarray(fitter.render(GLOSSY, SCENE))
    target = clean + np.random.default_rng(1).normal(0.0, 1e-4, clean.shape)
    r = fitter.fit(target, SCENE, "lambert+torrance_sparrow", noise_sigma=1e-4)
    assert r.status == "converged", r.message
    assert abs(r.adequacy["neighbour_correlation"]) < 0.1
    disc = max(np.max(np.asarray(r.stderr_disc[k]) / np.asarray(r.stderr_stat[k]))
               for k in r.stderr)
    assert disc > _adequacy.SYS_WARN  # the case the warning is for
    assert not any("spatially structured" in w for w in r.warnings), r.warnings
    assert [w for w in r.warnings if w.startswith("the stated errors are mostly the model's "
                                                  "own discretisation")], r.warnings
    assert fit_badge(r)[0] == "CONVERGED, ERRORS MOSTLY DISCRETISATION"


@pytest.mark.parametrize("structured,disc,expected", [
    (4.0, 1.0, "the residual is spatially structured"),
    (1.0, 4.0, "the stated errors are mostly the model's own discretisation"),
    (2.5, 2.5, "the residual is spatially structured"),  # each below 3, together above
    (2.0, 2.0, None),  # together 2.8: below SYS_WARN
])
def test_mostly_systematic_errors_name_their_larger_source(structured, disc, expected):
    # Two coordinates, statistical errors 1 and 2; the first carries the parts
    # (added in quadrature), the second none.
    stat = np.array([1.0, 2.0])
    sd_disc = np.array([disc, 0.0])
    sd_sys = np.hypot(np.array([structured, 0.0]), sd_disc)
    regions = {"rim": {"pixels": 10, "rmse_over_noise": 2.0, "energy_share": 0.5}}
    adequacy = {"regions": regions,  # (as ``_with_systematic`` leaves them)
                 "blocks": {"discretisation": {"supersampling": [2, 4]}}}
    text = _verdict._systematic_warning(adequacy, stat, sd_sys, sd_disc)
    if expected is None:
        assert text is None
    else:
        assert text.startswith(expected), text
        # the structure's total systematic part, or the discretisation's own
        said = np.hypot(structured, disc) if structured >= disc else disc
        assert f"up to {said:.3g} times" in text


def test_regions_follow_the_geometry():
    """Highlight pixels sit where n is near a light's half vector; rim pixels on
    the silhouette."""
    res = fitter.fit(np.asarray(fitter.render(GLOSSY, SCENE)), SCENE, "lambert+torrance_sparrow")
    regions = res.adequacy["regions"]
    assert regions["highlight"]["pixels"] > 0 and regions["rim"]["pixels"] > 0
    assert regions["body"]["pixels"] > regions["highlight"]["pixels"]


def test_block_ids_and_region_stats_equal_their_direct_definitions():
    """The sandwich's blocks: ids equal ``np.unique``'s inverse of the block keys
    (the definition); per-region statistics equal masked sums per region."""
    rng = np.random.default_rng(3)
    for width, n in ((256, 60000), (37, 500), (64, 1)):
        pix = np.sort(rng.choice(width * width, n, replace=False))
        ids, n_blocks = _adequacy.block_ids(pix, width)
        side = max(_adequacy.MIN_SIDE, int(round(np.sqrt(n / _adequacy.N_BLOCKS))))
        key = (pix // width // side) * (width // side + 1) + pix % width // side
        uniq, inverse = np.unique(key, return_inverse=True)
        assert np.array_equal(ids, inverse) and n_blocks == uniq.size
    r = rng.normal(size=(900, 3))
    weights = (rng.random((900, 3)) > 0.1).astype(float)
    labels = rng.integers(0, 3, 900)
    stats = _adequacy.region_stats(r, weights, labels, 0.5)
    e = np.where(weights > 0, r, 0.0) ** 2
    for k, name in enumerate(_adequacy.REGIONS):
        sel = labels == k
        assert stats[name]["pixels"] == sel.sum()
        np.testing.assert_allclose(stats[name]["rmse_over_noise"],
                                   np.sqrt(e[sel].sum() / (weights[sel] > 0).sum()) / 0.5,
                                   rtol=1e-12)
        np.testing.assert_allclose(stats[name]["energy_share"], e[sel].sum() / e.sum(),
                                   rtol=1e-12)


def test_wrong_model_with_agreeing_starts_blames_the_model():
    target = np.asarray(fitter.render(GLOSSY, SCENE.replace(supersampling=4)))
    r = fitter.fit(target, SCENE, "lambert", n_starts=2)
    assert r.status == "failed" and "poor fit" in r.message
    assert "not the start" in r.message and "cannot explain the image at the" in r.message
    assert fit_badge(r)[0].startswith("MODEL CANNOT EXPLAIN")


def test_clipped_highlight_is_named_and_its_saturation_level_recovers_the_truth():
    """A target whose highlight is clipped flat (a camera's white level) at 0.8 of
    its peak: a poor fit whose cause names the clipping and a saturation level;
    fitted again with it the truth the target was rendered with comes back
    (inverse crime: no model error)."""
    target = np.asarray(fitter.render(GLOSSY, SCENE))
    level = 0.8 * target.max()
    clipped = np.minimum(target, level)
    r = fitter.fit(clipped, SCENE, "lambert+torrance_sparrow")
    assert r.status == "failed" and "likely a clipped highlight" in r.message, r.message
    assert fit_badge(r)[0].startswith("TARGET LOOKS CLIPPED")
    named = float(r.message.split("saturation = ")[1].split(" ")[0])
    assert level * (1 - 1e-5) <= named <= level  # drops the flat top, six digits
    again = fitter.fit(clipped, SCENE, "lambert+torrance_sparrow", saturation=named)
    assert again.status == "converged", again.message
    for key, want in GLOSSY.items():
        np.testing.assert_allclose(again.params[key], want, rtol=INVERSE_CRIME_RTOL)


def test_clipped_counts_a_flat_top_only():
    """``_adequacy.clipped``: a channel's maximum shared by CLIPPED_PIXELS fitted
    pixels where the fit is above it; not fewer, not where the fit is below, not
    a black target, not a pixel left out."""
    rng = np.random.default_rng(5)
    target = rng.random((50, 3))
    model = target + 0.01
    used = np.ones((50, 3), bool)
    assert _adequacy.clipped(target, model, used) is None  # distinct values
    n = _adequacy.CLIPPED_PIXELS
    target[:n, 1], model[:n, 1] = 2.0, 2.5
    assert _adequacy.clipped(target, model, used) == (n, 2.0)
    model[0, 1] = 1.0  # the fit below the top at one of them
    assert _adequacy.clipped(target, model, used) is None
    model[0, 1] = 3.0
    used[1, 1] = False  # one of them left out: the top is the other n - 1
    assert _adequacy.clipped(target, model, used) is None
    assert _adequacy.clipped(np.zeros((50, 3)), np.ones((50, 3)), np.ones((50, 3), bool)) is None


def test_a_target_brighter_than_the_box_allows_fails_as_a_poor_fit_naming_it():
    """A Lambert render 3x brighter than its albedo (0.5, 0.4, 0.3) allows (lights
    or exposure wrong): the best albedo lies on its bound 1 in two channels.
    Before, the fit ended "max_steps" (values on the box's edge) with no verdict on
    the residual, 158 times the noise; now a best fit on the box's edge is judged
    like a converged one and the cause points at the lights and exposure."""
    target = 3.0 * np.asarray(fitter.render({"lambert.rho_d": [0.5, 0.4, 0.3]}, SCENE))
    r = fitter.fit(target, SCENE, "lambert")
    assert r.status == "failed" and r.message.startswith("poor fit"), r.message
    assert "at a best fit on the edge of its box (lambert.rho_d" in r.message, r.message
    assert "likely values beyond the parameters' boxes" in r.message, r.message
    assert "the lights' intensity and the image's exposure" in r.message
    np.testing.assert_allclose(r.params["lambert.rho_d"][:2], 1.0, atol=1e-3)
    assert all(np.all(np.isfinite(v)) for v in r.stderr.values())


def test_a_target_far_brighter_than_any_albedo_names_the_lights_and_exposure():
    """100x brighter: the albedo's logit runs to where its slope underflows to 0,
    and it is held as unconstrained (``_identify``: a zero column says nothing of
    a bound), so every parameter is held. The message says so and, as the held
    values' render is a uniform scale of the target far above the noise, what
    to check; before, it said only "no parameter is identifiable"."""
    target = 100.0 * np.asarray(fitter.render({"lambert.rho_d": [0.5, 0.4, 0.3]}, SCENE))
    r = fitter.fit(target, SCENE, "lambert")
    assert r.status == "failed" and "no parameter is identifiable" in r.message
    assert "check the lights' intensity and the image's exposure" in r.message, r.message
    scale = float(r.message.split("the target ")[1].split(" times")[0])
    assert 60.0 <= scale <= 100.0  # the render at the held 0.5 against 50, 40, 30


def test_exposure_scale_is_named():
    """The diffuse albedo held at its true value, the image 0.7 times darker:
    nothing free can absorb the scale, and the message says so."""
    target = 0.7 * np.asarray(fitter.render(GLOSSY, SCENE))
    r = fitter.fit(target, SCENE, "lambert+torrance_sparrow",
                   fixed={"lambert.rho_d": GLOSSY["lambert.rho_d"]})
    assert r.status == "failed"
    assert "exposure or light scale" in r.message, r.message


def test_weak_direction_triggers_several_starts_without_being_asked():
    """rho_s and eta trade (F0 scales the lobe like rho_s): one start asked, the
    valley is found locally and the fit is re-solved from several starts."""
    scene = fitter.Scene(width=32, height=32, supersampling=2, lights=LIGHTS)
    truth = {"torrance_sparrow.m": 0.3, "torrance_sparrow.eta": 1.5,
             "torrance_sparrow.rho_s": 0.8}
    r = fitter.fit(np.asarray(fitter.render(truth, scene)), scene, "torrance_sparrow",
                   init={"torrance_sparrow.rho_s": 0.5})
    assert len(r.starts) == 4
    assert any(w.startswith("weakly identified") and "torrance_sparrow.eta" in w
               for w in r.warnings), r.warnings
    assert not any("spatially structured" in w for w in r.warnings)  # rounding residual
    np.testing.assert_allclose(r.params["torrance_sparrow.m"], 0.3, rtol=1e-6)


@pytest.mark.parametrize("mean,mx,label", [
    (0.3, 1.0, "MITSUBA: NO VISIBLE DIFFERENCE"),
    (0.9, 6.7, "MITSUBA: VISIBLE DIFFERENCE"),  # issue 12: mean < 1 hid a max of 6.7
    (0.9, 4.0, "MITSUBA: JUST NOTICEABLE"),
    (3.0, 3.0, "MITSUBA: VISIBLE DIFFERENCE"),
])
def test_mitsuba_badge_uses_the_max(mean, mx, label):
    assert mitsuba_badge(mean, mx)[0] == label


def _gauss_newton_errors(params, target, scene, lobes):
    """sqrt(diag(s^2 (J^T J)^-1)) in user units over the pixels wholly on the sphere,
    s^2 the residual's chi^2 per degree of freedom: J by ``jax.jacfwd`` of
    ``fitter.render`` (independent of the fitter's transforms and covariance)."""
    import jax
    import jax.numpy as jnp

    keys = list(params)
    sizes = [np.size(params[k]) for k in keys]
    renderer = fitter.Renderer(scene, fitter.Material.make(lobes))
    inside = renderer.pixel_index[np.asarray(renderer.geometry.hit).all(axis=1)]

    def image(x):
        p, i = {}, 0
        for k, n in zip(keys, sizes):
            p[k] = x[i:i + n] if n > 1 else x[i]
            i += n
        return fitter.render(p, scene, lobes).reshape(-1, 3)[inside].reshape(-1)

    x = jnp.asarray(np.concatenate([np.atleast_1d(params[k]) for k in keys]))
    J = np.asarray(jax.jacfwd(image)(x))
    r = np.asarray(image(x)) - np.asarray(target).reshape(-1, 3)[inside].reshape(-1)
    s2 = float(r @ r) / (r.size - J.shape[1])
    sd = np.sqrt(s2 * np.diag(np.linalg.inv(J.T @ J)))
    return dict(zip(keys, np.split(sd, np.cumsum(sizes)[:-1])))


def test_discretisation_error_is_propagated_into_the_stated_error():
    """k vs 2k: a noise-free target rendered with 16 x 16 samples per pixel,
    fitted with 2 x 2. The fit absorbs the model's quadrature error (the
    residual cannot show it); rendering the fit at 4 x 4 and taking the
    difference through the linearisation gives the parameters' shift. The
    stated errors cover the actual errors (which the reference at 16 x 16,
    a converged quadrature, gives), and the discretisation part is most of it:
    the Gauss-Newton error alone would be over-confident."""
    fine = np.asarray(fitter.render(GLOSSY, SCENE.replace(supersampling=16)))
    r = fitter.fit(fine, SCENE, "lambert+torrance_sparrow")
    assert r.status == "converged", r.message
    info = r.adequacy["blocks"]["discretisation"]
    assert info["supersampling"] == [2, 4]
    gauss_newton = _gauss_newton_errors({k: r.params[k] for k in GLOSSY}, fine, SCENE,
                                        "lambert+torrance_sparrow")
    worst = 0.0
    for k, t in GLOSSY.items():
        err = np.abs(np.asarray(r.params[k]) - np.asarray(t))
        worst = max(worst, float(np.max(err / gauss_newton[k])))
        assert np.all(err < 1.5 * np.asarray(r.stderr[k])), (k, err, r.stderr[k])
        assert np.all(np.asarray(r.stderr_disc[k]) > 0.5 * err), (k, err, r.stderr_disc[k])
    assert worst > 4.0, worst  # measured 5.3


def test_an_environment_sun_marks_highlight_pixels(tmp_path):
    """An env-only scene (no scene lights) with a sun: the sun's cells are
    ``Geometry.sun`` entries, not rows of ``light_weight``; the highlight region
    must still be found there (the discretisation term renders it wholly). The
    reference: the mirror direction of the sun's centroid on the sphere."""
    import jax.numpy as jnp

    from fitter.imageio import write_image
    from fitter.render import cached_renderer

    img = np.full((16, 32, 3), 0.3)
    img[6, 12] = [3000.0, 2900.0, 2500.0]  # a sun above the horizon, in front
    path = str(tmp_path / "sun.exr")
    write_image(path, img)
    scene = fitter.Scene(width=32, height=32, supersampling=2,
                         environment=fitter.Environment(type="envmap", file=path))
    mat = fitter.Material.from_params({"torrance_sparrow.m": 0.1})
    r = cached_renderer(scene, mat, jnp.dtype(jnp.float64), None)
    geo = r.geometry
    assert not np.asarray(geo.light_weight).shape[0] and len(geo.sun)
    label = _adequacy.pixel_regions(geo)
    high = np.nonzero(label == 1)[0]
    assert high.size > 0
    # Those pixels' normals lie near the half vector of the sun and the view.
    idx, cos, _, _ = next(geo.sun.groups())
    peak = np.asarray(idx)[np.argmax(np.max(np.asarray(cos.cos_h), axis=0))]
    assert np.max(np.asarray(cos.cos_h)) > np.cos(_adequacy.HIGHLIGHT_ANGLE)
    assert peak in high or label[peak] == 2


def test_regions_of_a_subset_sharing_the_sun_pairs(tmp_path):
    """A fit's pixel subset shares the sun's pairs (``Geometry.subset(...,
    shared_sun=True)``): a dropped pixel's samples point past the last row. With
    highlight pixels dropped, the regions are those of the whole geometry's kept
    pixels (an env_sweep case had raised IndexError here)."""
    import jax.numpy as jnp

    from fitter.imageio import write_image
    from fitter.render import cached_renderer

    img = np.full((16, 32, 3), 0.3)
    img[6, 12] = [3000.0, 2900.0, 2500.0]
    path = str(tmp_path / "sun.exr")
    write_image(path, img)
    scene = fitter.Scene(width=32, height=32, supersampling=2,
                         environment=fitter.Environment(type="envmap", file=path))
    mat = fitter.Material.from_params({"torrance_sparrow.m": 0.1})
    geo = cached_renderer(scene, mat, jnp.dtype(jnp.float64), None).geometry
    whole = _adequacy.pixel_regions(geo)
    high = np.nonzero(whole == 1)[0]
    keep = np.setdiff1d(np.arange(whole.size), high[::2])
    sub = geo.subset(keep, shared_sun=True)
    assert np.asarray(sub.sun.index).max() == keep.size  # a dropped pixel's sample
    np.testing.assert_array_equal(_adequacy.pixel_regions(sub), whole[keep])


def test_sub_pixel_highlight_is_not_a_confident_wrong_eta():
    """Issue 12: m = 1e-3, eta = 1.5 (a sub-pixel highlight), 32^2, noise 0.1 % of
    the mean lit pixel, one start at m = 0.01. The weakest direction's profile
    rose as quadratic (correlation eigenvalue 0.86), so one start stood: eta =
    1.0017 +- 0.095 (5 stated errors off) listed identifiable, while the truth
    is only chi^2 +3.6 above it. eta's own profile is flat (chi^2 +0.36 at 3
    stated errors): several starts follow and the ambiguity check decides.
    Truth: the image model's own render (the check is of the fit's honesty)."""
    lights = (fitter.PointLight((3.0, 4.0, 5.0), (50.0,) * 3),
              fitter.PointLight((-4.0, 1.0, 3.0), (25.0,) * 3))
    scene = fitter.Scene(width=32, height=32, supersampling=2, lights=lights)
    smith = {"torrance_sparrow.geometry": "smith"}
    mat = fitter.Material.make("lambert+torrance_sparrow", smith)
    truth = {"lambert.rho_d": [0.5] * 3, "torrance_sparrow.m": 1e-3,
             "torrance_sparrow.eta": 1.5}
    clean = np.asarray(fitter.render({**truth, **smith}, scene, mat), dtype=np.float64)
    sigma = 1e-3 * float(clean[clean.sum(-1) > 0].mean())
    target = clean + np.random.default_rng(13).normal(0.0, sigma, clean.shape)
    r = fitter.fit(target, scene, mat, init={"torrance_sparrow.m": 0.01}, noise_sigma=sigma)
    for key, tol in (("torrance_sparrow.eta", 0.005), ("torrance_sparrow.m", 0.02 * 1e-3)):
        err = abs(float(r.params[key]) - truth[key])
        confident = r.status == "converged" and key not in r.unidentifiable
        assert not (confident and err > tol and err > 3.0 * float(r.stderr[key])), \
            (key, r.params, r.stderr, r.unidentifiable, r.warnings)


def test_few_pixels_names_the_coordinates_one_or_two_pixels_carry():
    """A column whose weight sits in one pixel (a glint) or two is named with the
    pixel carrying most of it; a column spread over the image, or over four
    pixels alike, is not (``_adequacy.MIN_PIXELS`` = 3 effective pixels)."""
    rng = np.random.default_rng(3)
    pixels = 400
    J = np.zeros((3 * pixels, 4))
    J[:, 0] = rng.normal(size=3 * pixels)                 # every pixel
    J[:, 1] = 1e-3 * rng.normal(size=3 * pixels)          # one pixel ...
    J[3 * 37:3 * 38, 1] = 5.0                             # ... pixel 37
    J[:, 2] = 1e-3 * rng.normal(size=3 * pixels)          # two pixels, 212 the larger
    J[3 * 211:3 * 212, 2], J[3 * 212:3 * 213, 2] = 3.0, 4.0
    J[:, 3] = 1e-3 * rng.normal(size=3 * pixels)          # four pixels alike
    J[3 * 100:3 * 104, 3] = 2.0
    few = _adequacy.few_pixels(J, pixels)
    assert sorted(few) == [1, 2], few
    assert few[1][1] == [37] and few[2][1] == [212, 211], few
    assert few[1][0] < 1.1 and 1.5 < few[2][0] < 2.0, few  # one pixel; two (9:16 shares)
    # the same from the pixel sandwich's N_j, and for the columns scaled (the report's)
    scaled = J * np.array([1.0, 10.0, 0.1, 3.0])
    n_eff = _adequacy.pixel_sandwich(scaled, np.zeros(3 * pixels), pixels)[1]
    again = _adequacy.few_pixels(scaled, pixels, n_eff=n_eff)
    assert {j: v[1] for j, v in again.items()} == {j: v[1] for j, v in few.items()}, again
    np.testing.assert_allclose([v[0] for v in again.values()], [v[0] for v in few.values()],
                               rtol=1e-12)


#: A parameter in the issue's tolerance list (rho 0.005, eta 0.005).
GLINT_TOL = 0.005


@pytest.mark.mitsuba
@pytest.mark.parametrize("material,truth,init", [
    ("dielectric", {"dielectric.eta": 1.5, "dielectric.attenuation": [0.9, 0.7, 0.5]},
     {"dielectric.eta": 1.3, "dielectric.attenuation": [0.8] * 3}),
    ("mirror", {"mirror.rho_m": [0.9, 0.8, 0.7]}, {}),
])
def test_a_glint_is_left_out_and_the_others_recover_the_truth(tmp_path, material, truth, init):
    """A glass or mirror sphere under a sky with a sun of one texel (2.8 degrees,
    ~2000x the sky), target by Mitsuba (4096 spp): the sun's glint, one pixel,
    carried 96 % of eta's information (a mirror's rho_m: 1.1 effective pixels),
    its Monte Carlo noise ~3 % of its value while the other pixels' was ~0.1 %,
    so eta came out 1.5105 +- 0.0015 (7 stated errors off) and rho_m 0.011 off,
    converged and identifiable. The glint and its neighbours are now left out
    and the fit refit from the others (``_glints``). Reference: the truth
    Mitsuba rendered."""
    blue = np.array([0.5, 0.7, 1.0])  # (0.3 + 0.7 (1 - v)) blue
    scene = one_texel_sun(tmp_path / "sky.exr", 16, 76, 0.3 * blue, 0.7 * blue,
                          [0.2, 0.15, 0.1], [2000.0, 1900.0, 1800.0])
    target = np.asarray(fitter.mitsuba.render(scene, material, truth, spp=4096, seed=0))
    r = fitter.fit(target, scene, material, init=init or None)
    assert r.status == "converged" and not r.unidentifiable, (r.message, r.warnings)
    assert any(w.startswith("left out the pixel(s) at row 20, column 25") for w in r.warnings)
    for key, value in truth.items():
        err = np.abs(np.asarray(r.params[key]) - value)
        assert np.all(err < GLINT_TOL) and np.all(err < 3.0 * np.asarray(r.stderr[key])), \
            (key, r.params, r.stderr, r.warnings)

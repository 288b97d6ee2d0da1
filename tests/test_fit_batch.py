"""fit_batch: many targets of one scene in one compiled solve give what fit gives."""

import numpy as np
import pytest

import fitter
from fitter.fit import fit_batch

SCENE = fitter.Scene(width=24, height=24, supersampling=2, lights=(
    fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),))


@pytest.mark.parametrize("batch", ["map", "vmap"])
def test_batch_matches_single_fits(batch):
    truths = [{"lambert.rho_d": [0.2 + 0.1 * i, 0.5, 0.3], "phong.rho_s": 0.3,
               "phong.e": 10.0 + 15.0 * i} for i in range(3)]
    targets = np.stack([np.asarray(fitter.render(t, SCENE)) for t in truths])
    targets[1, 12, 12] = np.nan  # a bad pixel in one target only
    init = {"lambert.rho_d": 0.4, "phong.rho_s": 0.2, "phong.e": 20.0}
    results = fit_batch(targets, SCENE, "lambert+phong", init=init, batch=batch)
    assert len(results) == 3
    for truth, res, tgt in zip(truths, results, targets):
        single = fitter.fit(tgt, SCENE, "lambert+phong", init=init)
        assert res.status == "converged"
        for k, v in truth.items():
            np.testing.assert_allclose(res.params[k], v, rtol=1e-6)
            np.testing.assert_allclose(res.params[k], single.params[k], rtol=1e-9)
    assert results[1].n_excluded == results[0].n_excluded + 1


def test_each_result_carries_its_own_fitted_pixels_outside_the_json():
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3]}
    targets = np.stack([np.asarray(fitter.render(truth, SCENE))] * 2)
    targets[1, 12, 12] = np.nan
    results = fit_batch(targets, SCENE, "lambert")
    single = fitter.fit(targets[0], SCENE, "lambert")
    np.testing.assert_array_equal(results[0].fitted, single.fitted)
    assert results[0].fitted.dtype == bool and results[0].fitted.shape == (24, 24)
    assert results[0].fitted[12, 12] and not results[1].fitted[12, 12]
    assert results[0].fitted.sum() == results[1].fitted.sum() + 1 == single.n_pixels
    assert "fitted" not in single.to_dict()

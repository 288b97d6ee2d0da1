"""The sun's cells as the far samples' lights (``suncells.clusters``).

Reference: Lambert's irradiance at a normal n is the direct sum over every cell,
sum_i max(n . d_i, 0) E_i (the cells are exact directional lights); the merged lights
must reproduce it away from the highlight and the sun's horizon (where the near
samples see every cell).
"""

from __future__ import annotations

import numpy as np

from fitter import suncells
from fitter.envlight import LUMINANCE

#: Lambert's far irradiance through the clusters: each cluster's cells lie within
#: ~CLUSTER_WIDTH / 2 of its light, so its cos-weighted mean is off by ~(0.03)^2 / 2.
CLUSTERS_ACCURACY = 5e-4
#: One light for a 20 deg disc is off by ~s^2 / 2, s = 0.124 rad its cells' rms angle.
ONE_LIGHT_ERROR = 5e-3


def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _around(centre, angle, phi):
    """Unit directions at ``angle`` (rad) from ``centre``, at azimuths ``phi`` about it."""
    t1 = _unit(np.cross([1.0, 0.0, 0.0], centre))
    t2 = np.cross(centre, t1)
    return _unit(np.sin(angle)[:, None] * (np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2)
                 + np.cos(angle)[:, None] * centre)


def _disc(centre, diameter_deg, n, rng):
    """``n`` cell directions uniform on a cap of that diameter about ``centre``."""
    z = rng.uniform(np.cos(np.radians(diameter_deg / 2)), 1.0, n)
    return _around(centre, np.arccos(z), rng.uniform(0.0, 2 * np.pi, n))


def _far_normals(centre, rng, n=200):
    """Normals 40-80 deg from the sun's centre: far from its horizon."""
    return _around(centre, np.radians(rng.uniform(40.0, 80.0, n)),
                   rng.uniform(0.0, 2 * np.pi, n))


def _irradiance(normals, dirs, irr):
    return np.maximum(normals @ dirs.T, 0.0) @ irr


def test_a_wide_sun_reaches_far_samples_as_clusters():
    rng = np.random.default_rng(0)
    centre = _unit(np.array([0.3, 0.5, 0.8]))
    dirs = _disc(centre, 20.0, 400, rng)
    irr = rng.uniform(0.5, 1.5, (400, 1)) * np.array([1.0, 0.9, 0.8])
    far_dir, far_irr = suncells.clusters(dirs, irr)
    assert 10 < far_dir.shape[0] < 400
    np.testing.assert_allclose(far_irr.sum(0), irr.sum(0), rtol=1e-13)  # the power kept
    normals = _far_normals(centre, rng)
    want = _irradiance(normals, dirs, irr)
    got = _irradiance(normals, far_dir, far_irr)
    assert np.max(np.abs(got / want - 1.0)) < CLUSTERS_ACCURACY
    lum = irr @ LUMINANCE
    one = _unit((dirs * lum[:, None]).sum(0))
    single = _irradiance(normals, one[None], irr.sum(0, keepdims=True))
    assert np.max(np.abs(single / want - 1.0)) > ONE_LIGHT_ERROR  # what one light did


def test_a_small_sun_stays_one_light():
    # Cells spread like the probe's 3 deg sun and its cells' bilinear halo (rms 0.031
    # rad here, the probe's 0.034): one light at their centroid, as before clusters.
    rng = np.random.default_rng(1)
    centre = _unit(np.array([0.45, 0.55, 0.70]))
    dirs = _disc(centre, 5.0, 64, rng)
    irr = rng.uniform(0.5, 1.5, (64, 3))
    far_dir, far_irr = suncells.clusters(dirs, irr)
    lum = irr @ LUMINANCE
    np.testing.assert_allclose(far_dir, _unit((dirs * lum[:, None]).sum(0))[None], rtol=1e-15)
    np.testing.assert_allclose(far_irr, irr.sum(0, keepdims=True), rtol=1e-15)

"""The sky sum's blocked layout (``fitter.skystencil.blocks``, ``sky_sum``): windows of
theta_o nodes per block, checked against a direct per-sample evaluation in NumPy."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from fitter import skystencil
from fitter.atan2 import atan2


def _samples(rng, count, nodes):
    """Lower nodes crowded towards node 0 and the last (as a sphere's are), fractions in
    [0, 1] with both ends exactly."""
    node = np.concatenate([rng.integers(0, nodes - 1, count // 2),
                           np.minimum(rng.geometric(0.3, count - count // 2) - 1, nodes - 2),
                           ])[rng.permutation(count)]
    node = np.where(rng.random(count) < 0.3, nodes - 2 - node, node).astype(np.int32)
    frac = rng.random(count)
    frac[:3], frac[3:6] = 0.0, 1.0
    node[3] = nodes - 2  # the last node's far end: pos = S - 1
    return node, frac


@pytest.mark.parametrize(("nodes", "block", "window"),
                         [(9, 32, 3), (9, 16, 2), (97, 64, 4), (3, 8, 4), (2, 8, 4)])
def test_blocks_cover_every_sample_once_within_its_window(nodes, block, window):
    node, frac = _samples(np.random.default_rng(nodes + block), 500, nodes)
    order, win, pos = skystencil.blocks(node, frac, nodes, block=block, window=window)
    s = max(min(window, nodes), 2)
    assert order.size % block == 0 and win.shape == (order.size // block, s)
    np.testing.assert_array_equal(np.sort(order[order >= 0]), np.arange(node.size))
    assert np.all(win.min(1) >= 0) and np.all(win.max(1) <= nodes - 1)
    np.testing.assert_array_equal(np.diff(win, axis=1), 1)  # consecutive nodes
    start = np.repeat(win[:, 0], block)
    real = order >= 0
    lower = node[order[real]] - start[real]
    assert np.all(lower >= 0) and np.all(lower + 1 <= s - 1)  # both neighbours in the window
    np.testing.assert_allclose(pos[real], lower + frac[order[real]], rtol=0, atol=1e-15)
    assert np.all(pos[~real] == 0)


@pytest.mark.parametrize("rgb", [False, True])
@pytest.mark.parametrize(("block", "window"), [(32, 3), (16, 2), (64, 5)])
def test_windowed_sum_equals_a_direct_per_sample_evaluation(rgb, block, window):
    """Reference: per sample, h linearly interpolated between its node and the next,
    summed against the sample's row of c (NumPy, no blocks)."""
    rng = np.random.default_rng(block + window + rgb)
    nodes, cells, cols, count = 11, 20, 3, 400
    node, frac = _samples(rng, count, nodes)
    c = rng.normal(size=(count, 3, cells))
    h = rng.normal(size=(cols, nodes, cells) + ((3,) if rgb else ()))
    f = frac.reshape((1, count) + (1,) * (h.ndim - 2))
    hs = h[:, node] * (1 - f) + h[:, node + 1] * f  # (K, R0, N[, 3])
    ref = (np.einsum("rcn,krnc->krc", c, hs) if rgb else np.einsum("rcn,krn->krc", c, hs))

    order, win, pos = skystencil.blocks(node, frac, nodes, block=block, window=window)
    cb = np.where((order >= 0)[:, None, None], c[np.maximum(order, 0)], 0.0)
    cb = cb.reshape(win.shape[0], 3 * block, cells)
    val = np.asarray(skystencil.sky_sum(jnp.asarray(h), jnp.asarray(win), jnp.asarray(pos),
                                        jnp.asarray(cb)))
    assert val.shape == (cols, order.size, 3)
    np.testing.assert_allclose(val[:, order >= 0], ref[:, order[order >= 0]], rtol=1e-12,
                               atol=1e-12 * np.abs(ref).max())
    assert np.all(val[:, order < 0] == 0)
    # no lead axes: one lobe column
    one = np.asarray(skystencil.sky_sum(jnp.asarray(h[0]), jnp.asarray(win), jnp.asarray(pos),
                                        jnp.asarray(cb)))
    np.testing.assert_allclose(one, val[0], rtol=1e-13, atol=1e-13 * np.abs(ref).max())


def test_node_cos_o_is_one_value_per_node():
    """cos_o = n . wo at theta_o node t is cos(t) (the local frame's n = (sin t, 0,
    cos t), wo = (sin 2t, 0, cos 2t)): kept (T, 1, 1), every other cosine (T, N, M)."""
    cos, w = skystencil._node_geometry(9, (2, 4))
    t = skystencil.node_angles(9)
    assert cos.cos_o.shape == (9, 1, 1) and cos.cos_i.shape == w.shape
    np.testing.assert_allclose(cos.cos_o[:, 0, 0], np.cos(t), rtol=0, atol=1e-15)


def test_the_tables_bilinear_lookup_is_mitsubas_on_every_level():
    """``_flat_levels``' 2 x 2 neighbourhoods give, through ``_bilinear``, the
    same value as a lookup of each level's own image (``envlight.bilinear``,
    Mitsuba's convention: x wraps, y clamps), on a random pyramid and at
    random points plus the seam (u = 0, 1 - 1e-12) and the poles (v = 0, 1)."""
    from types import SimpleNamespace

    from fitter.envlight import bilinear

    rng = np.random.default_rng(3)
    levels = [rng.random((h, 2 * h - 2, 3)) for h in (9, 5, 3)]
    quads, lh, lw, loff = skystencil._flat_levels(SimpleNamespace(levels=levels))
    u = np.concatenate([rng.random(500), [0.0, 1.0 - 1e-12, 0.5, 0.0]])
    v = np.concatenate([rng.random(500), [0.0, 1.0, 1.0, 0.5]])
    for xp in (jnp, np):  # on the device, and on the host (``sky_table``'s small tables)
        for i, img in enumerate(levels):
            got = skystencil._bilinear(xp, xp.asarray(quads), xp.int32(lh[i]), xp.int32(lw[i]),
                                       xp.int32(loff[i]), xp.asarray(u), xp.asarray(v))
            np.testing.assert_allclose(np.asarray(got), bilinear(img, u, v), rtol=1e-12, atol=0)


#: ``fitter.atan2.atan2``'s stated accuracy (float32 inputs), radians.
ATAN2_ATOL = 3e-7


@pytest.mark.parametrize("xp", [jnp, np])
def test_the_tables_atan2_is_numpys_to_float32_accuracy(xp):
    """The sky table's vectorised atan2 (``fitter.atan2``) against NumPy's float64
    ``arctan2`` of the same float32 inputs: random points of every octant and scale, the axes,
    the octant boundaries |y| = |x| and |y| = tan(pi / 8) |x|, and IEEE's signed
    zeros (atan2(+-0, -0) = +-pi, atan2(+-0, +0) = +-0)."""
    rng = np.random.default_rng(5)
    y = rng.normal(size=200_000) * 10.0 ** rng.uniform(-6, 6, 200_000)
    x = rng.normal(size=200_000) * 10.0 ** rng.uniform(-6, 6, 200_000)
    t = np.tan(np.pi / 8)
    special = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0], [1.0, 1.0],
                        [-1.0, -1.0], [t, 1.0], [-t, -1.0], [1.0, t], [0.0, 0.0],
                        [-0.0, 0.0], [0.0, -0.0], [-0.0, -0.0], [1e-30, -1.0]])
    y = np.concatenate([y, special[:, 0]]).astype(np.float32)
    x = np.concatenate([x, special[:, 1]]).astype(np.float32)
    got = np.asarray(atan2(xp, xp.asarray(y), xp.asarray(x)), np.float64)
    want = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    np.testing.assert_allclose(got, want, rtol=0, atol=ATAN2_ATOL)
    np.testing.assert_array_equal(np.signbit(got[-5:]), np.signbit(want[-5:]))

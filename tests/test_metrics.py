"""CIEDE2000 of ``fitter.metrics``: Sharma et al.'s published test pairs, and
colour-science's implementation of the same route (both independent of it)."""

from __future__ import annotations

import numpy as np

from fitter.metrics import _lab, compare, delta_e2000

#: Sharma, Wu, Dalal (2005), "The CIEDE2000 color-difference formula:
#: implementation notes, supplementary test data and mathematical observations",
#: Table 1: (L*a*b* 1, L*a*b* 2, ΔE00), published to 4 decimals.
SHARMA = [
    ((50.0000, 2.6772, -79.7751), (50.0000, 0.0000, -82.7485), 2.0425),
    ((50.0000, 3.1571, -77.2803), (50.0000, 0.0000, -82.7485), 2.8615),
    ((50.0000, 2.8361, -74.0200), (50.0000, 0.0000, -82.7485), 3.4412),
    ((50.0000, -1.3802, -84.2814), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, -1.1848, -84.8006), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, -0.9009, -85.5211), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, 0.0000, 0.0000), (50.0000, -1.0000, 2.0000), 2.3669),
    ((50.0000, -1.0000, 2.0000), (50.0000, 0.0000, 0.0000), 2.3669),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0009), 7.1792),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0010), 7.1792),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0011), 7.2195),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0012), 7.2195),
    ((50.0000, -0.0010, 2.4900), (50.0000, 0.0009, -2.4900), 4.8045),
    ((50.0000, -0.0010, 2.4900), (50.0000, 0.0011, -2.4900), 4.7461),
    ((50.0000, 2.5000, 0.0000), (50.0000, 0.0000, -2.5000), 4.3065),
    ((50.0000, 2.5000, 0.0000), (73.0000, 25.0000, -18.0000), 27.1492),
    ((50.0000, 2.5000, 0.0000), (61.0000, -5.0000, 29.0000), 22.8977),
    ((50.0000, 2.5000, 0.0000), (56.0000, -27.0000, -3.0000), 31.9030),
    ((50.0000, 2.5000, 0.0000), (58.0000, 24.0000, 15.0000), 19.4535),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.1736, 0.5854), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.2972, 0.0000), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 1.8634, 0.5757), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.2592, 0.3350), 1.0000),
    ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644),
    ((63.0109, -31.0961, -5.8663), (62.8187, -29.7946, -4.0864), 1.2630),
    ((61.2901, 3.7196, -5.3901), (61.4292, 2.2480, -4.9620), 1.8731),
    ((35.0831, -44.1164, 3.7933), (35.0232, -40.0716, 1.5901), 1.8645),
    ((22.7233, 20.0904, -46.6940), (23.0331, 14.9730, -42.5619), 2.0373),
    ((36.4612, 47.8580, 18.3852), (36.2715, 50.5065, 21.2231), 1.4146),
    ((90.8027, -2.0831, 1.4410), (91.1528, -1.6435, 0.0447), 1.4441),
    ((90.9257, -0.5406, -0.9208), (88.6381, -0.8985, -0.7239), 1.5381),
    ((6.7747, -0.2908, -2.4247), (5.8714, -0.0985, -2.2286), 0.6377),
    ((2.0776, 0.0795, -1.1350), (0.9033, -0.0636, -0.5514), 0.9082),
]


def test_delta_e2000_reproduces_sharmas_published_pairs():
    lab1, lab2, want = (np.array(c, dtype=np.float64) for c in zip(*SHARMA))
    np.testing.assert_allclose(delta_e2000(lab1, lab2), want, atol=5e-5)
    np.testing.assert_allclose(delta_e2000(lab2, lab1), want, atol=5e-5)  # symmetric


def test_compare_is_colour_sciences_route_to_rounding():
    import colour

    rng = np.random.default_rng(3)
    target = rng.uniform(-0.05, 1.1, (20, 30, 3))  # below 0 and above 1: clipped
    image = target * rng.uniform(0.9, 1.1, target.shape) + 0.002
    image[0, :5] = target[0, :5]  # equal pixels: ΔE 0
    image[1, :3] = 0.0  # black: the linear segment of the transfer function

    def lab(rgb):
        encoded = colour.cctf_encoding(np.clip(rgb, 0.0, 1.0), function="sRGB")
        xyz = colour.RGB_to_XYZ(encoded, colour.RGB_COLOURSPACES["sRGB"],
                                apply_cctf_decoding=True)
        return colour.XYZ_to_Lab(
            xyz, colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])

    np.testing.assert_allclose(_lab(target), lab(target), rtol=0, atol=1e-10)
    want = colour.delta_E(lab(target), lab(image), method="CIE 2000")
    got = compare(target, image)
    np.testing.assert_allclose(got["delta_e2000_mean"], want.mean(), rtol=1e-12)
    np.testing.assert_allclose(got["delta_e2000_max"], want.max(), rtol=1e-12)

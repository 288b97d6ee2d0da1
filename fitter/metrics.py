"""Image agreement metrics: RMSE, PSNR and CIEDE2000 colour difference.

ΔE route (colour-science's, written out here: importing ``colour`` took
0.8 s, on every validated fit): linear RGB, clipped to the display range
[0, 1] -> sRGB-encoded and decoded again (IEC 61966-2-1 transfer function)
-> CIE XYZ (the IEC sRGB matrix, D65) -> CIE L*a*b* (D65 white, CIE 1976)
-> CIEDE2000 (Sharma et al. 2005, k_L = k_C = k_H = 1).
``tests/test_metrics.py`` checks it against Sharma's published pairs and
against ``colour.delta_E(method="CIE 2000")`` on the same route.
ΔE < 1 is commonly taken as not visible side by side; ~2.3 as a "just
noticeable difference".

References:
    Sharma, Wu, Dalal (2005), "The CIEDE2000 color-difference formula",
        Color Research & Application 30(1).
    IEC 61966-2-1:1999 (sRGB).
"""

from __future__ import annotations

import numpy as np


#: IEC 61966-2-1 sRGB -> CIE XYZ (the standard's rounded matrix, as colour-science's
#: sRGB colourspace uses it) and the D65 white point (CIE 1931 2 degree xy).
SRGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805],
                        [0.2126, 0.7152, 0.0722],
                        [0.0193, 0.1192, 0.9505]])
D65_XY = (0.3127, 0.3290)


def _srgb_encode(linear):
    return np.where(linear <= 0.0031308, linear * 12.92,
                    1.055 * np.power(linear, 1 / 2.4) - 0.055)


def _srgb_decode(encoded):
    return np.where(_srgb_encode(0.0031308) >= encoded, encoded / 12.92,
                    np.power((encoded + 0.055) / 1.055, 2.4))


def _lab(linear_rgb: np.ndarray) -> np.ndarray:
    """CIE L*a*b* (..., 3) of linear sRGB (..., 3), the route of the module docstring."""
    rgb = _srgb_decode(_srgb_encode(np.clip(linear_rgb, 0.0, 1.0)))
    xyz = np.einsum("ij,...j->...i", SRGB_TO_XYZ, rgb)
    x, y = D65_XY
    white = np.array([x * 1.0 / y, 1.0, (1 - x - y) * 1.0 / y])
    t = xyz / white
    f = np.where(t > (24 / 116) ** 3, np.power(t, 1 / 3), (841 / 108) * t + 16 / 116)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]),
                     200 * (f[..., 1] - f[..., 2])], axis=-1)


def delta_e2000(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    """CIEDE2000 colour difference (...) of CIE L*a*b* arrays (..., 3), k_L = k_C = k_H = 1
    (Sharma, Wu, Dalal 2005, eqs. 1-22; hue angles in degrees as there)."""
    L1, a1, b1 = np.moveaxis(np.asarray(lab1, dtype=np.float64), -1, 0)
    L2, a2, b2 = np.moveaxis(np.asarray(lab2, dtype=np.float64), -1, 0)
    c_bar7 = ((np.hypot(a1, b1) + np.hypot(a2, b2)) / 2) ** 7
    g = 0.5 * (1 - np.sqrt(c_bar7 / (c_bar7 + 25**7)))
    ap1, ap2 = (1 + g) * a1, (1 + g) * a2
    cp1, cp2 = np.hypot(ap1, b1), np.hypot(ap2, b2)
    hp1 = np.where((b1 == 0) & (ap1 == 0), 0, np.degrees(np.arctan2(b1, ap1)) % 360)
    hp2 = np.where((b2 == 0) & (ap2 == 0), 0, np.degrees(np.arctan2(b2, ap2)) % 360)
    dl, dc = L2 - L1, cp2 - cp1
    dh, cc = hp2 - hp1, cp1 * cp2
    dh = np.select([cc == 0, np.abs(dh) <= 180, dh > 180, dh < -180],
                   [0, dh, dh - 360, dh + 360])
    d_big_h = 2 * np.sqrt(cc) * np.sin(np.deg2rad(dh / 2))
    l_bar, c_bar = (L1 + L2) / 2, (cp1 + cp2) / 2
    apart, total = np.abs(hp1 - hp2), hp1 + hp2
    h_bar = np.select([cc == 0, apart <= 180, (apart > 180) & (total < 360),
                       (apart > 180) & (total >= 360)],
                      [total, total / 2, (total + 360) / 2, (total - 360) / 2])
    t = (1 - 0.17 * np.cos(np.deg2rad(h_bar - 30)) + 0.24 * np.cos(np.deg2rad(2 * h_bar))
         + 0.32 * np.cos(np.deg2rad(3 * h_bar + 6)) - 0.20 * np.cos(np.deg2rad(4 * h_bar - 63)))
    d_theta = 30 * np.exp(-(((h_bar - 275) / 25) ** 2))
    c_bar_p7 = c_bar**7
    r_c = 2 * np.sqrt(c_bar_p7 / (c_bar_p7 + 25**7))
    l50 = (l_bar - 50) ** 2
    s_l = 1 + (0.015 * l50) / np.sqrt(20 + l50)
    s_c = 1 + 0.045 * c_bar
    s_h = 1 + 0.015 * c_bar * t
    r_t = -np.sin(np.deg2rad(2 * d_theta)) * r_c
    return np.sqrt((dl / s_l) ** 2 + (dc / s_c) ** 2 + (d_big_h / s_h) ** 2
                   + r_t * (dc / s_c) * (d_big_h / s_h))


def compare(target, image, mask=None) -> dict:
    """Agreement of ``image`` with ``target``, both (H, W, 3) linear RGB.

    Args:
        target: the reference image (e.g. a Mitsuba render).
        image: the image judged (e.g. the fitted model's render).
        mask: optional (H, W) bool, pixels compared; default all.

    Returns:
        ``{"rmse", "psnr_db", "delta_e2000_mean", "delta_e2000_max", "n_pixels"}``:
        RMSE over pixels and channels (linear units); PSNR = 20 log10(peak /
        RMSE) with peak = max of the target over the compared pixels (inf
        when identical); CIEDE2000 mean and max over pixels (route in the
        module docstring).
    """
    t = np.asarray(target, dtype=np.float64)
    x = np.asarray(image, dtype=np.float64)
    if t.shape != x.shape or t.ndim != 3 or t.shape[-1] != 3:
        raise ValueError(f"compare: target {t.shape} and image {x.shape} must both be (H, W, 3)")
    if mask is None:
        mask = np.ones(t.shape[:2], dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != t.shape[:2]:
        raise ValueError(f"compare: mask {mask.shape} must be (H, W) = {t.shape[:2]}")
    tp, xp = t[mask], x[mask]
    if tp.size == 0:
        raise ValueError("compare: the mask selects no pixels")
    rmse = float(np.sqrt(np.mean(np.square(tp - xp))))
    peak = float(tp.max())
    with np.errstate(divide="ignore"):
        psnr = float("inf") if rmse == 0 else float(20.0 * np.log10(peak / rmse))
    de = delta_e2000(_lab(tp), _lab(xp))
    return {"rmse": rmse, "psnr_db": psnr, "delta_e2000_mean": float(de.mean()),
            "delta_e2000_max": float(de.max()), "n_pixels": int(mask.sum())}

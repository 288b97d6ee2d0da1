"""Image agreement metrics: RMSE, PSNR and CIEDE2000 colour difference.

ΔE route (colour-science): linear RGB, clipped to the display range [0, 1]
-> sRGB-encoded (IEC 61966-2-1 transfer function) -> CIE XYZ (sRGB
primaries, D65) -> CIE L*a*b* (D65) -> ``colour.delta_E(method="CIE 2000")``.
ΔE < 1 is commonly taken as not visible side by side; ~2.3 as a "just
noticeable difference".

References:
    Sharma, Wu, Dalal (2005), "The CIEDE2000 color-difference formula",
        Color Research & Application 30(1).
    IEC 61966-2-1:1999 (sRGB).
"""

from __future__ import annotations

import numpy as np


def _lab(linear_rgb: np.ndarray) -> np.ndarray:
    import colour

    encoded = colour.cctf_encoding(np.clip(linear_rgb, 0.0, 1.0), function="sRGB")
    xyz = colour.RGB_to_XYZ(encoded, colour.RGB_COLOURSPACES["sRGB"],
                            apply_cctf_decoding=True)
    white = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    return colour.XYZ_to_Lab(xyz, white)


def warm_up() -> None:
    """Import colour-science (with matplotlib, ~1 s) and score a one-pixel
    image, so that a later ``compare`` costs only its arithmetic."""
    one = np.full((1, 1, 3), 0.5)
    compare(one, one)


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
    import colour

    de = np.asarray(colour.delta_E(_lab(tp), _lab(xp), method="CIE 2000"), dtype=np.float64)
    return {"rmse": rmse, "psnr_db": psnr, "delta_e2000_mean": float(de.mean()),
            "delta_e2000_max": float(de.max()), "n_pixels": int(mask.sum())}

"""What the residual says about the model: where it sits, how structured it is,
and the systematic error it implies for the parameters.

Three pieces, all read from the residuals r and the Jacobian J at the solution:

* A pixel sandwich (``heteroscedastic``): where the residual's scatter differs
  from pixel to pixel beyond chance (shot noise: a bright highlight far
  noisier than the body), the statistical covariance is White's sandwich
  with every pixel its own block (HC3's leverage correction), not s^2 A^-1.
* A spatial-block sandwich (HAC) covariance. The fitted pixels are cut into
  square blocks of ``block_side`` pixels (about ``N_BLOCKS`` of them); with
  block scores g_b = J_b^T r_b and A = J^T J,

      V_hac = A^-1 (B / (B - n) sum_b g_b g_b^T) A^-1,

  which equals the Gauss-Newton s^2 A^-1 for white residuals and grows when
  the residuals are spatially correlated (a model that cannot follow the
  image, a discretisation error, a wrong light scale): each block then
  pushes the parameters its own way. The excess over the statistical
  covariance V_stat is reported as the systematic part only where it is
  significant: the diagonal ratio
  V_hac / V_stat of white residuals scatters about 1 with relative standard
  deviation about sqrt(2 / B), and an excess below ``SYS_SIGNIFICANCE`` of
  those deviations is taken as 0 (so fits to white-noise targets keep the
  Cramer-Rao errors).
* Residual energy per region of the sphere defined by its geometry:
  ``highlight`` (pixels whose normal is within ``HIGHLIGHT_ANGLE`` of a
  light's half vector, the scene's lights and an environment's sun cells),
  ``rim`` (pixels on the silhouette or seen at a grazing angle, cos_o <
  ``RIM_COS``) and ``body`` (the rest), each as RMSE over the noise level,
  plus the lag-1 correlation of neighbouring residuals (about 0 for white
  noise, near 1 for a smooth model error).

References:
    White (1980), Econometrica 48, "A heteroskedasticity-consistent
        covariance matrix estimator" (sandwich; HC1 factor N / (N - n)).
    Conley (1999), J. Econometrics 92, "GMM estimation with cross sectional
        dependence" (spatial blocks; here uniform weights within a block).
    Newey, West (1987), Econometrica 55 (HAC covariance).
"""

from __future__ import annotations

import numpy as np

#: Target number of spatial blocks over the fitted pixels.
N_BLOCKS = 64
#: Smallest block side (pixels): 2 x 2 blocks still average neighbours.
MIN_SIDE = 2
#: Excess of V_hac over V_stat (diagonal) counted as systematic only beyond
#: this many standard deviations sqrt(2 / B) of white residuals' ratio.
SYS_SIGNIFICANCE = 3.0
#: Highlight neighbourhood: normal within this angle (radians) of a light's
#: half vector (n.h >= cos), at any sub-pixel sample.
HIGHLIGHT_ANGLE = 0.25
#: Rim: a silhouette pixel (partly covered) or one seen at cos_o below this.
RIM_COS = 0.3
REGIONS = ("body", "highlight", "rim")


def pixel_regions(geometry) -> np.ndarray:
    """(P,) int region of each fitted pixel: 0 body, 1 highlight, 2 rim.

    Depends on the geometry alone (not on the parameters): kept with it
    (``Geometry.kept``, read-only), measured 13-30 ms each at 256^2."""
    return geometry.kept("regions", lambda: _regions(geometry))


def _regions(geometry) -> np.ndarray:
    hit = np.asarray(geometry.hit)
    c = geometry.cosines
    cos_o = np.asarray(c.cos_o)
    lit = np.asarray(geometry.light_weight) > 0
    label = np.zeros(hit.shape[0], dtype=np.int64)
    if cos_o.size and cos_o.shape[0] > 0:
        near = (np.asarray(c.cos_h) >= np.cos(HIGHLIGHT_ANGLE)) & lit
        label[near.any(axis=(0, 2))] = 1
        grazing = np.where(hit, cos_o.min(axis=0), 1.0).min(axis=1) < RIM_COS
    else:  # no lights: the view cosine from the normal and the camera ray
        cos_v = -np.sum(np.asarray(geometry.normal) * np.asarray(geometry.ray_dir), axis=-1)
        grazing = np.where(hit, cos_v, 1.0).min(axis=1) < RIM_COS
    sun = getattr(geometry, "sun", ())
    for index, cos, weight, _ in sun.groups() if sun else ():  # an environment's sun cells
        near = (np.asarray(cos.cos_h) >= np.cos(HIGHLIGHT_ANGLE)) & (np.asarray(weight) > 0)
        rows = np.asarray(index)[near.any(axis=0)]
        label[rows[rows < label.size]] = 1  # (shared pairs: a pixel not fitted is past the end)
    label[grazing | ~hit.all(axis=1)] = 2
    return label


def block_ids(pixel_index, width: int) -> tuple[np.ndarray, int]:
    """(P,) block index of each fitted pixel (flat index row * W + col) and the
    number of non-empty blocks."""
    pix = np.asarray(pixel_index, dtype=np.int64)
    side = max(MIN_SIDE, int(round(np.sqrt(pix.size / N_BLOCKS))))
    row, col = pix // width, pix % width
    key = (row // side) * (width // side + 1) + col // side
    # np.unique's inverse without its sort: the keys are few and small.
    present = np.zeros(int(key.max(initial=-1)) + 1, dtype=bool)
    present[key] = True
    rank = np.cumsum(present) - 1
    return rank[key], int(np.count_nonzero(present))


def sandwich(J, r, ids, n_blocks: int, gram=None):
    """V_hac (n, n) of the fit coordinates: J (N, n) the Jacobian of the
    residuals r (N,) (3 per pixel, channel fastest), ``ids`` (N // 3,) blocks;
    ``gram``: J^T J if the caller has it."""
    J = np.asarray(J, dtype=np.float64)
    n = J.shape[1]
    ids = np.asarray(ids)
    per = J.shape[0] // len(ids)  # residuals per pixel
    # Per pixel (P, n) in one pass (einsum: 1.4 ms at 256^2 against 1.9 for a
    # transposed product and a sum by a product), then per block by bincount
    # (~10x faster than np.add.at; the same sums up to the order of addition).
    Jr = np.einsum("pcn,pc->pn", J.reshape(-1, per, n),
                   np.asarray(r, dtype=np.float64).reshape(-1, per))
    g = np.zeros((n_blocks, n))
    for j in range(n):
        g[:, j] = np.bincount(ids, Jr[:, j], minlength=n_blocks)
    bread = np.linalg.pinv(J.T @ J if gram is None else gram, hermitian=True)
    meat = g.T @ g * n_blocks / max(n_blocks - n, 1)
    return bread @ meat @ bread


def systematic(cov_stat, cov_hac, n_blocks: int):
    """Systematic covariance (n, n): the significant excess of V_hac over V_stat.

    Per coordinate, var_sys = V_hac - V_stat where V_hac / V_stat exceeds
    1 + SYS_SIGNIFICANCE sqrt(2 / B), else 0; correlations follow V_hac.
    """
    return _excess(cov_stat, cov_hac, block_threshold(n_blocks))


def block_threshold(n_blocks: int) -> float:
    """The ratio V_hac / V_stat above which the block sandwich counts (``systematic``)."""
    return 1.0 + SYS_SIGNIFICANCE * np.sqrt(2.0 / max(n_blocks, 1))


def heteroscedastic(cov_stat, J, r, pixels: int, gram=None):
    """Covariance (n, n) that noise varying from pixel to pixel adds to the
    Gauss-Newton V_stat = s^2 (J^T J)^-1, which assumes one noise level: the
    significant excess of the pixel sandwich V_pix over V_stat.

    Shot noise grows with the signal, so a highlight far brighter than the
    body is far noisier; its parameters (Phong's e, a microfacet m) then have
    errors V_stat understates (``benchmarks/shot_noise.py``: bright_phong's e
    off by up to 6.8 of them, their spread 2 times theirs). V_pix = A^-1
    (sum_p g_p g_p^T) A^-1 with pixel scores g_p = J_p^T (I - H_pp)^-1 r_p:
    White's sandwich with every pixel its own block, its residual corrected
    for the pixel's leverage H_pp = J_p A^-1 J_p^T as HC3 does (MacKinnon and
    White; Long and Ervin find it the one to use in small samples): a sharp
    highlight's peak pixel carried 0.47 of a parameter, its residual that much
    below its noise (with (I - H_pp)^-1/2 instead, Bell and McCaffrey's, 1 of
    12 bright_phong draws kept e 3.2 stated errors off). Per coordinate j the
    excess counts where V_pix / V_stat > 1 + SYS_SIGNIFICANCE sqrt(2 / N_j):
    for white noise of one level V_pix scatters about V_stat with relative
    deviation sqrt(2 / N_j), N_j = (sum_p w_pj)^2 / sum_p w_pj^2 the effective
    number of pixels behind coordinate j (w_pj pixel p's share of V_stat).
    Correlations follow V_pix. ``J`` (N, n) and ``r`` (N,) as ``sandwich``
    takes them, N // ``pixels`` rows a pixel; ``gram``: J^T J.

    A model error that differs from pixel to pixel (a sharp lobe's sub-pixel
    quadrature) is counted here too: a residual cannot tell it from noise.

    References: White (1980), Econometrica 48; MacKinnon, White (1985), J.
    Econometrics 29 (HC3); Long, Ervin (2000), The American Statistician 54(3),
    "Using heteroscedasticity consistent standard errors in the linear
    regression model".
    """
    return pixel_excess(cov_stat, *pixel_sandwich(J, r, pixels, gram))


def pixel_excess(cov_stat, cov_pix, n_eff):
    """``heteroscedastic`` of a ``pixel_sandwich`` already made."""
    return _excess(cov_stat, cov_pix, pixel_threshold(n_eff))


def pixel_threshold(n_eff):
    """The ratio V_pix / V_stat above which the pixel sandwich counts
    (``heteroscedastic``), for ``n_eff`` effective pixels."""
    return 1.0 + SYS_SIGNIFICANCE * np.sqrt(2.0 / np.maximum(n_eff, 1.0))


def pixel_sandwich(J, r, pixels: int, gram=None):
    """(V_pix (n, n), N_j (n,)): ``heteroscedastic``'s pixel sandwich and each
    coordinate's effective number of pixels."""
    J = np.asarray(J, dtype=np.float64)
    n, per = J.shape[1], J.shape[0] // max(pixels, 1)
    bread = np.linalg.pinv(J.T @ J if gram is None else gram, hermitian=True)
    r = np.asarray(r, dtype=np.float64)
    meat, w1, w2 = np.zeros((n, n)), np.zeros(n), np.zeros(n)
    for p0, jp, jb in _chunks(J, pixels, bread):
        rp = r[p0 * per:(p0 + CHUNK) * per].reshape(-1, per)
        big = np.nonzero(np.einsum("pcn,pcn->p", jb, jp) > LEVERAGE)[0]  # trace of H_pp
        if big.size:  # (I - H_pp)^-1 r_p by each such pixel's eigenvectors (H_pp's <= 1)
            lam, u = np.linalg.eigh(np.einsum("pcn,pdn->pcd", jb[big], jp[big]))
            inv = 1.0 / np.maximum(1.0 - lam, 1e-12)
            rp = rp.copy()
            rp[big] = np.einsum("pcj,pj,pdj,pd->pc", u, inv, u, rp[big])
        g = np.einsum("pcn,pc->pn", jp, rp)
        meat += g.T @ g
        w = np.einsum("pcn,pcn->pn", jb, jb)
        w1 += w.sum(0)
        w2 += np.einsum("pn,pn->n", w, w)
    return bread @ meat @ bread, w1**2 / np.maximum(w2, 1e-300)


def _chunks(J, pixels: int, bread):
    """(first pixel, J_p (k, per, n), J_p A^-1 (k, per, n)) for ``CHUNK`` pixels at a
    time (no (N, n) temporaries: J alone is 0.2 GB at 1024^2)."""
    n, per = J.shape[1], J.shape[0] // max(pixels, 1)
    for p0 in range(0, pixels, CHUNK):
        jp = J[p0 * per:(p0 + CHUNK) * per].reshape(-1, per, n)
        yield p0, jp, (jp.reshape(-1, n) @ bread).reshape(jp.shape)


def few_pixels(J, pixels: int, gram=None, n_eff=None) -> dict:
    """Coordinates that rest on a pixel or two: {j: (N_j, pixels)} where the
    effective number of pixels behind coordinate j (``heteroscedastic``'s N_j)
    is below ``MIN_PIXELS``; ``pixels`` (indices into the fitted pixels) are
    those with ``GLINT_SHARE`` or more of its variance, the largest share
    first. ``J`` (N, n) and ``gram`` as ``heteroscedastic`` takes them;
    ``n_eff``: N_j where ``pixel_sandwich`` made it already (both are the same
    for J scaled by column).

    Such a coordinate (a glint, a sub-pixel highlight) has its error from those
    pixels' own residuals, one draw of their noise each: without a known noise
    level (``noise_sigma``) neither V_stat's one level, estimated from the
    image, nor the pixel sandwich can measure it.
    """
    J = np.asarray(J, dtype=np.float64)
    bread = np.linalg.pinv(J.T @ J if gram is None else gram, hermitian=True)
    if n_eff is None:
        w1, w2 = np.zeros(J.shape[1]), np.zeros(J.shape[1])
        for _, _, jb in _chunks(J, pixels, bread):
            w = np.einsum("pcn,pcn->pn", jb, jb)
            w1 += w.sum(0)
            w2 += np.einsum("pn,pn->n", w, w)
        n_eff = w1**2 / np.maximum(w2, 1e-300)
    few = np.nonzero((n_eff > 0) & (n_eff < MIN_PIXELS))[0]  # (0: a column without effect)
    if not few.size:
        return {}
    # (seldom: a pass over the few columns, each pixel's share of their variance)
    w = np.concatenate([np.einsum("pcn,pcn->pn", jb[..., few], jb[..., few])
                        for _, _, jb in _chunks(J, pixels, bread)])
    share = w / np.maximum(w.sum(0), 1e-300)
    out = {}
    for k, j in enumerate(few):
        big = np.nonzero(share[:, k] >= GLINT_SHARE)[0]
        out[int(j)] = (float(n_eff[j]), [int(p) for p in big[np.argsort(-share[big, k],
                                                                      kind="stable")]])
    return out


#: ``few_pixels``: a coordinate with fewer effective pixels than this rests on one or
#: two. Measured: every shipped case 9.0 (extreme_sharp_phong's rho_s) and more; a
#: glass sphere under a 3-degree sun (64^2, Mitsuba 4096 spp) 1.09 for eta, the sun's
#: glint one pixel with 96 % of it, the fit 7 stated errors off (the glint's Monte
#: Carlo noise ~3 %, the image's other pixels' ~0.1 %).
MIN_PIXELS = 3.0
#: ``few_pixels`` names the pixels holding at least this share of such a coordinate's
#: variance (the glass sphere's glint: 0.96, the next pixel 0.02).
GLINT_SHARE = 0.1
#: ``heteroscedastic`` corrects the residuals of pixels of more leverage than this
#: (the trace of H_pp) only: the others' variance is understated by under 2 %.
LEVERAGE = 0.01
#: ``heteroscedastic`` takes this many pixels at a time.
CHUNK = 1 << 16


def _excess(cov_base, cov_robust, thresh):
    """The excess of ``cov_robust`` over ``cov_base`` (n, n) on the coordinates where
    their diagonal ratio exceeds ``thresh`` (scalar or (n,)), else 0; correlations
    follow ``cov_robust``."""
    vs, vh = np.diag(cov_base), np.diag(cov_robust)
    ok = np.isfinite(vs) & np.isfinite(vh) & (vs > 0)
    excess = np.where(ok & (vh > thresh * np.where(ok, vs, 1.0)), vh - vs, 0.0)
    d = np.sqrt(np.maximum(vh, 1e-300))
    corr = np.where(np.outer(ok, ok), cov_robust / np.outer(d, d), 0.0)
    s = np.sqrt(excess)
    return corr * np.outer(s, s)


def region_stats(r, weights, labels, scale: float) -> dict:
    """Per region: pixels, RMSE of the residual / ``scale`` (the noise level)
    and its share of the residual energy. ``r``, ``weights``: (P, 3)."""
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3)
    used = np.asarray(weights).reshape(-1, 3) > 0
    e = np.where(used, r, 0.0) ** 2
    total = max(float(e.sum()), 1e-300)
    labels = np.asarray(labels)
    # Per region in one pass each (bincount), not three boolean gathers per region.
    k = len(REGIONS)
    pixels = np.bincount(labels, minlength=k)
    counts = np.bincount(labels, used @ np.ones(3), minlength=k)
    energy = np.bincount(labels, e @ np.ones(3), minlength=k)
    out = {}
    for i, name in enumerate(REGIONS):
        if counts[i] == 0:
            continue
        out[name] = {"pixels": int(pixels[i]),
                     "rmse_over_noise": float(np.sqrt(energy[i] / counts[i]) / scale)
                     if scale > 0 else 0.0,
                     "energy_share": float(energy[i] / total)}
    return out


def neighbour_pairs(pixel_index, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) (K,) each: indices of fitted pixels and of their right, then their
    lower, neighbour where that is fitted too (``pixel_index``: flat image
    indices of the fitted pixels, an image ``width`` wide)."""
    pix = np.asarray(pixel_index, dtype=np.int64)
    at = np.full(int(pix.max()) + width + 2, -1)
    at[pix] = np.arange(pix.size)
    i, j = [], []
    for step in (1, width):
        nb = at[pix + step]
        ok = (nb >= 0) & ((pix % width != width - 1) if step == 1 else True)
        i.append(np.nonzero(ok)[0])
        j.append(nb[ok])
    return np.concatenate(i), np.concatenate(j)


def neighbour_correlation(r, pixel_index, width: int, pairs=None) -> float:
    """Lag-1 correlation of the residual luminance between horizontally and
    vertically adjacent fitted pixels (0 for white noise, -> 1 when smooth);
    ``pairs``: ``neighbour_pairs`` of these pixels if made already. A pair
    whose neighbour's residual is not finite is left out."""
    # The channels' mean as a product (NumPy's mean over an axis of 3: 10x slower).
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3) @ np.full(3, 1.0 / 3.0)
    i, j = neighbour_pairs(pixel_index, width) if pairs is None else pairs
    a, b = r[i], r[j]
    ok = np.isfinite(b)
    if not ok.all():
        a, b = a[ok], b[ok]
    if a.size < 3:
        return 0.0
    a, b = a - a.mean(), b - b.mean()
    den = np.sqrt(np.sum(a * a) * np.sum(b * b))
    return float(np.sum(a * b) / den) if den > 0 else 0.0


#: A region whose residual RMSE is this many times the noise level fails the
#: fit even when the whole image passes. Measured on the shipped Mitsuba cases:
#: good fits reach 10.2 (Phong's highlight at 4 x 4 samples), rims 3-6; a
#: roughplastic target fitted with lambert + torrance_sparrow 150-620.
MAX_REGION_RATIO = 30.0
#: Residuals this correlated between neighbouring pixels are dominated by a
#: smooth model error, whatever the noise estimate says (white noise: ~0;
#: measured on the shipped cases: -0.04-0.29, env-lit 0.5-0.6; roughplastic 0.98) ...
STRUCTURE_CORR = 0.8
#: ... and fail the fit when that structured part, sqrt(corr) * RMSE, exceeds
#: this fraction of the mean value: the model's own discretisation (4 x 4 vs
#: 8 x 8 samples) leaves 5e-5 - 2.8e-4 (``_verdict.NOISE_FLOOR``).
MODEL_FLOOR = 1e-3
#: A uniform scale explaining this share of the residual energy is named
#: (measured: 0.88 for a target 0.7 times darker with the diffuse albedo held,
#: the specular lobe absorbing part of the scale).
SCALE_SHARE = 0.8
#: Starts whose final costs are within this relative gap of the best agree.
STARTS_AGREE = 1e-2
#: stderr_sys / stderr_stat above this gets a warning, when the residual RMSE is
#: at least SYS_WARN_LEVEL of the noise level (rounding residuals of a
#: noise-free inverse-crime fit, ~1e-10 of it, are structured but say nothing).
SYS_WARN = 3.0
SYS_WARN_LEVEL = 0.1


def where(adequacy: dict) -> str:
    """'at the rim (617 times the noise, 55 % of the residual energy)'."""
    regions = adequacy.get("regions", {})
    if not regions:
        return ""
    name, v = max(regions.items(), key=lambda kv: kv[1]["rmse_over_noise"])
    return (f"at the {name} ({v['rmse_over_noise']:.3g} times the noise level, "
            f"{100 * v['energy_share']:.0f} % of the residual energy)")


def starts_agree(starts: list) -> bool | None:
    """True if two or more starts ended at costs within STARTS_AGREE of the
    best, False if they did not, None with one start."""
    costs = np.array([s["cost"] for s in starts if np.isfinite(s["cost"])])
    if costs.size < 2:
        return None
    best = costs.min()
    return bool(np.sum(costs <= best * (1 + STARTS_AGREE) + 1e-300) >= 2)


def scale_share(err, model, used) -> tuple[float, float]:
    """(c, share): the residual's projection on the fitted image, model - target
    ~ c model, and the share of the residual energy it explains."""
    m = np.where(used, np.asarray(model, dtype=np.float64), 0.0)
    mm, ee = float(np.sum(m * m)), float(np.sum(err * err))
    if mm <= 0 or ee <= 0:
        return 0.0, 0.0
    c = float(np.sum(err * m)) / mm
    return c, c * c * mm / ee


#: Fitted pixels at a plateau of a target channel's maximum, with the fit above it,
#: that make a poor fit's cause a clipped highlight: no lobe renders a flat top, and
#: rendered or noisy radiance repeats its maximum by chance only (float32 EXR values
#: are 2^-24 apart). Measured on the quickstart's target clipped at 0.9 of its peak:
#: 76 pixels, a poor fit (17 times the noise) said to be "likely the model".
CLIPPED_PIXELS = 4


def clipped(target, model, used) -> tuple[int, float] | None:
    """(pixels, level): the fitted pixels whose value in some channel equals that
    channel's largest fitted value (> 0) while the fit is above it, and the
    lowest such level; None where no channel has ``CLIPPED_PIXELS`` of them.
    ``target``, ``model``, ``used``: (P, 3)."""
    t = np.asarray(target, dtype=np.float64)
    top = np.max(np.where(used, t, -np.inf), axis=0)  # (3,)
    at = used & (t == top) & (np.asarray(model) > t) & (top > 0)
    plateau = at.sum(axis=0) >= CLIPPED_PIXELS
    if not plateau.any():
        return None
    return int(at[:, plateau].any(axis=1).sum()), float(top[plateau].min())


def _below(level: float) -> float:
    """``level`` to six significant digits, rounded down (a ``saturation`` that
    drops the pixels at ``level``)."""
    step = 10.0 ** (np.floor(np.log10(level)) - 5)
    return float(np.floor(level / step) * step)


#: What a poor fit of the wrong brightness asks the user to check.
EXPOSURE_ADVICE = ("check the lights' intensity and the image's exposure, or fit it (exposure "
                   "in init, with one lobe parameter fixed as the reference)")


def cause(err, model, used, adequacy: dict, starts: list, target, edge: bool) -> str:
    """The likely cause of a poor fit, in words: light/exposure scale, a clipped
    highlight (``clipped`` of ``target`` (P, 3)), values beyond the boxes
    (``edge``: the best fit lies on a box's edge), the start, or the model (and
    where the residual sits)."""
    c, share = scale_share(err, model, used)
    loc = where(adequacy)
    if share > SCALE_SHARE:
        return (f"likely an exposure or light scale: the target is {1 - c:.4g} times the "
                f"fitted image ({100 * share:.0f} % of the residual is that uniform scale); "
                + EXPOSURE_ADVICE)
    flat = clipped(target, model, used)
    if flat is not None:
        return (f"likely a clipped highlight: {flat[0]} fitted pixels share a channel's "
                f"largest value ({flat[1]:.6g}), a flat top the fit rises above (residual "
                f"{loc}); leave them out with saturation = {_below(flat[1]):.6g} "
                "(fit.saturation in a config)")
    if edge:  # (an albedo held at 1 by a target 3 times brighter, per channel)
        return ("likely values beyond the parameters' boxes: the best fit presses on a box "
                "edge (above), so the image asks for more than the lobes can give; "
                f"{EXPOSURE_ADVICE}; residual {loc}")
    agree = starts_agree(starts)
    if agree:
        return (f"{len(starts)} starts agree, so it is not the start: the lobes cannot "
                f"explain the image {loc}; try another material model")
    if agree is False:
        return (f"the starts end at different costs: a local minimum is likely (residual "
                f"{loc}); try more starts (n_starts) or other initial values")
    return (f"likely the model: the lobes cannot explain the image {loc}; with one start "
            "a local minimum is not ruled out (n_starts > 1 tells)")


def judge(adequacy: dict, rel_rmse: float) -> str | None:
    """A failure message when the residual shows the model cannot explain the
    image (a region far above the noise, or a smooth residual above the
    model's discretisation level), else None."""
    regions = adequacy.get("regions", {})
    if regions:
        name, v = max(regions.items(), key=lambda kv: kv[1]["rmse_over_noise"])
        if v["rmse_over_noise"] > MAX_REGION_RATIO:
            return (f"poor fit: the residual at the {name} is {v['rmse_over_noise']:.3g} times "
                    f"the noise level (> {MAX_REGION_RATIO:g})")
    nc = adequacy.get("neighbour_correlation", 0.0)
    structured = np.sqrt(max(nc, 0.0)) * rel_rmse
    if nc > STRUCTURE_CORR and structured > MODEL_FLOOR:
        return (f"poor fit: the residual is smooth (neighbour correlation {nc:.2f}) and "
                f"{structured:.2g} of the mean value, above the model's own discretisation "
                f"({MODEL_FLOOR:g}), whatever the noise level")
    return None

"""Problem set-up: the fitted pixels, their data arrays and the free
parameters, checked and fixed once, before any solve."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._keep import recent
from .._math import finite_rows, to_device
from ..material import EXPOSURE_KEY, Material
from ..render import KEEP_BYTES, Renderer, cached_renderer
from .. import checks
from . import _args
from ._args import FitError as FitError
from ._noise import estimate_noise
from ._problem import LOSSES, Block, Data, Spec, z_from_params
from ._solvers import ATOL, RTOL, SOLVERS, default_max_steps

#: Starts on a box edge (e.g. the default attenuation 1) are moved this fraction
#: of the range inside: on the edge the coordinate is saturated and the
#: Jacobian column vanishes.
START_MARGIN = 1e-2


def select_pixels(renderer: Renderer, target, mask, exclude, saturation):
    """Rows of the renderer's active pixels to fit, and how many were dropped.

    ``mask``: ``"interior"`` (pixels whose every sub-pixel sample hits the
    sphere; default), ``"active"`` (any sample hits) or an (H, W) bool array.
    Pixels with a NaN/Inf value, in ``exclude``, or with a channel at/above
    ``saturation`` are dropped. Negative values are kept: zero-mean noise on a
    dark pixel is data, and dropping it would bias the fit.
    """
    geo = renderer.geometry
    h, w = renderer.scene.height, renderer.scene.width
    flat = target.reshape(h * w, 3)[renderer.pixel_index]
    hit = np.asarray(geo.hit)
    if isinstance(mask, str):
        if mask == "interior":  # every sample: a count by a product (all() over K: 2x slower)
            chosen = geo.kept("interior", lambda: (hit @ np.ones(hit.shape[1])) == hit.shape[1])
        elif mask == "active":
            chosen = np.ones(hit.shape[0], dtype=bool)
        else:
            raise FitError(f"mask = {mask!r}: expected 'interior', 'active' or an (H, W) array")
    else:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (h, w):
            raise FitError(f"mask has shape {m.shape}, expected {(h, w)}")
        chosen = m.reshape(-1)[renderer.pixel_index]
    good = finite_rows(flat)
    if exclude is not None:
        ex = np.asarray(exclude, dtype=bool)
        if ex.shape != (h, w):
            raise FitError(f"exclude has shape {ex.shape}, expected {(h, w)}")
        good &= ~ex.reshape(-1)[renderer.pixel_index]
    if saturation is not None:
        good &= np.all(np.where(np.isfinite(flat), flat, 0) < saturation, axis=1)
    rows = np.nonzero(chosen & good)[0]
    return rows, int(chosen.sum() - rows.size), flat


#: The fitted pixels' geometry shares the renderer's sun pairs (``Geometry.subset``'s
#: ``shared_sun``) when at least this share of its pixels is fitted: env_plastic
#: (96 % of its pixels) then renders 1.3 % of its pairs for nothing at every step, and
#: its first fit's set-up skips copying them (0.17 -> 0.03 s).
SHARED_SUN = 0.9


@recent(max_items=4, max_bytes=KEEP_BYTES)
def _fitted_geometry(renderer: Renderer, rows: bytes):
    """The renderer's geometry of the fitted ``rows`` (int64 bytes), on the device.

    Subset in NumPy (no per-op dispatch), then onto the device once: the
    solver must not copy host arrays on every call. Cached, as repeated fits
    of one scene (a series of images, a batch) select the same pixels.
    """
    idx = np.frombuffer(rows, dtype=np.int64)
    shared = idx.size >= SHARED_SUN * renderer.n_active
    return jax.tree_util.tree_map(to_device, renderer.geometry.subset(
        idx, shared_sun=shared)._replace(pixel_index=None, background_image=None))


def _free_blocks(material: Material, fixed_keys, bounds: dict) -> tuple[Block, ...]:
    """Free parameters as solver blocks, with their (possibly narrowed) boxes.

    Every key of ``bounds`` must be a free parameter, and its ``(lower,
    upper)`` a pair of numbers inside the parameter's box.
    """
    specs = material.param_specs()
    for key, pair in bounds.items():
        if key not in specs:
            raise FitError(f"bounds: unknown parameter {key!r} for lobes "
                           f"{list(material.lobes)}; known: {', '.join(specs)}")
        if key in fixed_keys:
            raise FitError(f"bounds: {key} is fixed, so bounds on it have no effect; remove "
                           "it from bounds, or fit it (give it in init, not in fixed)")
        if not isinstance(pair, (tuple, list, np.ndarray)) or len(pair) != 2:
            raise FitError(f"bounds for {key}: expected (lower, upper), got "
                           f"{checks.show(pair)}")
        for v in pair:
            try:
                checks.number(v)
            except checks.Problem as exc:
                raise FitError(f"bounds for {key}: {exc}") from None
    blocks = []
    for key, spec in specs.items():
        if key in fixed_keys:
            continue
        lo, hi = spec.lower, spec.upper
        if key in bounds:
            lo, hi = (float(v) for v in bounds[key])
            if not (spec.lower <= lo < hi <= spec.upper):
                raise FitError(f"bounds for {key} = {(lo, hi)} must satisfy "
                               f"{spec.lower:g} <= lower < upper <= {spec.upper:g}")
        blocks.append(Block(key, spec.size, spec.transform, lo, hi))
    return tuple(blocks)


def _all_fixed(material: Material, numeric_fixed: dict) -> FitError:
    """The error of a fit whose every parameter is fixed, naming what to change."""
    given = [k for k in material.param_specs() if k in numeric_fixed]
    by_default = [k for k, s in material.param_specs().items()
                  if not s.free and k not in numeric_fixed]
    what = []
    one = lambda keys: keys[0] if len(keys) == 1 else "one of " + ", ".join(keys)  # noqa: E731
    if given:
        what.append(f"remove {one(given)} from fixed (material.fixed in a config)")
    if by_default:
        what.append(f"fit {one(by_default)} (fixed by default) by giving it in init "
                    "(material.init)")
    return FitError("every parameter is fixed, so there is nothing to fit: "
                    + ", or ".join(what))


def _no_pixels(renderer: Renderer, mask, n_dropped: int, saturation) -> FitError:
    """The error of a fit without pixels, naming the key or argument to change."""
    scene = renderer.scene
    sphere = (f"scene.sphere.center = {list(scene.sphere.center)}, scene.sphere.radius = "
              f"{scene.sphere.radius:g}")
    if n_dropped:
        sat = f", or at/above saturation = {saturation:g}" if saturation is not None else ""
        return FitError(f"no pixels to fit: every selected pixel of the target is NaN/Inf, in "
                        f"exclude{sat}; check the target image (fit.target), exclude or "
                        "saturation (fit.saturation)")
    if not np.asarray(renderer.geometry.hit).any():
        return FitError(f"no pixels to fit: the sphere covers no pixel of the "
                        f"{scene.width}x{scene.height} image ({sphere}); put it in the "
                        "camera's view (scene.camera.origin, target, fov) or enlarge "
                        "scene.sphere.radius")
    if isinstance(mask, str) and mask == "interior":
        return FitError(f"no pixels to fit: no pixel lies wholly on the sphere ({sphere}; "
                        "mask = 'interior'); enlarge scene.sphere.radius or the image "
                        "(scene.width, scene.height), or fit mask = 'active'")
    return FitError("no pixels to fit: mask selects no pixel the sphere covers; check mask")


def _exposure_degenerate(material: Material, blocks, background) -> FitError | None:
    """The error of a free exposure the image cannot tell from the lobes' scales.

    Exact degeneracy: every lobe's radiance is linear in a free scale
    (``Lobe.scale``: a reflectance, mirror.rho_m), so exposure * c and every
    scale / c render the same image, unless a fitted pixel shows light of known
    absolute scale -- the environment behind the rim (``background()``: (P, 3)
    of the fitted pixels, asked for only with exposure free). A weaker trade (a
    fixed-scale specular lobe whose Fresnel eta can brighten it) is left to the
    identifiability checks.
    """
    free = {b.key for b in blocks}
    if EXPOSURE_KEY not in free:
        return None
    scales = [f"{lb.name}.{lb.scale}" if lb.scale else None for lb in material.lobe_objects]
    if not all(k in free for k in scales) or np.any(np.asarray(background()) != 0):
        return None
    names = ", ".join(scales)
    return FitError(
        f"exposure is free, but so is every lobe's brightness scale ({names}), so the image "
        "fixes only their products (exposure x c with each scale / c renders the same image) "
        f"and no fitted pixel has a known absolute scale: fix {names if len(scales) == 1 else 'one of ' + names} "
        "at a known value (a reference such as a measured white patch) or fix exposure "
        "(material.fixed in a config, fixed= in fitter.fit)")


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A fit set up: pixels, data arrays, free blocks; shared by fit and fit_batch.

    Immutable: holding parameters (``held``) returns a new Problem.
    """

    material: Material
    renderer: Renderer
    geometry: Any  # the renderer's geometry restricted to ``rows``
    rows: np.ndarray  # fitted rows of the renderer's active pixels
    n_dropped: int  # selected pixels dropped (NaN/Inf, excluded, saturated)
    targets: np.ndarray  # (B, P, 3) selected pixels, 0 where unusable
    weights: np.ndarray  # (B, P, 3); 0 where unusable
    init_full: dict  # every numeric parameter: initial, fixed or held value
    blocks: tuple[Block, ...]  # the free parameters
    loss: str
    loss_scale: float
    noise_sigma: float | None
    dtype: Any
    static: dict  # solver_name, rtol, atol, max_steps of the compiled solve
    noise: np.ndarray  # (B, 3) noise level estimated from each target
    unidentifiable: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    base_dir: str | None = None  # a relative envmap path is resolved against it
    alive: frozenset = frozenset()  # keys the start search saw change the cost (``_search``)
    # ``data``'s arrays by (b, stride): made once (a 256^2 fit asked four times,
    # ~1 ms of copies each); a replaced Problem starts empty (init=False).
    _data: dict = dataclasses.field(default_factory=dict, init=False, repr=False)

    @classmethod
    def make(cls, targets, scene, material, *, init=None, fixed=None, bounds=None,
             solver="levenberg_marquardt", mask="interior", exclude=None, weights=None,
             noise_sigma=None, loss="l2", loss_scale=None, saturation=None, max_steps=None,
             rtol=RTOL, atol=ATOL, dtype=jnp.float64, base_dir=None,
             estimate=True) -> Problem:
        """Check the arguments of ``fit`` (``_args``) and set up targets (B, H, W, 3).
        ``estimate``: estimate each target's noise (NaN without: the coarse
        stage's problem, which only solves)."""
        scene = _args.scene_of(scene)
        material = material if isinstance(material, Material) else Material.make(material)
        if solver not in SOLVERS:
            raise FitError(f"unknown solver {solver!r}; known: {', '.join(SOLVERS)}")
        if loss not in LOSSES:
            raise FitError(f"unknown loss {loss!r}; known: {', '.join(LOSSES)}")
        noise_sigma = _args.optional("noise_sigma", noise_sigma)
        loss_scale = _args.optional("loss_scale", loss_scale)
        saturation = _args.optional("saturation", saturation)
        max_steps = _args.optional("max_steps", max_steps)
        rtol, atol = _args.option("rtol", rtol), _args.option("atol", atol)
        dtype = _args.dtype_of(dtype)
        if base_dir is not None:
            base_dir = _args.text("base_dir", base_dir)
        init, fixed = _args.mapping(init, "init"), _args.mapping(fixed, "fixed")
        bounds = _args.mapping(bounds, "bounds")
        targets = _args.images(targets, "targets", scene)
        if targets.shape[1:] != (scene.height, scene.width, 3):
            raise FitError(f"target has shape {targets.shape[1:]}, expected "
                           f"{_args.image_shape(scene)}")
        wt = _args.weights_of(weights, scene)
        material = Material.given(material, {**init, **fixed})
        opt_keys = material.option_keys()
        numeric_fixed = {k: v for k, v in fixed.items() if k not in opt_keys}
        numeric_init = {k: v for k, v in init.items() if k not in opt_keys}
        overlap = set(numeric_fixed) & set(numeric_init)
        if overlap:
            raise FitError(f"{sorted(overlap)} given both as initial and as fixed values")
        init_full = material.full_params({**numeric_init, **numeric_fixed})
        fixed_keys = set(numeric_fixed) | {k for k, s in material.param_specs().items()
                                           if not s.free and k not in numeric_init}
        blocks = _free_blocks(material, fixed_keys, bounds)
        if not blocks:
            raise _all_fixed(material, numeric_fixed)

        renderer = cached_renderer(scene, material, dtype,
                                   os.path.abspath(base_dir) if base_dir else None)
        # Pixels are chosen on the first target; others mark their bad pixels by weight 0.
        rows, n_dropped, _ = select_pixels(renderer, targets[0], mask, exclude, saturation)
        if rows.size == 0:
            raise _no_pixels(renderer, mask, n_dropped, saturation)
        degenerate = _exposure_degenerate(material, blocks,
                                          lambda: np.asarray(renderer.geometry.background)[rows])
        if degenerate is not None:
            raise degenerate
        picked = targets.reshape(len(targets), -1, 3)[:, renderer.pixel_index[rows]]
        usable = finite_rows(picked)[..., None]
        if saturation is not None:
            usable &= np.all(np.where(np.isfinite(picked), picked, 0) < saturation,
                             axis=-1, keepdims=True)
        w = np.ones(picked.shape)
        if wt is not None:
            w = w * wt.reshape(-1, 3)[renderer.pixel_index[rows]]
            if not np.any(w > 0):
                raise FitError(f"no pixels to fit: weights are 0 on all {rows.size} selected "
                               "pixels; give the pixels to fit a weight > 0")
        if noise_sigma is not None:
            w = w / noise_sigma
        w = np.where(usable, w, 0.0)
        geometry = _fitted_geometry(renderer, rows.astype(np.int64).tobytes())
        interior = np.zeros(scene.height * scene.width, dtype=bool)
        interior[renderer.pixel_index[rows]] = True
        noise = [estimate_noise(t, interior.reshape(scene.height, scene.width)) if estimate
                 else np.full(3, np.nan) for t in targets]
        return cls(material=material, renderer=renderer, geometry=geometry, rows=rows,
                   n_dropped=n_dropped, targets=np.where(usable, picked, 0.0), weights=w,
                   init_full=init_full, blocks=blocks, loss=loss,
                   loss_scale=(loss_scale if loss_scale is not None
                               else (1.0 if noise_sigma else 0.01)),
                   noise_sigma=noise_sigma, dtype=dtype,
                   static={"solver_name": solver, "rtol": rtol, "atol": atol,
                           "max_steps": max_steps or default_max_steps(solver)},
                   noise=np.asarray(noise),
                   base_dir=os.path.abspath(base_dir) if base_dir else None)

    def cast(self, a):
        if isinstance(a, jax.Array):
            return jnp.asarray(a, dtype=self.dtype)
        return to_device(a, self.dtype)

    @property
    def spec(self) -> Spec:
        return Spec(self.material, self.renderer.env_type, self.blocks, self.loss,
                    self.loss_scale)

    def data(self, b: int | None, stride: int = 1) -> Data:
        """Arrays of target ``b`` (all targets stacked if None); every
        ``stride``-th fitted pixel only if ``stride`` > 1. The same arrays at
        each call (device arrays are immutable)."""
        if (b, stride) not in self._data:
            self._data[b, stride] = self._make_data(b, stride)
        return self._data[b, stride]

    def _make_data(self, b: int | None, stride: int) -> Data:
        free = {blk.key for blk in self.blocks}
        fixed = {k: self.cast(v) for k, v in self.init_full.items() if k not in free}
        sel = slice(None) if b is None else b
        geometry = self.geometry if stride == 1 else _fitted_geometry(
            self.renderer, self.rows[::stride].astype(np.int64).tobytes())
        pick = lambda a: self.cast(a[sel][..., ::stride, :])  # noqa: E731
        return Data(geometry, self.renderer.env, self.renderer.sphere,
                    pick(self.targets), pick(self.weights), fixed)

    def z_init(self):
        return z_from_params(self.spec, self.init_full, START_MARGIN)

    def fitted(self, b: int) -> np.ndarray:
        """(H, W) bool: the pixels of target ``b`` the fit uses (a weight > 0)."""
        scene = self.renderer.scene
        mask = np.zeros(scene.height * scene.width, dtype=bool)
        used = np.any(self.weights[b] > 0, axis=-1)
        mask[np.asarray(self.renderer.pixel_index)[self.rows[used]]] = True
        return mask.reshape(scene.height, scene.width)

    def pinned(self, values: dict) -> Problem:
        """This problem with the parameters ``values`` fixed there (``held``), as
        values fitted on the edge of their box (``_edge``), not unidentifiable."""
        return dataclasses.replace(self.held(list(values), [], values),
                                   unidentifiable=self.unidentifiable)

    def without(self, b: int | None, pixels, reasons) -> Problem:
        """This problem with the fitted ``pixels`` (indices into ``rows``) of target
        ``b`` (every target if None) weighted 0, ``reasons`` added to its warnings.
        The shapes stay: the compiled solve is reused."""
        weights = self.weights.copy()
        weights[slice(None) if b is None else b, np.asarray(pixels, dtype=np.int64)] = 0.0
        return dataclasses.replace(self, weights=weights,
                                   warnings=self.warnings + tuple(reasons))

    def held(self, keys, reasons, values=None) -> Problem:
        """This problem with parameters ``keys`` no longer free, ``reasons``
        added to its warnings, and held at ``values`` where given (else at
        their initial values)."""
        return dataclasses.replace(
            self, blocks=tuple(b for b in self.blocks if b.key not in keys),
            init_full={**self.init_full, **(values or {})},
            unidentifiable=self.unidentifiable + tuple(keys),
            warnings=self.warnings + tuple(reasons))

"""Camera rays through stratified sub-pixel samples (NumPy, float64).

The frame is Mitsuba's ``look_at``: forward = target - origin, image right =
forward x up, image up = right x forward (so, looking down -z with up = +y,
world +x is on the right). Pixel (row i, column j) covers film coordinates
[j, j+1] x [i, i+1]; row 0 is the top. With k x k supersampling the pixel
value is a k x k product quadrature of the box-filtered pixel (see
``pixel_rule``).
"""

from __future__ import annotations

import numpy as np

from .scene import PIXEL_RULES, Scene, SceneError as SceneError, check_scene


def camera_frame(scene: Scene):
    """(forward, right, up) unit vectors of the camera, each (3,), of a checked scene."""
    cam = scene.camera
    fwd, up = _unit(np.subtract(cam.target, cam.origin)), _unit(cam.up)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    return fwd, right, np.cross(right, fwd)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def pixel_rule(k: int, rule: str):
    """Sub-pixel sample offsets in [0, 1] and weights (summing to 1), each (k,).

    ``gauss``: k-point Gauss-Legendre nodes on [0, 1] -- exact for
    polynomials of degree 2k - 1 per axis, so smooth shading is box-averaged
    to far better than the midpoint rule with the same samples;
    ``midpoint``: centres of k equal sub-intervals (stratified grid).
    """
    if rule == "gauss":
        x, w = np.polynomial.legendre.leggauss(k)
        return 0.5 * (x + 1.0), 0.5 * w
    if rule == "midpoint":
        return (np.arange(k) + 0.5) / k, np.full(k, 1.0 / k)
    raise SceneError(f"scene.pixel_rule: {rule!r} is not allowed; allowed values: "
                     + ", ".join(repr(r) for r in PIXEL_RULES))


def film_samples(scene: Scene, pixels=None):
    """Film coordinates and weights of the k x k sub-pixel samples of every pixel.

    Returns:
        (x, y, weight): x, y of shape (H, W, k*k), x in [-1, 1] left to
        right, y in [-H/W, H/W] bottom to top; weight (k*k,) sums to 1.
        ``pixels``: flat indices (row * W + col); then x, y of those pixels
        only, each (P, 1, k*k).
    """
    k, w, h = scene.supersampling, scene.width, scene.height
    sub, wt = pixel_rule(k, scene.pixel_rule)
    if pixels is None:
        r, c = np.arange(h)[:, None], np.arange(w)[None, :]  # (H, 1), (1, W)
    else:
        r, c = np.divmod(np.asarray(pixels, dtype=np.int64), w)
        r, c = r[:, None], c[:, None]  # (P, 1) each
    # Sample index ky * k + kx, as camera_rays and the weights expect.
    sx = np.broadcast_to((c[..., None, None] + sub[None, :]), (*r.shape[:1], c.shape[1], k, k))
    sy = np.broadcast_to((r[..., None, None] + sub[:, None]), (*r.shape[:1], c.shape[1], k, k))
    x, y = film_coordinates(scene, sx, sy)
    weight = (wt[:, None] * wt[None, :]).reshape(k * k)
    return x.reshape(*x.shape[:2], k * k), y.reshape(*y.shape[:2], k * k), weight


def camera_rays(scene: Scene, pixels=None):
    """Ray origins and unit directions, each (H, W, k*k, 3), float64; checks the scene first.

    ``pixels``: flat indices (row * W + col), sorted; then only their rays,
    each (P, 1, k*k, 3) (a finer model of a few pixels need not trace them all).
    """
    check_scene(scene)
    x, y, _ = film_samples(scene, pixels)
    return rays_through(scene, x, y)


def film_coordinates(scene: Scene, sx, sy):
    """Film coordinates (x, y) of points at column ``sx``, row ``sy`` in pixel units
    (pixel (i, j) covers [j, j+1] x [i, i+1]): x in [-1, 1] left to right, y in
    [-H/W, H/W] bottom to top."""
    w, h = scene.width, scene.height
    return 2.0 * np.asarray(sx) / w - 1.0, (1.0 - 2.0 * np.asarray(sy) / h) * (h / w)


def rays_through(scene: Scene, x, y):
    """Ray origins and unit directions (..., 3), float64, through the film points
    ``x``, ``y`` (..., as ``film_coordinates`` gives them) of a checked scene."""
    cam = scene.camera
    fwd, right, up = camera_frame(scene)
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    origin = np.asarray(cam.origin, dtype=np.float64)
    if cam.type == "perspective":
        t = np.tan(np.radians(cam.fov) / 2.0)
        d = fwd + (t * x)[..., None] * right + (t * y)[..., None] * up
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(origin, d.shape)
    else:
        hw = cam.half_width
        o = origin + (hw * x)[..., None] * right + (hw * y)[..., None] * up
        d = np.broadcast_to(fwd, o.shape)
    return np.ascontiguousarray(o), np.ascontiguousarray(d)

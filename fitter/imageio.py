"""Image files through OpenImageIO: float files read as linear, integer files decoded.

All reads return float64 (H, W, 3) linear RGB; 8-bit (and 16-bit integer)
files are decoded as their colour space tag says, untagged ones from sRGB
(colour-science), unless the caller says how (``ENCODINGS``). Problems raise
``ImageError`` with one sentence naming the file.
"""

from __future__ import annotations

import os
import re
import tempfile

import numpy as np

from .errors import FitterError


class ImageError(FitterError):
    """An image that cannot be used (message names the file and the problem)."""


LINEAR_FORMATS = (".exr", ".hdr", ".pfm")


#: How a target's values are encoded (``fit.target_encoding``): "auto" takes float
#: files (EXR, HDR, float TIFF) as linear and integer files (8/16-bit PNG, TIFF,
#: JPEG) as their colour space says (OpenImageIO's ``oiio:ColorSpace``: a PNG's
#: gAMA chunk; ``LINEAR_SPACES`` linear, "g22_..." a 2.2 power law), else sRGB; "srgb"
#: and "linear" say it for any file (a 16-bit TIFF of linear raw values is
#: common, and nothing in an untagged TIFF tells).
ENCODINGS = ("auto", "srgb", "linear")
#: OpenImageIO's names of linear colour spaces (its colour-config-free defaults).
LINEAR_SPACES = ("linear", "lin_rec709_scene", "lin_rec709", "lin_srgb", "scene_linear")


def read_image_raw(path: str):
    """(pixels float64 (H, W, C), is_integer_format, OpenImageIO's colour space
    name or "") as stored, no conversion."""
    import OpenImageIO as oiio

    if not os.path.exists(path):
        raise ImageError(f"{path}: file not found")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageError(f"{path}: cannot read image ({oiio.geterror().strip() or 'unknown format'})")
    try:
        spec = inp.spec()
        is_int = _integer_bits(spec) > 0
        space = spec.get_string_attribute("oiio:ColorSpace", "")
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
    finally:
        inp.close()
    if pixels is None:
        raise ImageError(f"{path}: cannot decode image data")
    pixels = np.asarray(pixels, dtype=np.float64)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    return pixels, is_int, space


def _integer_bits(spec) -> int:
    """Bits of an integer-format image's channels (an OpenImageIO ``ImageSpec``), 0 for float."""
    import OpenImageIO as oiio

    return {oiio.UINT8: 8, oiio.INT8: 8, oiio.UINT16: 16, oiio.INT16: 16}.get(
        spec.format.basetype, 0)


def to_rgb(pixels: np.ndarray, path: str) -> np.ndarray:
    """Keep RGB of RGB/RGBA, expand grey; any other channel count is an error."""
    c = pixels.shape[-1]
    if c == 1:
        return np.repeat(pixels, 3, axis=-1)
    if c in (3, 4):
        return pixels[..., :3]
    raise ImageError(f"{path}: has {c} channels, expected 1, 3 or 4 (RGB[A])")


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    import colour

    return np.asarray(colour.cctf_decoding(values, function="sRGB"), dtype=np.float64)


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of linear values clipped to [0, 1] (the formula of
    ``colour.cctf_encoding(function="sRGB")``, written out: importing colour costs ~1 s)."""
    x = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def image_size(path: str) -> tuple[int, int]:
    """(width, height) of an image file from its header (``ImageError`` where it
    cannot be opened)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageError(f"{path}: cannot read image ({oiio.geterror().strip() or 'unknown'})")
    try:
        spec = inp.spec()
        return spec.width, spec.height
    finally:
        inp.close()


def read_image(path: str, with_saturation: bool = False, encoding: str = "auto"):
    """Read ``path`` as linear RGB float64 (H, W, 3).

    ``encoding``: one of ``ENCODINGS`` (integer values are scaled to [0, 1]
    first). With ``with_saturation=True`` also return a (H, W) bool mask of
    pixels clipped in an integer-format file (any channel at the format's
    maximum); it is all False for float files.
    """
    pixels, is_int, space = read_image_raw(path)
    rgb = to_rgb(pixels, path)
    saturated = np.zeros(rgb.shape[:2], dtype=bool)
    if is_int:
        saturated = np.any(rgb >= 1.0, axis=-1)
    if encoding == "auto" and is_int:
        encoding = _tagged(space)
    if encoding == "srgb":
        rgb = srgb_to_linear(rgb)
    elif isinstance(encoding, float):  # a pure power law
        rgb = np.maximum(rgb, 0.0) ** encoding
    return (rgb, saturated) if with_saturation else rgb


def _tagged(space: str):
    """How an integer file tagged ``space`` (OpenImageIO's colour space name) is
    decoded: "linear", a power law's exponent ("g22_rec709_scene", a PNG's gAMA
    of 1/2.2: 2.2) or "srgb" (also untagged)."""
    space = space.lower()
    gamma = re.match(r"g(\d)(\d)_", space)
    if space in LINEAR_SPACES:
        return "linear"
    return float(f"{gamma.group(1)}.{gamma.group(2)}") if gamma else "srgb"


def encoding_note(path: str, encoding: str) -> str | None:
    """A sentence where ``encoding`` "auto" decodes ``path``, a 16-bit integer
    file without a colour space tag, from sRGB (such files often hold a raw
    converter's linear values, and nothing in them tells), else None."""
    if encoding != "auto" or not path or not os.path.isfile(path):
        return None
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        return None
    try:
        spec = inp.spec()
        wide = _integer_bits(spec) == 16
        tagged = bool(spec.get_string_attribute("oiio:ColorSpace", ""))
    finally:
        inp.close()
    if not wide or tagged:
        return None
    return (f"{path}: 16-bit values without a colour space tag were decoded from sRGB; if "
            'they are linear (a raw converter\'s), set fit.target_encoding = "linear"')


def check_radiance(img: np.ndarray, where: str, what: str) -> None:
    """Raise ``ImageError`` unless every value of ``img`` (..., 3) is linear
    radiance: finite and >= 0. ``where`` begins the message (the file, and its
    key); ``what`` names the image (``"a target"``)."""
    bad = ~np.isfinite(img)
    if bad.any():
        raise ImageError(f"{where}: {int(bad.any(axis=-1).sum())} pixel(s) are NaN or Inf")
    if (img < 0).any():
        raise ImageError(f"{where}: {int((img < 0).any(axis=-1).sum())} pixel(s) have negative "
                         f"values (minimum {img.min():.3g}); {what} must be linear radiance >= 0")


def atomic_write(path: str, write) -> None:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it to ``path``.

    Readers see the old file or the whole new one, never a partial write.
    """
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(suffix=suffix, dir=folder, prefix=".tmp-")
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp files are 0600
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def current_umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_image(path: str, image: np.ndarray, attributes: dict | None = None) -> None:
    """Write linear RGB (H, W, 3): float32 EXR/HDR as is, 8-bit formats sRGB-encoded.

    ``attributes`` are extra metadata (e.g. a fixed ``"DateTime"`` for
    bit-for-bit reproducible files; OpenImageIO otherwise stamps the time).
    """
    import OpenImageIO as oiio

    image = np.asarray(image, dtype=np.float64)
    ext = os.path.splitext(path)[1].lower()
    if ext in LINEAR_FORMATS:
        data, fmt = image.astype(np.float32), oiio.FLOAT
    else:
        data = np.round(linear_to_srgb(image) * 255.0).astype(np.uint8)
        fmt = oiio.UINT8

    def write(tmp):
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise ImageError(f"{path}: no writer for this format ({oiio.geterror().strip()})")
        spec = oiio.ImageSpec(data.shape[1], data.shape[0], data.shape[2], fmt)
        for key, value in (attributes or {}).items():
            spec.attribute(key, value)
        if not out.open(tmp, spec) or not out.write_image(data):
            msg = out.geterror()
            out.close()
            raise ImageError(f"{path}: cannot write image ({msg})")
        out.close()

    atomic_write(path, write)

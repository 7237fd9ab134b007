"""JPEG for camera images, in the shape image_transport's `compressed` plugin puts on the wire:
a sensor_msgs/CompressedImage whose `data` is a plain JPEG file and whose `format` is
"<input encoding>; jpeg compressed <target>" (target "bgr8" for colour, "mono8" for grey), so
compressed_image_transport's subscriber, rqt_image_view and this package's GUI all read it.
Debian 12 packages image_transport but not that plugin; this module (Pillow, no ROS) stands in.
"""

import io
import struct

import numpy as np
from PIL import Image as PilImage

CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1}
"""Input encodings the compressor handles, with their channels per pixel."""


class InvalidImage(ValueError):
    """An image that cannot be compressed or a payload that cannot be decoded."""


def _checked_quality(quality):
    if (
        isinstance(quality, bool)
        or not isinstance(quality, (int, float, np.integer))
        or int(quality) != quality
        or not 1 <= quality <= 100
    ):
        raise ValueError(f"jpeg quality must be an integer 1..100, got {quality!r}")
    return int(quality)


def encode_jpeg(pixels, quality=75):
    """A JPEG file of an HxWx3 RGB or HxW (HxWx1) grey uint8 array; 4:2:0 chroma like OpenCV's
    default. ValueError for other shapes or dtypes, or a quality outside 1..100."""
    quality = _checked_quality(quality)
    pixels = np.asarray(pixels)
    if pixels.dtype != np.uint8:
        raise InvalidImage(f"pixels must be uint8, got {pixels.dtype}")
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[:, :, 0]
    if pixels.ndim == 2:
        mode = "L"
    elif pixels.ndim == 3 and pixels.shape[2] == 3:
        mode = "RGB"
    else:
        raise InvalidImage(f"pixels must be HxWx3 (RGB) or HxW (grey), got shape {pixels.shape}")
    if pixels.shape[0] == 0 or pixels.shape[1] == 0:
        raise InvalidImage(f"empty image {pixels.shape}")
    out = io.BytesIO()
    PilImage.fromarray(np.ascontiguousarray(pixels), mode).save(out, "JPEG", quality=quality)
    return out.getvalue()


def decode_jpeg(data, grey=False):
    """The pixels of a JPEG file: HxWx3 RGB uint8 (grey JPEGs expanded), or HxW with `grey`.
    InvalidImage when `data` is not a complete JPEG."""
    try:
        with PilImage.open(io.BytesIO(bytes(data))) as image:
            if image.format != "JPEG":
                raise InvalidImage(f"payload is {image.format or 'unknown'}, not JPEG")
            image.load()
            return np.asarray(image.convert("L" if grey else "RGB"))
    except InvalidImage:
        raise
    except (OSError, ValueError, SyntaxError) as exc:  # Pillow's errors for damaged or truncated files
        raise InvalidImage(f"cannot decode JPEG ({len(data)} bytes): {exc}") from exc


def compressed_format(encoding):
    """The `format` image_transport's compressed plugin writes for an image of `encoding`."""
    target = "mono8" if CHANNELS.get(encoding) == 1 else "bgr8"
    return f"{encoding}; jpeg compressed {target}"


def format_encoding(format_field):
    """The original encoding named by a CompressedImage `format` ("rgb8; jpeg compressed bgr8" ->
    "rgb8"), "" when the field has no encoding part (plain "jpeg")."""
    head, sep, _ = format_field.partition(";")
    return head.strip() if sep else ""


def image_pixels(encoding, width, height, step, data):
    """The pixels of a sensor_msgs/Image as RGB (HxWx3) or grey (HxW) uint8, the row padding cut.
    InvalidImage for other encodings, empty images or data shorter than height x step."""
    channels = CHANNELS.get(encoding)
    if channels is None:
        raise InvalidImage(f"encoding '{encoding}' not handled (only {', '.join(CHANNELS)})")
    if width <= 0 or height <= 0:
        raise InvalidImage(f"empty image ({width}x{height})")
    if step < width * channels:
        raise InvalidImage(f"step {step} is shorter than a row of {width} x {channels} bytes")
    if len(data) < step * height:
        raise InvalidImage(f"image data has {len(data)} bytes, expected {height} rows of {step}")
    rows = np.frombuffer(data, dtype=np.uint8, count=step * height).reshape(height, step)
    pixels = rows[:, : width * channels].reshape(height, width, channels)
    if channels == 1:
        return pixels[:, :, 0]
    return pixels[:, :, ::-1] if encoding == "bgr8" else pixels


def resize_pixels(pixels, width, height):
    """RGB (HxWx3) or grey (HxW) uint8 pixels at width x height: unchanged when already that size,
    else resampled with Pillow's box filter (each output pixel the mean of the input it covers)."""
    pixels = np.asarray(pixels)
    if pixels.shape[1] == width and pixels.shape[0] == height:
        return pixels
    image = PilImage.fromarray(np.ascontiguousarray(pixels))
    return np.asarray(image.resize((int(width), int(height)), PilImage.Resampling.BOX))


def compress_image(encoding, width, height, step, data, quality=75):
    """(format, JPEG bytes) of a sensor_msgs/Image's fields, as the compressed plugin sends them."""
    return compressed_format(encoding), encode_jpeg(image_pixels(encoding, width, height, step, data), quality)


def psnr_db(reference, decoded):
    """Peak signal-to-noise ratio in dB of two uint8 arrays of one shape (inf when equal)."""
    reference, decoded = np.asarray(reference, np.float64), np.asarray(decoded, np.float64)
    if reference.shape != decoded.shape:
        raise ValueError(f"shapes differ: {reference.shape} vs {decoded.shape}")
    mse = float(np.mean((reference - decoded) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def camera_test_image(width=320, height=240, seed=0):
    """An RGB uint8 scene with what a camera sees in the hall: smooth shading, hard edges and a
    little sensor noise (flat colour would flatter JPEG, pure noise would defeat it)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    image = np.empty((height, width, 3), np.float64)
    image[:, :, 0] = 90 + 80 * x / width
    image[:, :, 1] = 110 + 60 * y / height
    image[:, :, 2] = 140 - 50 * (x + y) / (width + height)
    floor = y > 0.6 * height
    image[floor] = [70, 70, 75]
    for i in range(6):  # shelves and pipes: rectangles of a few colours
        x0, y0 = int((0.05 + 0.15 * i) * width), int((0.15 + 0.05 * (i % 3)) * height)
        image[y0 : y0 + height // 3, x0 : x0 + width // 12] = [(40 * i) % 255, 200 - 25 * i, 60 + 30 * i]
    image += rng.normal(0.0, 3.0, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


# JPEG start-of-frame markers (baseline, extended, progressive, lossless; not DHT/JPG/DAC).
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def jpeg_dimensions(data):
    """(width, height) from a JPEG file's start-of-frame header without decoding it, or None when
    `data` is not a JPEG or has no frame header (as delivered: what the receiver would show)."""
    view = memoryview(data)
    if len(view) < 4 or view[0] != 0xFF or view[1] != 0xD8:
        return None
    i = 2
    while i + 4 <= len(view):
        if view[i] != 0xFF:
            return None
        marker = view[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length
            i += 2
            continue
        (length,) = struct.unpack_from(">H", view, i + 2)
        if marker in _SOF:
            if i + 9 > len(view):
                return None
            height, width = struct.unpack_from(">HH", view, i + 5)
            return width, height
        if marker == 0xDA:  # start of scan before any frame header
            return None
        i += 2 + length
    return None

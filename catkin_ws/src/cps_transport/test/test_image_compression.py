"""JPEG camera compression: round trip within a PSNR bound, the compressed plugin's format
strings, encodings and bad input."""

import io

import numpy as np
import pytest

from cps_transport.image_compression import (
    InvalidImage,
    camera_test_image,
    compress_image,
    compressed_format,
    decode_jpeg,
    encode_jpeg,
    format_encoding,
    image_pixels,
    jpeg_dimensions,
    psnr_db,
)


@pytest.mark.parametrize("width,height", [(320, 240), (640, 480)])
def test_round_trip_stays_within_psnr_bound_and_shrinks(width, height):
    rgb = camera_test_image(width, height)
    data = encode_jpeg(rgb, 75)
    assert data[:2] == b"\xff\xd8"  # a plain JPEG file, as cv::imencode writes
    decoded = decode_jpeg(data)
    assert decoded.shape == rgb.shape and decoded.dtype == np.uint8
    assert psnr_db(rgb, decoded) > 30.0
    assert len(data) < rgb.nbytes / 8


def test_quality_trades_size_for_fidelity():
    rgb = camera_test_image()
    low, high = encode_jpeg(rgb, 20), encode_jpeg(rgb, 95)
    assert len(low) < len(high)
    assert psnr_db(rgb, decode_jpeg(low)) < psnr_db(rgb, decode_jpeg(high))


@pytest.mark.parametrize("quality", [0, 101, 50.5, "high", True])
def test_quality_outside_1_to_100_is_refused(quality):
    with pytest.raises(ValueError, match="quality"):
        encode_jpeg(camera_test_image(32, 24), quality)


def test_format_strings_are_those_of_image_transport_compressed():
    assert compressed_format("rgb8") == "rgb8; jpeg compressed bgr8"
    assert compressed_format("bgr8") == "bgr8; jpeg compressed bgr8"
    assert compressed_format("mono8") == "mono8; jpeg compressed mono8"
    assert format_encoding("rgb8; jpeg compressed bgr8") == "rgb8"
    assert format_encoding("jpeg") == ""


def test_bgr8_and_mono8_come_out_as_the_same_picture():
    rgb = camera_test_image(160, 120)
    bgr = np.ascontiguousarray(rgb[:, :, ::-1])
    fmt, data = compress_image("bgr8", 160, 120, 480, bgr.tobytes())
    assert fmt == "bgr8; jpeg compressed bgr8"
    assert psnr_db(rgb, decode_jpeg(data)) > 30.0  # red stays red: channels swapped back
    grey = rgb[:, :, 1]
    padded = np.zeros((120, 168), np.uint8)
    padded[:, :160] = grey
    fmt, data = compress_image("mono8", 160, 120, 168, padded.tobytes())
    assert fmt == "mono8; jpeg compressed mono8"
    assert psnr_db(grey, decode_jpeg(data, grey=True)) > 30.0
    assert decode_jpeg(data).shape == (120, 160, 3)


def test_row_padding_is_cut():
    rgb = camera_test_image(10, 4)
    padded = np.zeros((4, 40), np.uint8)
    padded[:, :30] = rgb.reshape(4, 30)
    np.testing.assert_array_equal(image_pixels("rgb8", 10, 4, 40, padded.tobytes()), rgb)


@pytest.mark.parametrize(
    "encoding,width,height,step,size,match",
    [
        ("rgba8", 4, 4, 16, 64, "not handled"),
        ("16UC1", 4, 4, 8, 32, "not handled"),
        ("rgb8", 0, 4, 0, 0, "empty"),
        ("rgb8", 4, 4, 8, 64, "step"),
        ("rgb8", 4, 4, 12, 47, "bytes"),
    ],
)
def test_bad_images_are_refused_with_the_reason(encoding, width, height, step, size, match):
    with pytest.raises(InvalidImage, match=match):
        compress_image(encoding, width, height, step, bytes(size))


def test_damaged_payloads_are_refused():
    data = encode_jpeg(camera_test_image(64, 48))
    for bad in (b"", b"not a jpeg", data[: len(data) // 2]):
        with pytest.raises(InvalidImage):
            decode_jpeg(bad)
    import io

    from PIL import Image

    png = io.BytesIO()
    Image.fromarray(camera_test_image(8, 8)).save(png, "PNG")
    with pytest.raises(InvalidImage, match="not JPEG"):
        decode_jpeg(png.getvalue())


@pytest.mark.parametrize("width, height", [(640, 480), (320, 240), (160, 120), (17, 9)])
def test_a_jpegs_dimensions_are_read_from_its_frame_header(width, height):
    data = encode_jpeg(np.zeros((height, width, 3), np.uint8), quality=75)
    assert jpeg_dimensions(data) == (width, height)
    assert jpeg_dimensions(encode_jpeg(np.zeros((height, width), np.uint8))) == (width, height)


def test_a_payload_without_a_frame_header_has_no_dimensions():
    data = encode_jpeg(np.zeros((8, 8, 3), np.uint8))
    for bad in (b"", b"\xff\xd8", b"not a jpeg", data[:20], b"\xff\xd8\xff\xda\x00\x02"):
        assert jpeg_dimensions(bad) is None, bad


def test_a_serialized_compressed_images_dimensions():
    from sensor_msgs.msg import CompressedImage

    from cps_transport.topic_stats import compressed_image_dimensions

    msg = CompressedImage(format="rgb8; jpeg compressed bgr8", data=encode_jpeg(np.zeros((240, 320, 3), np.uint8)))
    msg.header.frame_id = "jackal/camera"
    buff = io.BytesIO()
    msg.serialize(buff)
    assert compressed_image_dimensions(buff.getvalue()) == (320, 240)
    assert compressed_image_dimensions(buff.getvalue()[:40]) is None
    assert compressed_image_dimensions(b"\x00" * 8) is None

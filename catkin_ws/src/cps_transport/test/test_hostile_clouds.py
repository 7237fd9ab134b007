"""Fuzz (hypothesis) of the Draco encoder and decoder with hostile clouds and payloads: a message
is either coded or refused with InvalidCloud/DracoError (the reason a node counts); nothing else
escapes, and what comes out is a cloud the readers accept with finite coordinates."""

import struct

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import PointField

from cps_harness.hostile_clouds import FIELD_NAMES, hostile_clouds, hostile_value_clouds, packed_cloud, wire_copy
from cps_transport.cloud_levels import LEAF_FIELD
from cps_transport.draco import DracoDecoder, DracoEncoder, DracoError, declared_points, leaf_of_compressed
from cps_transport.pointcloud import InvalidCloud, cloud_to_array, xyz_of

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ENCODER = DracoEncoder(leaf_size_m=0.05, fields="all")
DECODER = DracoDecoder()


def _good_compressed():
    rng = np.random.default_rng(13)
    out = []
    for n, extras in ((30, False), (200, True)):
        xyz = rng.uniform(-5, 5, (n, 3)).astype(np.float32)
        columns = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
        if extras:
            columns.update(
                intensity=rng.uniform(0, 1, n).astype(np.float32), rgb=rng.integers(0, 2**24, n).astype(np.uint32)
            )
        out.append(ENCODER.encode(packed_cloud(columns)))
    return out


GOOD_COMPRESSED = _good_compressed()
PAYLOAD_FAULTS = ("truncate", "flip", "random", "fields", "size", "empty", "none")


@st.composite
def hostile_compressed(draw):
    """A CompressedPointCloud2 whose payload is cut, flipped or random, or whose description
    (format, fields, height x width) no longer matches it."""
    msg = wire_copy(draw(st.sampled_from(GOOD_COMPRESSED)))
    payload = bytearray(msg.compressed_data)
    how = draw(st.sampled_from(PAYLOAD_FAULTS))
    if how == "truncate":
        payload = payload[: draw(st.integers(0, len(payload) - 1))]
    elif how == "flip":
        for _ in range(draw(st.integers(1, 8))):
            payload[draw(st.integers(0, len(payload) - 1))] ^= 1 << draw(st.integers(0, 7))
    elif how == "random":
        payload = bytearray(draw(st.binary(min_size=0, max_size=300)))
    elif how == "fields":
        msg.fields = [
            PointField(
                name=draw(st.sampled_from(FIELD_NAMES)),
                offset=draw(st.integers(0, 64)),
                datatype=draw(st.integers(0, 9)),
                count=draw(st.sampled_from((0, 1, 2))),
            )
            for _ in range(draw(st.integers(0, 5)))
        ]
    elif how == "size":
        msg.height, msg.width = draw(st.integers(0, 3)), draw(st.integers(0, 50))
    elif how == "empty":
        payload = bytearray()
    msg.compressed_data = bytes(payload)
    return wire_copy(msg)


def _decodes_to_finite_points(compressed):
    xyz = xyz_of(cloud_to_array(DECODER.decode(compressed)))
    assert len(xyz) and np.isfinite(xyz).all()


@FUZZ
@given(hostile_clouds())
def test_the_encoder_codes_or_refuses_every_cloud(cloud):
    try:
        compressed = ENCODER.encode(cloud)
    except (InvalidCloud, DracoError):
        return
    _decodes_to_finite_points(compressed)


@FUZZ
@given(hostile_value_clouds())
def test_hostile_coordinates_and_layouts_are_coded_or_refused_with_a_reason(pair):
    cloud, mutation = pair
    try:
        compressed = ENCODER.encode(cloud)
    except (InvalidCloud, DracoError) as exc:
        assert str(exc)
        return
    assert mutation not in ("xyz_count", "drop_z", "truncate"), f"a cloud with a '{mutation}' fault was coded"
    _decodes_to_finite_points(compressed)


@FUZZ
@given(hostile_compressed())
def test_the_decoder_decodes_or_refuses_every_payload(compressed):
    try:
        _decodes_to_finite_points(compressed)
    except (InvalidCloud, DracoError):
        pass


def test_a_payload_declaring_more_points_than_its_cloud_is_refused_before_decoding():
    """One flipped bit in the point count asked Draco for 1.07 G points: the fuzz test's worker grew
    to 8 GB and was killed. The header is read first; nothing is allocated for a count the message
    does not have room for, and a header that cannot be read is refused with the reason."""
    msg = wire_copy(GOOD_COMPRESSED[0])
    payload = bytes(msg.compressed_data)
    assert declared_points(payload) == msg.height * msg.width
    for count in (2**30, msg.height * msg.width + 1, 0, -5):
        msg.compressed_data = payload[:11] + struct.pack("<i", count) + payload[15:]
        try:
            DECODER.decode(msg)
            raise AssertionError(f"decoded a payload declaring {count} points")
        except DracoError as exc:
            assert f"declares {count} points" in str(exc)
    # a message whose own size is as hostile as its payload's count
    huge = wire_copy(msg)
    huge.height, huge.width = 1, 2**30
    huge.compressed_data = payload[:11] + struct.pack("<i", 2**30) + payload[15:]
    try:
        DECODER.decode(huge)
        raise AssertionError("decoded a payload of 2**30 points in a message of as many")
    except DracoError as exc:
        assert "byte limit of a cloud" in str(exc)
    # the rate limiter reads a cloud's leaf by decoding it: bounded the same way
    leafy = wire_copy(msg)
    leafy.compressed_data = payload[:11] + struct.pack("<i", 2**30) + payload[15:]
    leafy.fields = list(leafy.fields) + [PointField(name=LEAF_FIELD, offset=12, datatype=PointField.FLOAT32, count=1)]
    try:
        leaf_of_compressed(leafy)
        raise AssertionError("read the leaf of a payload declaring 2**30 points")
    except DracoError as exc:
        assert f"declares {2**30} points" in str(exc)
    # metadata (the encoder's attribute names) whose one entry states a 268 MB value: Draco would
    # allocate it before finding the payload short
    huge_entry = payload[:9] + b"\x00\x80" + b"\x00" + b"\x01" + b"\x01a" + b"\xff\xff\xff\x7f" + b"\x00" * 8
    for bad, words in (
        (b"DRACX" + payload[5:], "no DRACO magic"),
        (payload[:5] + b"\x01" + payload[6:], "version 1."),
        (payload[:7] + b"\x01" + payload[8:], "not a point cloud"),
        (payload[:8], "shorter than a Draco header"),
        (payload[:13], "point count of 4 bytes at byte 11 runs past the payload's 13 bytes"),
        (huge_entry, "metadata value of 268435455 bytes"),
    ):
        msg.compressed_data = bad
        try:
            DECODER.decode(msg)
            raise AssertionError(f"decoded a payload with {words}")
        except DracoError as exc:
            assert words in str(exc), exc


def test_a_cloud_with_x_of_count_3_or_a_point_beyond_the_coder_is_refused():
    xyz = np.ones((4, 3), np.float32)
    cloud = packed_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    cloud.fields[0].count = 3
    try:
        ENCODER.encode(cloud)
        raise AssertionError("coded a cloud whose x has count 3")
    except InvalidCloud as exc:
        assert "count 3" in str(exc)
    xyz[0] = (3.0e38, 0.0, 0.0)
    try:
        ENCODER.encode(packed_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}))
        raise AssertionError("coded a cloud spanning 3e38 m")
    except InvalidCloud as exc:
        assert "spanning" in str(exc)

"""Draco round trips within the quantization bound and with the kept fields, a payload Google's
reference draco_decoder reads, and every malformed input rejected with a clear error."""

import os
import subprocess
import zlib

import numpy as np
import pytest
from sensor_msgs.msg import PointField

from cps_harness.synthetic_clouds import depth_camera_cloud, lidar_cloud
from cps_transport.draco import DracoDecoder, DracoEncoder, DracoError, bits_for_tolerance, parse_fields
from cps_transport.pointcloud import InvalidCloud, array_to_cloud, cloud_to_array, xyz_of
from cps_transport.voxel import voxel_downsample

REFERENCE_DECODER = "/usr/bin/draco_decoder"  # Debian's package "draco"


def _filtered(msg, leaf):
    points = cloud_to_array(msg)
    extras = {name: points[name] for name in points.dtype.names if name not in "xyz"}
    centroids, averaged = voxel_downsample(xyz_of(points), leaf, extras)
    return array_to_cloud({"x": centroids[:, 0], "y": centroids[:, 1], "z": centroids[:, 2], **averaged})


@pytest.fixture(scope="module")
def depth():
    return depth_camera_cloud(width=320, height=240)


@pytest.fixture(scope="module")
def lidar():
    return lidar_cloud(samples_per_ring=600)


@pytest.mark.parametrize("leaf", [0.01, 0.1, 0.5])
def test_xyz_round_trip_within_half_a_leaf(depth, leaf):
    cloud = _filtered(depth, leaf)
    encoder = DracoEncoder(leaf_size_m=leaf)
    compressed = encoder.encode(cloud)
    decoded = DracoDecoder().decode(compressed)
    assert [f.name for f in decoded.fields] == ["x", "y", "z"]
    error = np.abs(xyz_of(cloud_to_array(decoded)) - xyz_of(cloud_to_array(cloud))).max()
    assert error <= encoder.last_info.position_error_bound_m <= leaf / 2
    assert len(compressed.compressed_data) < len(cloud.data) / 4
    assert decoded.header.frame_id == cloud.header.frame_id


def test_explicit_tolerance_and_fixed_bits(depth):
    cloud = _filtered(depth, 0.05)
    original = xyz_of(cloud_to_array(cloud))
    tight = DracoEncoder(position_tolerance_m=0.001)
    error = np.abs(xyz_of(cloud_to_array(DracoDecoder().decode(tight.encode(cloud)))) - original).max()
    assert error <= 0.001
    fixed = DracoEncoder(quantization_bits=14)
    fixed.encode(cloud)
    assert fixed.last_info.position_bits == 14


def test_kept_fields_depth_rgb_exact(depth):
    cloud = _filtered(depth, 0.1)
    decoded = DracoDecoder().decode(DracoEncoder(leaf_size_m=0.1, fields="xyz,rgb").encode(cloud))
    assert [f.name for f in decoded.fields] == ["x", "y", "z", "rgb"]
    assert np.array_equal(cloud_to_array(decoded)["rgb"].view(np.uint32), cloud_to_array(cloud)["rgb"].view(np.uint32))


def test_all_lidar_fields_integers_exact_floats_within_step(lidar):
    cloud = _filtered(lidar, 0.01)
    decoded = cloud_to_array(DracoDecoder().decode(DracoEncoder(leaf_size_m=0.01, fields="all").encode(cloud)))
    original = cloud_to_array(cloud)
    assert decoded.dtype.names == ("x", "y", "z", "intensity", "ring", "time")
    assert np.array_equal(decoded["ring"], original["ring"]) and decoded["ring"].dtype == np.uint16
    for name in ("intensity", "time"):
        step = np.ptp(original[name]) / (2**16 - 1)
        assert np.abs(decoded[name] - original[name]).max() <= step / 2 + 1e-6


def test_lossless_is_bit_exact(lidar):
    cloud = lidar  # unfiltered, every field, float64 added below
    points = cloud_to_array(cloud)
    columns = {name: points[name] for name in points.dtype.names}
    columns["time"] = columns["time"].astype(np.float64) + 1.0e9  # float64 field, needs all 64 bits
    columns["signed"] = (np.arange(len(points)) - 500).astype(np.int32)
    original = array_to_cloud(columns)
    decoded = cloud_to_array(DracoDecoder().decode(DracoEncoder(lossless=True, fields="all").encode(original)))
    for name, values in columns.items():
        assert decoded[name].dtype == values.dtype, name
        assert np.array_equal(decoded[name], values), name


def test_float64_positions_round_trip():
    rng = np.random.default_rng(3)
    xyz = rng.random((1000, 3)) * 20 - 10
    cloud = array_to_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    assert cloud.fields[0].datatype == PointField.FLOAT64
    decoded = cloud_to_array(DracoDecoder().decode(DracoEncoder(position_tolerance_m=0.005).encode(cloud)))
    assert decoded.dtype["x"] == np.float64
    assert np.abs(xyz_of(decoded) - xyz).max() <= 0.005


def test_organized_cloud_with_nans_is_stripped_counted_and_unorganized(depth):
    points = cloud_to_array(depth)
    n_nan = int((~np.isfinite(xyz_of(points)).all(axis=1)).sum())
    assert n_nan > 0
    encoder = DracoEncoder(position_tolerance_m=0.01, fields="xyz,rgb")
    compressed = encoder.encode(depth)
    assert (compressed.height, compressed.width) == (depth.height, depth.width)
    assert encoder.last_info.points_nan == n_nan
    decoded = DracoDecoder().decode(compressed)
    assert decoded.height == 1 and decoded.width == depth.width * depth.height - n_nan and decoded.is_dense
    assert np.isfinite(xyz_of(cloud_to_array(decoded))).all()


@pytest.mark.skipif(not os.path.exists(REFERENCE_DECODER), reason="Debian package draco not installed")
def test_reference_draco_decoder_reads_our_payload(depth, tmp_path):
    cloud = _filtered(depth, 0.1)
    compressed = DracoEncoder(leaf_size_m=0.1, fields="xyz,rgb").encode(cloud)
    (tmp_path / "cloud.drc").write_bytes(bytes(compressed.compressed_data))
    result = subprocess.run(
        [REFERENCE_DECODER, "-i", str(tmp_path / "cloud.drc"), "-o", str(tmp_path / "cloud.ply")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    ply = (tmp_path / "cloud.ply").read_bytes()
    header, body = ply.split(b"end_header\n", 1)
    header = header.decode()
    assert f"element vertex {cloud.width}" in header, header
    properties = [line.split() for line in header.splitlines() if line.startswith("property")]
    assert [p[-1] for p in properties][:3] == ["x", "y", "z"]
    assert "binary_little_endian" in header
    row = np.dtype([(p[-1], {"float": "<f4", "uchar": "u1"}[p[1]]) for p in properties])
    vertices = np.frombuffer(body, dtype=row, count=cloud.width)
    ours = xyz_of(cloud_to_array(DracoDecoder().decode(compressed)))
    theirs = np.stack([vertices[a] for a in "xyz"], axis=1)
    np.testing.assert_allclose(np.sort(theirs, axis=0), np.sort(ours, axis=0), atol=1e-5)


def test_parse_fields_and_tolerance_bits():
    assert parse_fields("xyz") == ("x", "y", "z")
    assert parse_fields("xyz, rgb,intensity") == ("x", "y", "z", "rgb", "intensity")
    assert parse_fields("all") is None
    with pytest.raises(ValueError, match="x, y and z"):
        parse_fields("rgb")
    assert bits_for_tolerance(20.0, 0.05) == 8  # 20 m / 0.1 m steps = 200 < 255
    with pytest.raises(ValueError, match="tolerance"):
        bits_for_tolerance(1.0, 0.0)


# --- bad input: every case the issue lists -------------------------------------------------------


def _small_cloud():
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    return array_to_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})


def test_data_length_mismatch_is_rejected():
    cloud = _small_cloud()
    cloud.data = cloud.data[:-1]
    with pytest.raises(InvalidCloud, match="data has 119 bytes"):
        DracoEncoder(leaf_size_m=0.1).encode(cloud)


def test_cloud_without_xyz_is_rejected():
    cloud = _small_cloud()
    cloud.fields[2].name = "intensity"
    with pytest.raises(InvalidCloud, match="no field z"):
        DracoEncoder(leaf_size_m=0.1).encode(cloud)


def test_empty_and_all_nan_clouds_are_rejected():
    empty = _small_cloud()
    empty.width, empty.row_step, empty.data = 0, 0, b""
    with pytest.raises(InvalidCloud, match="empty"):
        DracoEncoder(leaf_size_m=0.1).encode(empty)
    nan = array_to_cloud(
        {"x": np.full(4, np.nan, np.float32), "y": np.zeros(4, np.float32), "z": np.zeros(4, np.float32)}
    )
    with pytest.raises(InvalidCloud, match="no finite points"):
        DracoEncoder(leaf_size_m=0.1).encode(nan)


def test_unknown_field_type_is_rejected_by_encoder_and_decoder():
    cloud = _small_cloud()
    cloud.fields.append(PointField(name="intensity", offset=0, datatype=42, count=1))
    with pytest.raises(InvalidCloud, match="unknown PointField datatype 42"):
        DracoEncoder(leaf_size_m=0.1).encode(cloud)
    compressed = DracoEncoder(leaf_size_m=0.1).encode(_small_cloud())
    compressed.fields.append(PointField(name="intensity", offset=0, datatype=42, count=1))
    with pytest.raises(DracoError, match="datatype 42"):
        DracoDecoder().decode(compressed)


@pytest.mark.parametrize("damage", ["truncated", "corrupt", "empty", "garbage", "other_codec"])
def test_damaged_payload_is_rejected(depth, damage):
    compressed = DracoEncoder(leaf_size_m=0.1).encode(_filtered(depth, 0.1))
    data = bytes(compressed.compressed_data)
    if damage == "truncated":
        compressed.compressed_data = data[: len(data) // 2]
    elif damage == "corrupt":
        compressed.compressed_data = data[:20] + bytes(255 - b for b in data[20:])
    elif damage == "empty":
        compressed.compressed_data = b""
    elif damage == "garbage":
        compressed.compressed_data = np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes()
    else:
        compressed.compressed_data = zlib.compress(bytes(_filtered(depth, 0.1).data))
    with pytest.raises(DracoError):
        DracoDecoder().decode(compressed)

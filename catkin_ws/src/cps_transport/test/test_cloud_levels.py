"""The leaf travels with the cloud: encoder -> Draco payload -> decoder -> the twin's PointCloud2,
and the tracker that labels clouds while the voxel grid's leaf is switched (no ROS)."""

import math
import struct

import numpy as np
import pytest

from cps_fleet.fleet import load_fleet
from cps_msgs.msg import CompressedPointCloud2
from cps_transport.cloud_levels import (
    LEAF_FIELD,
    LeafError,
    LeafLedger,
    LeafTracker,
    cloud_level_leaves,
    header_key,
    initial_leaf_m,
    leaf_of_points,
    level_of_leaf,
    nearest_level,
    one_point_per_voxel,
    serialized_header_key,
)
from cps_transport.draco import DracoDecoder, DracoEncoder, DracoError, carried_leaf_m, leaf_of_compressed
from cps_transport.pointcloud import array_to_cloud, cloud_to_array
from cps_transport.voxel import voxel_downsample

LEAVES = (0.05, 0.10, 0.20)


def _surface(n=20000, seed=0):
    """Points on two planes (a floor and a wall) 0..4 m, as a depth sensor sees them."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack([rng.uniform(0, 4, n), rng.uniform(0, 4, n), np.zeros(n)])
    wall = np.column_stack([rng.uniform(0, 4, n), np.full(n, 4.0), rng.uniform(0, 2, n)])
    return np.vstack([floor, wall]).astype(np.float32)


def _cloud(xyz):
    xyz = np.asarray(xyz, dtype=np.float32)
    return array_to_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})


def _wire(msg):
    """The message as it crosses the link: serialized and read back."""
    import io

    buffer = io.BytesIO()
    msg.serialize(buffer)
    return CompressedPointCloud2().deserialize(buffer.getvalue())


@pytest.mark.parametrize("leaf", LEAVES)
def test_leaf_survives_encode_wire_and_decode(leaf):
    points = voxel_downsample(_surface(), leaf)
    compressed = DracoEncoder(leaf_size_m=leaf).encode(_cloud(points), leaf_size_m=leaf)
    assert [f.name for f in compressed.fields] == ["x", "y", "z", LEAF_FIELD]
    received = _wire(compressed)
    assert leaf_of_compressed(received) == pytest.approx(leaf, rel=1e-7)
    decoded = cloud_to_array(DracoDecoder().decode(received))
    assert len(decoded) == len(points)
    assert leaf_of_points(decoded) == pytest.approx(leaf, rel=1e-7)
    assert level_of_leaf(LEAVES, leaf_of_points(decoded)) == LEAVES.index(leaf)


@pytest.mark.parametrize("leaf", LEAVES + (0.3,))
def test_the_ledger_gives_a_relayed_cloud_the_leaf_its_payload_carries(leaf):
    """What the rate limiter of the encoder's process gets without decoding: the serialized
    cloud's header key finds the noted leaf, equal to the one the payload carries."""
    import io

    cloud = _cloud(voxel_downsample(_surface(2000), leaf))
    cloud.header.stamp.secs, cloud.header.stamp.nsecs, cloud.header.frame_id = 1700000000, 123456789, "jackal/base"
    ledger = LeafLedger()
    ledger.note(header_key(cloud.header), carried_leaf_m(leaf))
    buffer = io.BytesIO()
    DracoEncoder(leaf_size_m=leaf).encode(cloud, leaf_size_m=leaf).serialize(buffer)
    relayed = buffer.getvalue()
    assert serialized_header_key(relayed) == (1700000000, 123456789, b"jackal/base")
    assert ledger.leaf_of(serialized_header_key(relayed)) == leaf_of_compressed(
        CompressedPointCloud2().deserialize(relayed)
    )


def test_the_ledger_answers_none_where_the_limiter_must_decode():
    ledger = LeafLedger(clouds=3)
    ledger.note((1, 0, b"f"), 0.1)
    ledger.note((1, 0, b"f"), 0.1)
    assert ledger.leaf_of((1, 0, b"f")) == 0.1
    assert ledger.leaf_of((2, 0, b"f")) is None  # never noted
    ledger.note((2, 0, b"f"), 0.1)
    ledger.note((2, 0, b"f"), 0.2)  # two clouds, one key, two leaves: which one is relayed?
    assert ledger.leaf_of((2, 0, b"f")) is None
    ledger.note((2, 0, b"f"), 0.1)
    assert ledger.leaf_of((2, 0, b"f")) is None  # stays ambiguous while remembered
    for secs in (3, 4, 5):
        ledger.note((secs, 0, b"f"), 0.2)
    assert ledger.leaf_of((1, 0, b"f")) is None  # forgotten: more than 3 clouds ago
    assert ledger.leaf_of((5, 0, b"f")) == 0.2
    with pytest.raises(struct.error):
        serialized_header_key(b"\0" * 10)


def test_leaf_costs_a_few_bytes_and_none_without_it():
    points = voxel_downsample(_surface(), 0.1)
    encoder = DracoEncoder(leaf_size_m=0.1)
    plain = encoder.encode(_cloud(points))
    labelled = encoder.encode(_cloud(points), leaf_size_m=0.1)
    extra = len(labelled.compressed_data) - len(plain.compressed_data)
    assert 0 < extra <= 128, f"the leaf costs {extra} bytes per cloud"
    assert leaf_of_compressed(plain) is None
    assert leaf_of_points(cloud_to_array(DracoDecoder().decode(plain))) is None


@pytest.mark.parametrize("bad", [0.0, -0.1, math.nan, math.inf])
def test_encoder_refuses_a_bad_leaf(bad):
    from cps_transport.pointcloud import InvalidCloud

    with pytest.raises(InvalidCloud, match="leaf_size_m"):
        DracoEncoder(leaf_size_m=0.1).encode(_cloud(_surface(100)), leaf_size_m=bad)


def test_a_named_leaf_missing_from_the_payload_is_a_draco_error():
    points = voxel_downsample(_surface(), 0.1)
    encoder = DracoEncoder(leaf_size_m=0.1)
    forged = encoder.encode(_cloud(points))
    forged.fields = list(encoder.encode(_cloud(points), leaf_size_m=0.1).fields)
    with pytest.raises(DracoError, match="no leaf attribute"):
        leaf_of_compressed(forged)


def test_leaf_of_points_refuses_what_is_not_one_leaf():
    def points(values):
        values = np.asarray(values, dtype=np.float32)
        return cloud_to_array(array_to_cloud({"x": values, "y": values, "z": values, LEAF_FIELD: values}))

    assert leaf_of_points(points([0.2, 0.2])) == pytest.approx(0.2)
    for values, why in (([0.1, 0.2], "varies"), ([math.nan, math.nan], "not a leaf"), ([0.0, 0.0], "not a leaf")):
        with pytest.raises(LeafError, match=why):
            leaf_of_points(points(values))


def test_levels_from_the_fleet_and_the_initial_leaf():
    fleet = load_fleet()
    assert cloud_level_leaves(fleet) == LEAVES
    assert nearest_level(LEAVES, 0.01) == 0 and nearest_level(LEAVES, 0.1) == 1 and nearest_level(LEAVES, 0.5) == 2
    for robot in fleet.robots:
        assert initial_leaf_m(fleet, robot) == LEAVES[nearest_level(LEAVES, robot.voxel_leaf_m)]
    assert level_of_leaf(LEAVES, float(np.float32(0.05))) == 0 and level_of_leaf(LEAVES, 0.07) is None


def test_voxel_grid_output_has_one_point_per_voxel_of_its_leaf_only():
    surface = _surface()
    for leaf in LEAVES:
        assert one_point_per_voxel(voxel_downsample(surface, leaf), leaf)
    assert not one_point_per_voxel(voxel_downsample(surface, 0.05), 0.10)
    assert not one_point_per_voxel(voxel_downsample(surface, 0.10), 0.20)


@pytest.mark.parametrize("old,new", [(0.10, 0.20), (0.20, 0.10), (0.05, 0.20), (0.20, 0.05)])
def test_tracker_labels_the_clouds_of_a_switch_by_what_they_are(old, new):
    surface = _surface()
    tracker = LeafTracker(old)
    assert tracker.leaf_of(voxel_downsample(surface, old)) == old
    tracker.switch(new)
    # clouds the voxel grid filtered before the switch are still in flight
    assert tracker.leaf_of(voxel_downsample(surface, old)) == old
    assert tracker.leaf_of(voxel_downsample(surface, old)) == old
    assert tracker.leaf_of(voxel_downsample(surface, new)) == new
    assert not tracker.switching
    # from the first cloud at the new leaf on, every cloud is the new leaf
    assert tracker.leaf_of(voxel_downsample(surface, new)) == new


def test_tracker_switched_back_before_any_new_cloud():
    surface = _surface()
    tracker = LeafTracker(0.1)
    tracker.switch(0.2)
    tracker.switch(0.1)
    assert tracker.leaf_m == 0.1 and tracker.pending == [0.2, 0.1]
    assert tracker.leaf_of(voxel_downsample(surface, 0.2)) == 0.2
    assert tracker.leaf_of(voxel_downsample(surface, 0.1)) == 0.1 and not tracker.switching


def test_tracker_through_a_voxel_grid_restart():
    """Level 0.05 m; the voxel grid comes back at 0.10 m (its initial leaf) and is set to 0.05 m
    again: the clouds in between are labelled 0.10 m, then 0.05 m."""
    surface = _surface()
    tracker = LeafTracker(0.10)
    tracker.switch(0.05)
    assert tracker.leaf_of(voxel_downsample(surface, 0.05)) == 0.05 and not tracker.switching
    tracker.switch(0.10)  # parameter_updates: it runs at 0.10 m
    tracker.switch(0.05)  # set again
    assert tracker.leaf_of(voxel_downsample(surface, 0.10)) == 0.10
    assert tracker.leaf_of(voxel_downsample(surface, 0.10)) == 0.10
    assert tracker.leaf_of(voxel_downsample(surface, 0.05)) == 0.05 and not tracker.switching

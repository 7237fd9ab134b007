"""Each cloud lands in the 0.1 m map at its own resolution (docs/cloud_levels.md): a depth camera's
view of a room with a crate, voxelized in the camera's frame at 0.05 m and at 0.2 m (as pcl's
VoxelGrid does on the robot), inserted from two poses, against the voxels the camera's dense
returns fall in (the truth). And the map server reads the leaf each cloud carries."""

import functools

import genpy
import numpy as np
import pytest
import synthetic_scene as sc
from scipy.spatial import cKDTree
from std_msgs.msg import Header

from cps_fleet.fleet import load_fleet
from cps_mapping.cloud_input import bridge_coarse_cloud, prepare_cloud
from cps_mapping.fused_map import FusedLogOddsMap
from cps_mapping.map_server import MapOutputs, MapServer, MapServerOptions
from cps_transport.cloud_levels import LEAF_FIELD
from cps_transport.pointcloud import array_to_cloud
from cps_transport.voxel import voxel_downsample

FLEET = load_fleet()
RES = 0.1
ROOM = sc._shifted(
    sc.BoxScene(
        (
            sc.Box("floor", (-3.0, -2.5, -0.2), (3.0, 2.5, 0.0)),
            sc.Box("wall_north", (-3.0, 2.5, 0.0), (3.0, 2.7, 2.5)),
            sc.Box("wall_east", (3.0, -2.5, 0.0), (3.2, 2.5, 2.5)),
            sc.Box("wall_west", (-3.2, -2.5, 0.0), (-3.0, 2.5, 2.5)),
            sc.Box("crate", (0.5, -0.8, 0.0), (1.3, 0.2, 0.9)),
        )
    ),
    sc.GRID_OFFSET_M,
)
POSES = (((-2.0, -1.8, 1.0), 0.55), ((-1.0, -2.0, 0.6), 1.2))  # camera origin (m), yaw (rad)


def _keys(points_m):
    return np.floor(np.asarray(points_m, dtype=np.float32).astype(np.float64) / RES).astype(np.int64)


def _packed(keys):
    keys = np.asarray(keys, dtype=np.int64) + (1 << 20)
    return (keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2]


def _through_draco(cloud, leaf_m):
    """The cloud as the map server gets it from the robot's tissue: Draco at the tissue's tolerance
    for that leaf and the map's resolution, the leaf carried, decoded on the twin's side."""
    from cps_transport.cloud_levels import leaf_of_points, position_tolerance_m
    from cps_transport.draco import DracoDecoder, DracoEncoder
    from cps_transport.pointcloud import cloud_to_array, xyz_of

    msg = array_to_cloud({"x": cloud[:, 0], "y": cloud[:, 1], "z": cloud[:, 2]})
    encoder = DracoEncoder(position_tolerance_m=position_tolerance_m(leaf_m, RES))
    points = cloud_to_array(DracoDecoder().decode(encoder.encode(msg, leaf_size_m=leaf_m)))
    assert leaf_of_points(points) == pytest.approx(leaf_m)
    return xyz_of(points)


@functools.lru_cache(maxsize=1)
def _views():
    """The room seen from each of POSES at 640 x 480, rendered once per run (every insertion below
    sees the same views; the arrays are only read): ((origin, rotation, returns in the camera
    frame) per view, every dense return in map, the truth voxel keys they fall in)."""
    views, dense_all = [], []
    for origin, yaw in POSES:
        dense = sc.depth_camera_cloud(ROOM, origin, yaw, width=640, height=480, far_m=8.0)
        rotation = sc.rotation_z(yaw) @ sc.OPTICAL_TO_BODY
        views.append((origin, rotation, sc.to_sensor_frame(dense, origin, rotation).astype(np.float32)))
        dense_all.append(dense)
    dense = np.vstack(dense_all)
    truth = np.unique(_keys(dense), axis=0)
    for array in (dense, truth, *(view[2] for view in views)):
        array.flags.writeable = False
    return tuple(views), dense, truth


def _insert(leaf_m, carry_leaf=True, draco=False):
    """(map, truth voxel keys, dense returns in map, surface samples added): the room seen from
    POSES at 640 x 480, each view voxelized at `leaf_m` in the camera frame (and sent through
    Draco with `draco`)."""
    fused = FusedLogOddsMap(RES, FLEET.mapping.sensor_model)
    views, dense, truth = _views()
    bridged = 0
    for origin, rotation, in_camera in views:
        cloud = voxel_downsample(in_camera, leaf_m)
        if draco:
            cloud = _through_draco(cloud, leaf_m)
        prepared = prepare_cloud(cloud, rotation, origin, 100.0, leaf_m if carry_leaf else None, RES)
        bridged += prepared.bridged
        fused.insert_cloud(prepared.points_m, prepared.origin_m)
    return fused, truth, dense, bridged


def _figures(fused, truth, dense):
    occupied = fused.occupied_index()
    recall = np.isin(_packed(truth), _packed(occupied)).mean()
    # distance of every occupied voxel's centre from the nearest dense return (the surface)
    distance, _ = cKDTree(dense).query((occupied + 0.5) * RES)
    carved = int(fused.is_free((truth + 0.5) * RES).sum())  # surface voxels the map says are free
    return recall, float(distance.max()), carved


@pytest.fixture(scope="module")
def inserted():
    return {
        "0.05": _insert(0.05),
        "0.10": _insert(0.10),
        "0.20": _insert(0.20),
        "0.20 as if at the map's resolution": _insert(0.20, carry_leaf=False),
    }


@pytest.mark.parametrize("leaf", ["0.05", "0.10", "0.20"])
def test_through_draco_every_level_lands_as_unquantized(inserted, leaf):
    """Draco's quantization at the tissue's tolerance (1/8 of the map's resolution at most) costs
    at most 1 point of surface and 1 % more of it cleared, at every level; so the levels keep
    their order of detail (at half the leaf, 0.10 m clouds filled 53 % of the surface)."""
    fused, truth, dense, _ = _insert(float(leaf), draco=True)
    recall, farthest, carved = _figures(fused, truth, dense)
    reference = _figures(*inserted[leaf][:3])
    assert recall >= reference[0] - 0.01, (recall, reference)
    assert carved <= reference[2] + 0.01 * len(truth), (carved, reference)
    assert farthest <= reference[1] + 0.5 * RES / 4, (farthest, reference)


# A voxel the surface passes through has its centre within half its diagonal of the surface.
HALF_VOXEL_DIAGONAL_M = 0.5 * RES * 3**0.5


def test_a_finer_cloud_lands_as_the_surface_does(inserted):
    fused, truth, dense, bridged = inserted["0.05"]
    recall, farthest, carved = _figures(fused, truth, dense)
    assert bridged == 0
    # tolerance: >= 98 % of the surface's voxels occupied, none off the surface, <= 1 % cleared by
    # the other view's grazing rays (plain OctoMap insertion does that too)
    assert recall >= 0.98, recall
    assert farthest <= HALF_VOXEL_DIAGONAL_M, farthest
    assert carved <= 0.01 * len(truth), carved


def test_a_coarser_cloud_leaves_no_holes_and_adds_nothing_beyond_its_leaf(inserted):
    fused, truth, dense, bridged = inserted["0.20"]
    recall, farthest, carved = _figures(fused, truth, dense)
    plain = _figures(*inserted["0.20 as if at the map's resolution"][:3])
    at_map = _figures(*inserted["0.10"][:3])
    assert bridged > 0
    # without bridging the 0.2 m cloud fills ~38 % of the surface and the second view's rays clear
    # ~30 % of its voxels: the test sees the holes
    assert plain[0] < 0.6 and plain[2] > 0.2 * len(truth), plain
    # bridged: as complete as a cloud at the map's own resolution (within 3 points of recall)...
    assert recall >= 0.92 and recall >= at_map[0] - 0.03, (recall, at_map)
    # ...no surface voxel cleared more than at the map's resolution (+1 % of the surface)...
    assert carved <= at_map[2] + 0.01 * len(truth), (carved, at_map)
    # ...and no occupied voxel farther from the surface than half the leaf's diagonal plus half a voxel's
    assert farthest <= 0.5 * 0.2 * 3**0.5 + HALF_VOXEL_DIAGONAL_M, farthest
    # and only on the room's surfaces: the crate's inside and the space behind the walls stay unknown
    inside_crate = np.array([[0.9, -0.3, 0.45], [0.8, -0.5, 0.3], [1.0, 0.0, 0.6]]) + sc.GRID_OFFSET_M
    behind_walls = np.array([[0.0, 2.9, 1.0], [3.4, 0.0, 1.0], [-3.4, 0.5, 1.0], [0.0, 0.0, -0.35]]) + sc.GRID_OFFSET_M
    known = fused.is_free(np.vstack([inside_crate, behind_walls]), max_probability=0.999)
    assert (
        not known.any()
        and not np.isin(_packed(_keys(np.vstack([inside_crate, behind_walls]))), _packed(fused.occupied_index())).any()
    )


def test_bridging_joins_neighbouring_leaf_cubes_only():
    """Two points in neighbouring 0.2 m cubes are joined; two cubes apart they are not."""
    identity, origin = np.eye(3), np.zeros(3)
    near = np.array([[0.05, 0.05, 0.05], [0.25, 0.05, 0.05]])
    samples = bridge_coarse_cloud(near, 0.2, RES, identity, origin)
    assert len(samples) == 1 and np.array_equal(_keys(samples), [[1, 0, 0]])
    far = np.array([[0.05, 0.05, 0.05], [0.45, 0.05, 0.05]])
    assert len(bridge_coarse_cloud(far, 0.2, RES, identity, origin)) == 0
    # at or finer than the map: nothing added
    assert prepare_cloud(near, identity, origin, 100.0, 0.1, RES).bridged == 0


# ---- the map server reads the leaf each cloud carries --------------------------------------------

FRAME = "jackal/camera_depth_optical_frame"
ORIGIN, YAW = POSES[0]
ROTATION = sc.rotation_z(YAW) @ sc.OPTICAL_TO_BODY


def _server():
    outputs = MapOutputs(
        **{name: (lambda _msg: None) for name in MapOutputs.__dataclass_fields__ if name != "full_wanted"}
    )
    return MapServer(
        FLEET, MapServerOptions(robots=("jackal",)), outputs, lambda _f, _s: (ROTATION, np.asarray(ORIGIN))
    )


def _cloud(points, leaf=None):
    pts = np.asarray(points, dtype=np.float32)
    columns = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}
    if leaf is not None:
        columns[LEAF_FIELD] = np.broadcast_to(np.asarray(leaf, dtype=np.float32), len(pts)).copy()
    return array_to_cloud(columns, header=Header(stamp=genpy.Time(100, 0), frame_id=FRAME))


@pytest.fixture(scope="module")
def coarse_view():
    dense = sc.depth_camera_cloud(ROOM, ORIGIN, YAW, width=320, height=240, far_m=8.0)
    return voxel_downsample(sc.to_sensor_frame(dense, ORIGIN, ROTATION).astype(np.float32), 0.2)


def test_map_server_inserts_a_cloud_at_the_leaf_it_carries(coarse_view):
    server = _server()
    server.receive_cloud("jackal", _cloud(coarse_view, leaf=0.2))
    assert server.insert_pending(timeout_s=0) == 1
    c = server.robot_counters("jackal")
    assert c.points_bridged > 0 and c.points_inserted == len(coarse_view) + c.points_bridged
    assert (c.clouds_without_leaf, c.clouds_bad_leaf, c.clouds_dropped_invalid) == (0, 0, 0)


def test_a_cloud_at_the_maps_own_leaf_is_not_bridged(coarse_view):
    """A cloud carries its leaf as float32: 0.1 arrives as 0.10000000149 > 0.1. Taken as coarser than
    a 0.1 m map, every such cloud was bridged (live: ~830 samples and ~4 ms of the twin's CPU per
    cloud, 70 % of its per-cloud path, for voxels its own points already reach)."""
    at_map = voxel_downsample(coarse_view, RES)
    server = _server()
    server.receive_cloud("jackal", _cloud(at_map, leaf=RES))
    assert server.insert_pending(timeout_s=0) == 1
    c = server.robot_counters("jackal")
    assert c.points_bridged == 0 and c.points_inserted == len(at_map)
    assert (c.clouds_without_leaf, c.clouds_bad_leaf) == (0, 0)


@pytest.mark.parametrize(
    "leaf,counter",
    [
        (None, "clouds_without_leaf"),
        ([0.2, 0.1], "clouds_bad_leaf"),
        (float("nan"), "clouds_bad_leaf"),
        (-0.2, "clouds_bad_leaf"),
        (5.0, "clouds_bad_leaf"),
    ],
)
def test_a_cloud_without_a_usable_leaf_is_counted_and_inserted_as_it_is(coarse_view, leaf, counter, caplog):
    server = _server()
    points = coarse_view[:2] if isinstance(leaf, list) else coarse_view
    server.receive_cloud("jackal", _cloud(points, leaf=leaf if not isinstance(leaf, list) else np.asarray(leaf)))
    assert server.insert_pending(timeout_s=0) == 1
    c = server.robot_counters("jackal")
    assert getattr(c, counter) == 1 and c.clouds_inserted == 1 and c.clouds_dropped_invalid == 0
    assert c.points_bridged == 0 and c.points_inserted == len(points)
    assert "inserted at the map's resolution as it is" in caplog.text

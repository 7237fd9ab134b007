"""The map server's boundaries against hostile input, without a master: fuzzed clouds (hypothesis)
are inserted or dropped and counted, never raised; map files too large for the grid limit
(a coarse pruned leaf, voxels kilometres apart) are refused with the running map unchanged, and
moved aside at resume; save/load stay inside the map folder."""

import os

import genpy
import numpy as np
from fleet_model import new_map
from hostile_maps import COARSE_LEAF_BT, far_apart_bt
from hypothesis import HealthCheck, given, settings

from cps_fleet.fleet import load_fleet
from cps_harness.hostile_clouds import hostile_clouds, packed_cloud
from cps_mapping.fused_map import MapFileError
from cps_mapping.map_server import MapOutputs, MapServer, MapServerOptions
from cps_msgs.srv import LoadMapRequest, SaveMapRequest
from cps_transport.pointcloud import InvalidCloud, cloud_to_array, xyz_of

FLEET = load_fleet()
RES = FLEET.mapping.resolution_m
FRAME = "jackal/camera_depth_optical_frame"


def _server(tmp_path, **options):
    outputs = MapOutputs(**{name: (lambda *_args: None) for name in MapOutputs.__dataclass_fields__})
    options.setdefault("map_file", str(tmp_path / "twin.bt"))
    return MapServer(
        FLEET,
        MapServerOptions(robots=("jackal",), **options),
        outputs,
        lambda _frame, _stamp: (np.eye(3), (0.0, 0.0, 0.5)),
    )


def _cloud(points):
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    msg = packed_cloud({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, frame_id=FRAME)
    msg.header.stamp = genpy.Time(100, 0)
    return msg


def _mapped(server):
    server.receive_cloud("jackal", _cloud([[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, 1.0, 1.0]]))
    server.insert_pending(timeout_s=0)
    return sorted(map(tuple, server.map.occupied_index()))


class _Fuzz:
    server = None


@settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture]
)
@given(cloud=hostile_clouds())
def test_every_hostile_cloud_is_inserted_or_dropped_and_counted(tmp_path, cloud):
    """Admission takes anything (nothing is read then); the insertion inserts it or drops it,
    counted by cause, and never raises."""
    if _Fuzz.server is None:
        _Fuzz.server = _server(tmp_path)
    server = _Fuzz.server
    before = dict(vars(server.robot_counters("jackal")))
    server.receive_cloud("jackal", cloud)
    assert server.waiting("jackal") == 1
    server.insert_pending(timeout_s=0)
    after = vars(server.robot_counters("jackal"))
    assert after["clouds_received"] == before["clouds_received"] + 1 and server.waiting("jackal") == 0
    dropped = after["clouds_dropped_invalid"] - before["clouds_dropped_invalid"]
    inserted = after["clouds_inserted"] - before["clouds_inserted"]
    assert dropped + inserted == 1
    try:
        readable = np.isfinite(xyz_of(cloud_to_array(cloud))).any()
    except InvalidCloud:
        readable = False
    if not readable:
        assert dropped == 1


def test_a_coarse_pruned_leaf_or_voxels_km_apart_are_refused_and_the_map_stays(tmp_path):
    server = _server(tmp_path)
    before = _mapped(server)
    (tmp_path / "coarse.bt").write_bytes(COARSE_LEAF_BT)
    far_apart_bt(tmp_path / "far.bt", RES)
    for name in ("coarse.bt", "far.bt"):
        reply = server.on_load(LoadMapRequest(path=str(tmp_path / name)))
        assert not reply.success and "max_grid_voxels" in reply.message and name in reply.message
        assert sorted(map(tuple, server.map.occupied_index())) == before
    fused = new_map(RES)
    try:
        fused.load(str(tmp_path / "coarse.bt"))
        raise AssertionError("loaded a map of 2^45 voxels")
    except MapFileError as exc:
        assert "over the map's limit" in str(exc)


def test_a_hostile_map_at_resume_is_moved_aside_and_the_server_starts_empty(tmp_path):
    (tmp_path / "twin.bt").write_bytes(COARSE_LEAF_BT)
    server = _server(tmp_path)
    assert len(server.map.occupied_index()) == 0
    assert not (tmp_path / "twin.bt").exists()
    assert [n for n in os.listdir(tmp_path) if n.startswith("twin.bt.unreadable-")]


def test_save_and_load_stay_inside_the_map_folder(tmp_path):
    (tmp_path / "mission").mkdir()
    server = _server(tmp_path / "mission")
    os.symlink("/etc", tmp_path / "mission" / "etc_link")
    for path in ("/etc/x.bt", str(tmp_path / "mission" / ".." / "x.bt"), str(tmp_path / "mission/etc_link/x.bt")):
        reply = server.on_save(SaveMapRequest(path=path))
        assert not reply.success and "refused" in reply.message, path
        assert not server.on_load(LoadMapRequest(path=path)).success
    assert not os.path.exists("/etc/x.bt") and not (tmp_path / "x.bt").exists()
    assert server.on_save(SaveMapRequest(path=str(tmp_path / "mission" / "sub" / "x.bt"))).success
    assert server.on_load(LoadMapRequest(path=str(tmp_path / "mission" / "sub" / "x.bt"))).success
    elsewhere = _server(tmp_path, map_folder=str(tmp_path / "maps"))
    assert not elsewhere.on_save(SaveMapRequest(path="")).success
    assert elsewhere.on_save(SaveMapRequest(path=str(tmp_path / "maps" / "y.bt"))).success

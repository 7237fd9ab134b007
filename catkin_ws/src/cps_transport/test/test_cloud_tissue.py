"""Every robot's tissue in one process (cloud_tissue, cloud_decoder, voxel_grid_loader): each robot
keeps its own topics, rate and drop counts, and one robot's malformed clouds stop nobody else's."""

import os
import signal

import numpy as np
import pytest

from cps_fleet import names
from cps_fleet.fleet import load_fleet
from cps_harness.hostile_clouds import packed_cloud, refused_clouds
from cps_harness.testing import TopicRecorder, wait_for
from cps_transport.cloud_levels import initial_leaf_m
from cps_transport.nodelet_loader import NodeletRequest, voxel_grid_requests
from cps_transport.tissue import parse_robot_list, robot_tissue_configs, twin_cloud_topics
from cps_transport.voxel_grid_command import voxel_nodelet_args


def test_robot_configs_come_from_the_fleet_file():
    fleet = load_fleet()
    configs = {c.robot: c for c in robot_tissue_configs(fleet)}
    assert list(configs) == fleet.robot_names
    for robot in fleet.robots:
        c = configs[robot.name]
        base = names.absolute(names.robot_topic(robot.name, names.POINTS_FILTERED))
        assert (c.filtered, c.draco, c.managed) == (base, f"{base}/draco", f"{base}/draco/managed")
        assert c.throttle_node == names.absolute(names.robot_topic(robot.name, names.CLOUD_THROTTLE))
        assert c.leaf_size_m == initial_leaf_m(fleet, robot) and c.rate_hz == fleet.link.min_rate_hz
        assert c.cloud_levels_m[c.initial_level] == c.leaf_size_m and c.level_topic == names.absolute(
            names.robot_topic(robot.name, names.LIMITER_LEVEL)
        )
    assert [c.robot for c in robot_tissue_configs(fleet, ["iris", "scout"])] == ["iris", "scout"]
    with pytest.raises(KeyError, match="robot 'nope' is not in the fleet"):
        robot_tissue_configs(fleet, ["scout", "nope"])


def test_robot_list_and_twin_topics():
    assert parse_robot_list(" a, b ,,c") == ["a", "b", "c"]
    assert parse_robot_list("") is None and parse_robot_list(["x"]) == ["x"]
    assert twin_cloud_topics("r", backfill=False) == [
        (names.absolute(names.managed_cloud_at_twin("r")), names.absolute(names.twin_points("r")))
    ]
    assert twin_cloud_topics("r", backfill=True)[1] == (
        names.absolute(names.in_twin(names.robot_topic("r", names.POINTS_BACKFILL_DRACO))),
        names.absolute(names.in_twin(names.robot_topic("r", names.POINTS_BACKFILL))),
    )


def test_loader_requests_carry_what_nodelet_load_passes():
    """The loader's service call has the name, remappings (resolved as nodelet.cpp resolves them)
    and parameters of `rosrun nodelet nodelet load` in the per-robot layout."""
    fleet = load_fleet()
    for robot, request in zip(fleet.robots, voxel_grid_requests(fleet)):
        argv = voxel_nodelet_args(robot, manager="/m", leaf_size_m=initial_leaf_m(fleet, robot))
        assert request.type == argv[4] == "pcl/VoxelGrid"
        assert f"__name:={request.name.rsplit('/', 1)[1]}" in argv and f"__ns:={names.absolute(robot.name)}" in argv
        sources, targets = request.resolved_remappings()
        assert sources == [f"{request.name}/input", f"{request.name}/output"]
        assert targets == [
            names.absolute(names.robot_topic(robot.name, robot.cloud_topic)),
            names.absolute(names.robot_topic(robot.name, names.POINTS_FILTERED)),
        ]
        assert [f"_{k}:={v}" for k, v in request.params.items()] == [a for a in argv if a[0] == "_" and a[1] != "_"]
        assert request.params["leaf_size"] == initial_leaf_m(fleet, robot) and request.params["filter_field_name"] == ""
    relative = NodeletRequest("/a/vg", "t", {"in": "pts", "~out": "/abs"}, {})
    assert relative.resolved_remappings() == (["/a/in", "/a/vg/out"], ["/a/pts", "/abs"])


def _good_cloud(robot, seed=1):
    xyz = np.random.default_rng(seed).uniform(-3, 3, (500, 3)).astype(np.float32)
    return packed_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, f"{robot}/lidar")


def _status(diagnostics, topic):
    for _, msg in reversed(diagnostics.messages):
        for status in msg.status:
            if status.hardware_id == topic:
                return {kv.key: kv.value for kv in status.values}
    return {}


@pytest.mark.ros
def test_one_robots_malformed_clouds_stop_no_other_robot(ros, rospy_node):
    """cloud_tissue for three robots and cloud_decoder for two: one robot fed only refused clouds
    (and damaged payloads on the twin) counts them; the others' clouds go through encoder, limiter
    and decoder, each limiter keeps its own rate."""
    rospy = rospy_node
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Float64

    from cps_msgs.msg import CompressedPointCloud2, RateLimiterStatus

    bad, good = "jackal", ("scout", "champ")
    tissue = ros.start_node(
        "cps_transport", "cloud_tissue", name="cloud_tissue", params={"~robots": ",".join((bad, *good))}
    )
    decoder = ros.start_node(
        "cps_transport",
        "cloud_decoder",
        name="cloud_decoder",
        namespace=names.absolute(names.TWIN_NS),
        params={"~robots": f"{bad},{good[0]}", "~backfill": True},
    )
    diagnostics = TopicRecorder(names.DIAGNOSTICS, DiagnosticArray)
    managed = {r: TopicRecorder(names.absolute(names.managed_cloud(r)), CompressedPointCloud2) for r in good}
    status = {
        r: TopicRecorder(names.absolute(names.robot_topic(r, names.LIMITER_STATUS)), RateLimiterStatus)
        for r in (bad, *good)
    }
    twin = TopicRecorder(names.absolute(names.twin_points(good[0])), PointCloud2)
    backfill = TopicRecorder(
        names.absolute(names.in_twin(names.robot_topic(good[0], names.POINTS_BACKFILL))), PointCloud2
    )
    raw = {
        r: rospy.Publisher(names.absolute(names.robot_topic(r, names.POINTS_FILTERED)), PointCloud2, queue_size=20)
        for r in (bad, *good)
    }
    to_twin = {
        r: rospy.Publisher(names.absolute(names.managed_cloud_at_twin(r)), CompressedPointCloud2, queue_size=20)
        for r in (bad, good[0])
    }
    relay = rospy.Subscriber(
        names.absolute(names.managed_cloud(good[0])), CompressedPointCloud2, to_twin[good[0]].publish
    )
    backfill_in = rospy.Publisher(
        names.absolute(names.in_twin(names.robot_topic(good[0], names.POINTS_BACKFILL_DRACO))),
        CompressedPointCloud2,
        queue_size=5,
    )
    rate = rospy.Publisher(
        names.absolute(names.robot_topic(good[1], names.LIMITER_RATE_HZ)), Float64, queue_size=1, latch=True
    )
    try:
        assert wait_for(
            lambda: all(p.get_num_connections() for p in (*raw.values(), *to_twin.values())), timeout_s=30
        ), ros.output("cloud_tissue")[-2000:] + ros.output("cloud_decoder")[-2000:]
        rate.publish(Float64(3.5))
        assert status[good[1]].wait(lambda m: m.set_rate_hz == 3.5, timeout_s=10)
        clouds = list(refused_clouds(f"{bad}/lidar").values())
        for i in range(12):
            raw[bad].publish(clouds[i % len(clouds)])
            to_twin[bad].publish(CompressedPointCloud2(compressed_data=bytes(range(200))))
            for r in good:
                raw[r].publish(_good_cloud(r, seed=i))
            rospy.sleep(0.15)
        for r in good:
            assert managed[r].wait_count(1, timeout_s=15)[-1].header.frame_id == f"{r}/lidar"
        decoded = twin.wait(timeout_s=15)
        assert decoded.header.frame_id == f"{good[0]}/lidar" and decoded.width > 0
        backfill_in.publish(managed[good[0]].latest)
        assert backfill.wait(timeout_s=10).header.frame_id == f"{good[0]}/lidar"

        def filtered(r):
            return names.absolute(names.robot_topic(r, names.POINTS_FILTERED))

        assert wait_for(
            lambda: int(_status(diagnostics, filtered(bad)).get("invalid_messages", 0)) >= 10, timeout_s=10
        ), _status(diagnostics, filtered(bad))
        bad_at_twin = names.absolute(names.managed_cloud_at_twin(bad))
        assert wait_for(
            lambda: int(_status(diagnostics, bad_at_twin).get("invalid_messages", 0)) >= 10,
            timeout_s=10,
        )
        for r in good:
            assert wait_for(lambda: _status(diagnostics, filtered(r)).get("processed") == "12", timeout_s=10), _status(
                diagnostics, filtered(r)
            )
            assert _status(diagnostics, filtered(r))["invalid_messages"] == "0"
        assert status[bad].latest.received == 0 and status[good[0]].latest.set_rate_hz == load_fleet().link.min_rate_hz
        assert tissue.poll() is None and decoder.poll() is None
    finally:
        relay.unregister()
        for recorder in (diagnostics, twin, backfill, *managed.values(), *status.values()):
            recorder.close()
        for pub in (*raw.values(), *to_twin.values(), backfill_in, rate):
            pub.unregister()


@pytest.mark.ros
def test_cloud_tissue_refuses_a_robot_not_in_the_fleet(ros):
    proc = ros.start_node("cps_transport", "cloud_tissue", name="bad_tissue", params={"~robots": "scout,nosuch"})
    assert proc.wait(timeout=30) != 0
    assert "robot 'nosuch' is not in the fleet" in ros.output("bad_tissue")


def _listed(listing):
    try:
        return list(listing().nodelets)
    except Exception:  # the manager restarting: its service gone for a moment
        return None


@pytest.mark.ros
def _stacks(ros, proc, name):
    """The node's output with every thread's stack (cps_ros.shutdown.init_node's SIGUSR1)."""
    os.kill(proc.pid, signal.SIGUSR1)
    wait_for(lambda: "most recent call first" in ros.output(name), timeout_s=5)
    return ros.output(name)[-6000:]


def test_one_loader_puts_every_robots_voxel_grid_into_one_manager(ros, rospy_node, tmp_path):
    """voxel_grid_loader loads two robots' pcl/VoxelGrid into one manager (clouds come out
    filtered per robot), loads them again into a restarted manager, unloads them when stopped,
    and a load the manager refuses is an error."""
    rospy = rospy_node
    from nodelet.srv import NodeletList
    from sensor_msgs.msg import PointCloud2

    from cps_harness.synthetic_clouds import lidar_cloud
    from cps_transport.nodelet_loader import NodeletLoader, NodeletLoadError

    manager = ros.popen(["rosrun", "nodelet", "nodelet", "manager", "__name:=vg_manager"], name="vg_manager")
    robots = ["scout", "jackal"]
    loader = ros.start_node(
        "cps_transport",
        "voxel_grid_loader",
        name="voxel_grid_loader",
        params={"~robots": ",".join(robots), "~manager": "/vg_manager"},
    )
    filtered = {
        r: TopicRecorder(names.absolute(names.robot_topic(r, names.POINTS_FILTERED)), PointCloud2) for r in robots
    }
    fleet = load_fleet()
    pubs = {
        r: rospy.Publisher(names.absolute(names.robot_topic(r, fleet.robot(r).cloud_topic)), PointCloud2, queue_size=2)
        for r in robots
    }
    listing = rospy.ServiceProxy("/vg_manager/list", NodeletList)
    try:
        ros.wait_for_service("/vg_manager/list", timeout_s=30)
        assert wait_for(
            lambda: sorted(_listed(listing) or ()) == ["/jackal/voxel_grid", "/scout/voxel_grid"], timeout_s=30
        ), ros.output("voxel_grid_loader")[-2000:]
        assert rospy.get_param("/scout/voxel_grid/leaf_size") == initial_leaf_m(fleet, fleet.robot("scout"))
        cloud = lidar_cloud(rings=8, samples_per_ring=400)
        for r in robots:
            assert wait_for(lambda: pubs[r].publish(cloud) or filtered[r].count, timeout_s=20, poll_s=0.3), r
            assert 0 < filtered[r].latest.width <= cloud.width
        # A restarted manager gets them back.
        ros.stop(manager)
        manager = ros.popen(["rosrun", "nodelet", "nodelet", "manager", "__name:=vg_manager"], name="vg_manager2")
        ros.wait_for_service("/vg_manager/list", timeout_s=30)
        # final20 (a full run): the loader never reloaded into the restarted manager, and said
        # nothing. Its threads' stacks say where it waited, should it happen again.
        assert wait_for(
            lambda: sorted(_listed(listing) or ()) == ["/jackal/voxel_grid", "/scout/voxel_grid"], timeout_s=30
        ), _stacks(ros, loader, "voxel_grid_loader")
        ros.stop(loader)
        assert wait_for(lambda: _listed(listing) == [], timeout_s=10), _listed(listing)

        refused = NodeletLoader("/vg_manager", [NodeletRequest("/x/vg", "pcl/NoSuchNodelet", {}, {})])
        with pytest.raises(NodeletLoadError, match="failed to load pcl/NoSuchNodelet as /x/vg .*unknown type"):
            refused.load_all()
    finally:
        listing.close()
        for recorder in filtered.values():
            recorder.close()
        for pub in pubs.values():
            pub.unregister()

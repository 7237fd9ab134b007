"""The map server's kernels are built with the code and keyed by what they compile (issue 29).

Each test starts from a fresh checkout: a copy of this package's source at a new path with no
kernel cache (`checkout` fixture), built as `make setup` builds it. So no test here depends on a
cache that another test, or the workspace, warmed.
- a copy of a built checkout at another path, with an older or a newer mtime, compiles nothing
  (numba's own cache keys by path and mtime and recompiled there);
- cold start: the map server node started from the fresh checkout reports ready with every kernel
  loaded from that cache, and the first cloud that reaches it is inserted within 1 s;
- an edited source never gets the old kernels: a node started from a built checkout whose source
  was then edited (the old kernels still beside it) finds none for its source, so its kernels are
  not built; it compiles them before it is ready (and says so), and a cloud that arrives meanwhile
  is queued and inserted, not lost. (One cold compile proves both: the edited source and the
  unbuilt node were two tests of ~11 CPU-s each, each compiling every kernel.)
"""

import json
import os
import subprocess
import sys
import time

import pytest

from cps_fleet import names
from cps_harness.warm_start import (
    checkout_env,
    copy_checkout,
    managed_cloud_topic,
    managed_wall_cloud,
    static_sensor_transform,
)
from cps_mapping.kernel_cache import KERNEL_FOLDER

pytestmark = pytest.mark.slow
PACKAGE = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
# The kernels' first use as the map server uses them: fused maps of both casting modes, a batch of
# clouds, the .bt and the projected map. Prints what this process compiled.
EXERCISE = """
import json
import numpy as np
from cps_fleet.fleet import load_fleet
from cps_mapping import kernel_cache, log_odds_grid
from cps_mapping.fused_map import FusedLogOddsMap

warm = log_odds_grid.warm_up()
rng = np.random.default_rng(0)
for exact in (True, False):
    fused = FusedLogOddsMap(0.1, load_fleet().mapping.sensor_model, exact_free_space=exact)
    points_m = rng.uniform(-5.0, 5.0, (3000, 3)).astype(np.float32)
    fused.insert_batch([(points_m, np.zeros(3)), (points_m + 1.0, np.ones(3))], max_range_m=8.0, robot="jackal")
    fused.binary_tree_nodes()
    fused.projected_grid(0.1, 2.0)
print(json.dumps({"module": log_odds_grid.__file__, "warm_up": list(warm.compiled),
                  "compiled": list(kernel_cache.compiled_kernels())}))
"""
# Sensor pose of the cold-start test's cloud, in map.
SENSOR_FRAME = "jackal/camera_depth_optical_frame"


def _module_file(checkout):
    return os.path.join(checkout, "src", "cps_mapping", "log_odds_grid.py")


def _exercise(checkout):
    out = subprocess.run(
        [sys.executable, "-c", EXERCISE],
        env=checkout_env(checkout),
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def checkout(tmp_path_factory):
    """A fresh checkout (no kernel cache) built as ci/setup.sh builds it; (path, build output)."""
    path = copy_checkout(PACKAGE, str(tmp_path_factory.mktemp("checkout") / "cps_mapping"), with_cache=False)
    assert not os.path.exists(os.path.join(path, "src", "cps_mapping", KERNEL_FOLDER))
    built = subprocess.run(
        [sys.executable, "-m", "cps_mapping.build_kernels"],
        env=checkout_env(path),
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    return path, built.stdout


def test_a_fresh_checkout_builds_its_own_kernels(checkout):
    path, output = checkout
    assert "compiled" in output and os.path.join(path, "src") in output, output


@pytest.mark.parametrize("mtime_shift_s", [-365 * 86400.0, 3600.0], ids=["older", "newer"])
def test_kernels_built_elsewhere_serve_a_copy_at_another_path_and_mtime(checkout, tmp_path, mtime_shift_s):
    """The issue's older checkout: the same source at another path, its file older (or newer) than
    the kernels, loads them all and compiles nothing."""
    other = copy_checkout(checkout[0], str(tmp_path / "other_checkout"), with_cache=True)
    now = time.time()
    os.utime(_module_file(other), (now + mtime_shift_s, now + mtime_shift_s))
    result = _exercise(other)
    assert result["module"] == _module_file(other)
    assert result["compiled"] == [], f"compiled at use: {result['compiled']}"


@pytest.mark.ros
def test_cold_start_first_cloud_is_inserted_within_1_s(checkout, ros, rospy_node, tmp_path):
    """The node of a fresh checkout (its cache built by the set-up, nothing warmed before) says it
    is ready with no kernel compiled, and inserts the first cloud within 1 s of its arrival."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from cps_harness.testing import TopicRecorder, wait_for
    from cps_msgs.msg import CompressedPointCloud2, Octomap

    rospy = rospy_node
    path, _ = checkout
    name = "cold_map_server"
    ready = TopicRecorder(names.absolute(names.in_twin(names.private(name, names.READY))), DiagnosticStatus)
    octomap = TopicRecorder(names.absolute(names.in_twin(names.OCTOMAP_BINARY)), Octomap)
    publisher = rospy.Publisher(managed_cloud_topic("jackal"), CompressedPointCloud2, queue_size=1)
    tf_keep = static_sensor_transform(rospy, SENSOR_FRAME)
    try:
        ros.popen(
            [
                sys.executable,
                os.path.join(path, "nodes", "map_server"),
                f"__ns:={names.absolute(names.TWIN_NS)}",
                f"__name:={name}",
                "_robots:=jackal",
                f"_map_file:={tmp_path / 'map.bt'}",
                "_publish_period_s:=0.05",
                "_autosave_period_s:=0.0",
            ],
            name=name,
            env=checkout_env(path),
        )
        status = ready.wait(timeout_s=120, what="the map server's ready")
        values = {kv.key: kv.value for kv in status.values}
        assert values["kernel_cache_dir"].startswith(os.path.join(path, "src")), values
        assert status.level == DiagnosticStatus.OK and values["kernels_compiled"] == "", status
        assert wait_for(lambda: publisher.get_num_connections(), timeout_s=20), "the map server did not subscribe"
        published_at = time.monotonic()
        publisher.publish(managed_wall_cloud(rospy, SENSOR_FRAME))
        octomap.wait(lambda m: len(m.data) > 0, timeout_s=10, what="the first cloud in the map")
        arrived_at = next(t for t, m in octomap.messages if t >= published_at and len(m.data) > 0)
        print(
            f"cold start: ready after {values['ready_after_s']} s, first cloud in the map "
            f"{arrived_at - published_at:.3f} s after it was sent"
        )
        assert arrived_at - published_at < 1.0
    finally:
        for recorder in (ready, octomap):
            recorder.close()
        publisher.unregister()
        del tf_keep


@pytest.mark.ros
def test_an_edited_source_never_gets_the_old_kernels_and_a_cloud_sent_during_the_warm_up_is_inserted(
    checkout, ros, rospy_node, tmp_path
):
    """The built checkout copied with its kernels, then its source edited: the old kernels are
    there, and none is for this source. The node compiles before it is ready and says so; a cloud
    sent once it subscribed, before its ready, waits in the queue and reaches the map."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from cps_harness.testing import TopicRecorder, wait_for
    from cps_mapping.kernel_cache import cache_dir
    from cps_msgs.msg import CompressedPointCloud2, Octomap

    rospy = rospy_node
    path = copy_checkout(checkout[0], str(tmp_path / "edited" / "cps_mapping"), with_cache=True)
    old_kernels = cache_dir(_module_file(path))
    assert os.listdir(old_kernels), "the copy must carry the kernels built for the unedited source"
    with open(_module_file(path), "a") as stream:
        stream.write("\n# an edit\n")
    assert cache_dir(_module_file(path)) != old_kernels
    name = "unbuilt_map_server"
    ready = TopicRecorder(names.absolute(names.in_twin(names.private(name, names.READY))), DiagnosticStatus)
    octomap = TopicRecorder(names.absolute(names.in_twin(names.private(name, names.OCTOMAP_BINARY))), Octomap)
    publisher = rospy.Publisher(managed_cloud_topic("jackal"), CompressedPointCloud2, queue_size=1)
    tf_keep = static_sensor_transform(rospy, SENSOR_FRAME)
    try:
        ros.popen(
            [
                sys.executable,
                os.path.join(path, "nodes", "map_server"),
                f"__ns:={names.absolute(names.TWIN_NS)}",
                f"__name:={name}",
                f"{names.OCTOMAP_BINARY}:={names.absolute(names.in_twin(names.private(name, names.OCTOMAP_BINARY)))}",
                "_robots:=jackal",
                f"_map_file:={tmp_path / 'map.bt'}",
                "_publish_period_s:=0.05",
                "_autosave_period_s:=0.0",
            ],
            name=name,
            env=checkout_env(path),
        )
        assert wait_for(lambda: publisher.get_num_connections(), timeout_s=60), "the map server did not subscribe"
        publisher.publish(managed_wall_cloud(rospy, SENSOR_FRAME))
        assert ready.count == 0, "ready before the cloud was sent: this test needs the cloud to arrive first"
        status = ready.wait(timeout_s=300, what="the map server's ready")
        values = {kv.key: kv.value for kv in status.values}
        assert status.level == DiagnosticStatus.WARN and "_integrate" in values["kernels_compiled"], status
        assert values["kernel_cache_dir"] == cache_dir(_module_file(path)) != old_kernels, values
        assert values["clouds_queued_before_ready"] == "1", status
        octomap.wait(lambda m: len(m.data) > 0, timeout_s=10, what="the queued cloud in the map")
    finally:
        for recorder in (ready, octomap):
            recorder.close()
        publisher.unregister()
        del tf_keep

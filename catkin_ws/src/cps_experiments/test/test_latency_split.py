"""The report's latency split joins the robots' side and the twin per cloud by capture stamp."""

import struct

import pytest

from cps_experiments.report import latency_split, read_csv
from cps_fleet import names
from cps_fleet.csv_log import CsvLog
from cps_transport.topic_stats import ARRIVAL_COLUMNS, stamp_ns_from_serialized


def _serialized_header(stamp_ns, frame_id=b"scout/lidar"):
    secs, nsecs = divmod(stamp_ns, 1_000_000_000)
    return struct.pack("<III", 7, secs, nsecs) + struct.pack("<I", len(frame_id)) + frame_id + b"payload"


def _log(path, arrivals):
    log = CsvLog(str(path), ARRIVAL_COLUMNS)
    for topic, robot, stamp_ns, receive_s in arrivals:
        log.write((topic, robot, stamp_from_bytes(stamp_ns), f"{receive_s:.6f}"))
    log.close()
    return read_csv(str(path))


def stamp_from_bytes(stamp_ns):
    return stamp_ns_from_serialized(_serialized_header(stamp_ns))


def test_split_is_per_cloud_over_the_clouds_that_reached_the_twin(tmp_path):
    base_ns = 1_700_000_000_123_456_789
    capture_ns = [base_ns + k * 100_000_000 for k in range(6)]  # clouds every 0.1 s
    robot_side_s = [0.050, 0.070, 0.300, 0.060, 0.055, 0.080]  # capture -> filtered, physical host
    tissue_s = [0.020, 0.030, None, None, 0.025, -0.010]  # None: dropped by the rate limiter
    physical, twin = [], []
    for stamp, robot_s, tissue in zip(capture_ns, robot_side_s, tissue_s):
        filtered = stamp * 1e-9 + robot_s
        physical.append((names.absolute(names.robot_topic("scout", names.POINTS_FILTERED)), "scout", stamp, filtered))
        if tissue is not None:
            twin.append((names.absolute(names.managed_cloud_at_twin("scout")), "scout", stamp, filtered + tissue))
    # A cloud of another robot with the same stamp must not join scout's.
    twin.append(
        (names.absolute(names.managed_cloud_at_twin("jackal")), "jackal", capture_ns[2], capture_ns[2] * 1e-9 + 0.2)
    )
    twin.append(
        (names.absolute(names.robot_topic("scout", names.ODOM)), "scout", capture_ns[3], capture_ns[3] * 1e-9 + 0.001)
    )  # not a managed cloud
    split = latency_split(_log(tmp_path / "physical_arrivals.csv", physical), _log(tmp_path / "arrivals.csv", twin))

    assert set(split) == {"scout"}
    scout = split["scout"]
    # Joined: clouds 0, 1, 4, 5. The last one's physical receive came 10 ms after its twin arrival (the
    # statistics node's own queueing): its robot side ends at the twin arrival, its tissue part is 0.
    assert scout["clouds"] == 4
    robot_parts = [0.050, 0.070, 0.055, 0.070]
    tissue_parts = [0.020, 0.030, 0.025, 0.0]
    assert scout["robot_side_avg_ms"] == pytest.approx(1e3 * sum(robot_parts) / 4, abs=1e-3)
    assert scout["tissue_link_avg_ms"] == pytest.approx(1e3 * sum(tissue_parts) / 4, abs=1e-3)
    assert scout["total_avg_ms"] == pytest.approx(scout["robot_side_avg_ms"] + scout["tissue_link_avg_ms"], abs=1e-6)
    assert scout["total_max_ms"] == pytest.approx(100.0, abs=1e-3)
    assert scout["tissue_link_avg_ms"] >= 0.0
    # Averages over different sets (what the report did before) would give a negative tissue + link.
    all_robot_side_ms = 1e3 * sum(robot_side_s) / len(robot_side_s)
    assert scout["total_avg_ms"] - all_robot_side_ms < 0.0


def test_stamp_in_nanoseconds_is_exact():
    stamp = 1_700_000_000_999_999_999
    assert stamp_from_bytes(stamp) == stamp
    assert stamp_ns_from_serialized(b"short") is None

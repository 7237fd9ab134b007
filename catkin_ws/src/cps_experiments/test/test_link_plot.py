"""The report's bandwidth plot: every managed stream (each robot's cloud and video) stacked as the
manager allocated it, from allocation.csv rows (with and without the `stream` column)."""

import numpy as np
import pytest

from cps_experiments.report import allocated_streams, plot_link


def _row(stamp, robot, mbytes, stream=None, rate=5.0):
    row = {"stamp_s": str(stamp), "robot": robot, "bandwidth_mbytes_per_s": str(mbytes), "rate_hz": str(rate)}
    if stream is not None:
        row["stream"] = stream
    return row


ROWS = [
    _row(10.0, "jackal", 1.0, "cloud"),
    _row(10.0, "jackal", 0.2, "video", 15.0),
    _row(10.0, "scout", 2.0, "cloud"),
    _row(11.0, "jackal", 1.5, "cloud"),
    _row(11.0, "scout", 2.5, "cloud"),
    _row(11.0, "jackal", 0.1, "video", 5.0),
]


def test_streams_are_keyed_robot_by_robot_cloud_then_video_and_held_per_instant():
    times, streams = allocated_streams(ROWS + [_row(12.0, "scout", 3.0)])
    assert list(times) == [10.0, 11.0, 12.0]
    assert list(streams) == [("jackal", "cloud"), ("jackal", "video"), ("scout", "cloud")]
    assert streams[("jackal", "video")] == pytest.approx([0.2, 0.1, 0.0])  # nothing allocated at 12 s
    assert streams[("scout", "cloud")] == pytest.approx([2.0, 2.5, 3.0])  # a row without `stream` is the cloud
    total = sum(streams.values())
    assert total == pytest.approx([3.2, 4.1, 3.0])


def test_plot_link_writes_the_stacked_plot(tmp_path):
    stats = [
        {
            "time_s": "10.5",
            "robot": "jackal",
            "managed": "True",
            "bandwidth_mbytes_per_s": "1.1",
            "latency_avg_ms": "40",
        },
        {
            "time_s": "10.5",
            "robot": "scout",
            "managed": "True",
            "bandwidth_mbytes_per_s": "2.1",
            "latency_avg_ms": "50",
        },
    ]
    png = tmp_path / "link.png"
    plot_link(stats, ROWS, 7.2, str(png))
    from PIL import Image

    with Image.open(png) as image:
        pixels = np.asarray(image.convert("RGB"))
    assert pixels.shape[0] > 500 and pixels.std() > 10.0  # a drawn figure, not a blank page

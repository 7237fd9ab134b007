#!/usr/bin/env python3
"""The managed video in the running simulator: what the operator would get when every camera
robot's video is set to one level and rate, with the depth clouds and the lidar running too.

Runs the real fleet_sim (light profile, fast renderer, its 2 sensor workers, the default fleet:
3 camera robots and a lidar robot) on a private master, sets every camera robot's
video_throttle/level and rate_hz (latched), subscribes to the videos (nothing is rendered
unwatched) and to the clouds (rospy.AnyMsg, no decoding), and after a warm-up counts for
`--seconds`: video frames and bytes per robot, the clouds received per robot, and fleet_sim's
CPU (its process and sensor workers, from /proc). Cases: the coarsest level at the default 5 Hz
(the anchor: what the fleet sent before the manager spoke), the operator target (320x240 at 15 Hz)
and 640x480 at 30 Hz; each printed as achieved / asked.

Usage: python bench/video_live_bench.py [--seconds 15]
The 2-core machine is shared with other work: figures are contended; the load is printed.
"""

import argparse
import os
import threading
import time

from live_fleet_sim import measure_cpu, start_fleet_sim

from cps_fleet import names

CASES = ((2, 5.0), (1, 15.0), (0, 30.0))


def run_case(graph, fleet, level_index, rate_hz, seconds, warmup_s=6.0):
    import rospy
    from sensor_msgs.msg import CompressedImage
    from std_msgs.msg import Float64, UInt8

    cameras = [r.name for r in fleet.robots if r.has_depth_camera]
    frames, video_bytes, clouds = {}, {}, {}
    lock, measuring = threading.Lock(), threading.Event()

    def on_frame(msg, robot):
        if measuring.is_set():
            with lock:
                frames[robot] = frames.get(robot, 0) + 1
                video_bytes[robot] = video_bytes.get(robot, 0) + len(msg.data)

    def on_cloud(_msg, robot):
        if measuring.is_set():
            with lock:
                clouds[robot] = clouds.get(robot, 0) + 1

    node_graph = graph.attach()
    pubs, subs = [], []
    try:
        for robot in cameras:
            level = rospy.Publisher(names.absolute(names.robot_topic(robot, names.VIDEO_LEVEL)), UInt8, latch=True)
            rate = rospy.Publisher(
                names.absolute(names.robot_topic(robot, names.VIDEO_RATE_HZ)), Float64, latch=True, queue_size=1
            )
            level.publish(UInt8(level_index))
            rate.publish(Float64(rate_hz))
            pubs += [level, rate]
        proc = start_fleet_sim(node_graph, fleet, f"fleet_sim_{level_index}")
        for robot in cameras:
            topic = names.absolute(names.robot_topic(robot, names.CAMERA_IMAGE_COMPRESSED))
            subs.append(rospy.Subscriber(topic, CompressedImage, on_frame, callback_args=robot, queue_size=5))
        for r in fleet.robots:
            topic = names.absolute(names.robot_topic(r.name, r.cloud_topic))
            subs.append(rospy.Subscriber(topic, rospy.AnyMsg, on_cloud, callback_args=r.name, queue_size=2))
        cpu = sum(measure_cpu(proc, warmup_s, seconds, measuring).values())
    finally:
        for item in subs + pubs:
            item.unregister()
        node_graph.close()
    configured = {
        r.name: fleet.profile.lidar.rate_hz if r.has_lidar else fleet.profile.depth_camera.rate_hz for r in fleet.robots
    }
    return {
        "video_hz": {r: frames.get(r, 0) / seconds for r in cameras},
        "video_mbytes": {r: video_bytes.get(r, 0) / seconds / 1e6 for r in cameras},
        "cloud_ratio": {n: clouds.get(n, 0) / seconds / hz for n, hz in configured.items()},
        "cpu": cpu,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=15.0)
    args = parser.parse_args(argv)
    from cps_fleet.fleet import load_fleet
    from cps_harness.testing import RosGraph

    fleet = load_fleet(profile="light")
    levels = fleet.streams.video_levels
    graph = RosGraph()
    graph.start()
    graph.point_this_process_here()
    import rospy

    rospy.init_node("video_live_bench", anonymous=True, disable_signals=True)
    print(
        f"fleet_sim, default fleet (light, fast renderer, 2 sensor workers) on {os.cpu_count()} cores, load average "
        f"{os.getloadavg()[0]:.1f} at start, {time.strftime('%Y-%m-%d %H:%M')}; {args.seconds:.0f} s per case"
    )
    results = {}
    try:
        for level_index, rate_hz in CASES:
            results[(level_index, rate_hz)] = result = run_case(graph, fleet, level_index, rate_hz, args.seconds)
            name = levels[level_index].name
            print(
                f"\n{name} at {rate_hz:g} Hz asked: video Hz "
                + ", ".join(f"{r} {hz:.1f} ({hz / rate_hz:.2f})" for r, hz in result["video_hz"].items())
                + f"; video MB/s total {sum(result['video_mbytes'].values()):.3f}"
            )
            print(
                "  clouds received / configured: "
                + ", ".join(f"{r} {ratio:.2f}" for r, ratio in result["cloud_ratio"].items())
                + f"; fleet_sim + workers CPU {result['cpu']:.2f} cores; load average {os.getloadavg()[0]:.1f}"
            )
    finally:
        graph.close()
    anchor = results[CASES[0]]
    for case in CASES[1:]:
        result = results[case]
        print(
            f"{levels[case[0]].name} at {case[1]:g} Hz vs the anchor ({levels[CASES[0][0]].name} at {CASES[0][1]:g} Hz): "
            f"CPU {result['cpu'] / anchor['cpu']:.2f}x, video MB/s "
            f"{sum(result['video_mbytes'].values()) / max(sum(anchor['video_mbytes'].values()), 1e-9):.1f}x"
        )


if __name__ == "__main__":
    main()

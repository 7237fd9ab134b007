#!/usr/bin/env python3
"""Managed video benchmark: what one frame of each video level (fleet.yaml streams.video_levels)
costs the simulated camera (render the colour image at the level's size + JPEG at its quality, as
cps_sim.video does in a sensor worker) and what it weighs on the link, on the demo's scene (the
depth robots at cps_sim's sample poses).

    source ci/env.sh && python bench/video_bench.py [--repeats 30] [--renderer fast]

Per level, medians over the robots' frames of: CPU ms per frame (process CPU time, so the GL
driver's threads count), wall ms of render and of encode, JPEG bytes and serialized
CompressedImage bytes. Anchors measured in the same run (OpenCV is not installed here, so no
cv2.imencode anchor):
  - render at 640x480 then shrink to the level (Pillow's box reduce), then encode: what "render
    fine and throw it away" would cost (ours/that);
  - the old fixed stream: the light depth capture (160x120 colour + depth + organized cloud) and a
    Pillow q75 JPEG of its image (ours at 160x120 / that).
Then whether two cores can render+encode 640x480 at 30 fps for 4 robots. Single-threaded
callers; the 2-core machine is shared, so timings are contended (medians).
"""

import argparse
import math
import statistics
import time

import numpy as np
from PIL import Image as PilImage

from cps_fleet.fleet import load_fleet
from cps_sim.video import VideoTask, compressed_image_bytes
from cps_transport.image_compression import encode_jpeg

FRAME_ID = "jackal/camera_depth_optical_frame"
FORMAT = "rgb8; jpeg compressed bgr8"


def cost(fn, repeats):
    """(median CPU ms, median wall ms) of `fn()` over `repeats` calls, and its last result."""
    cpu, wall = [], []
    result = None
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        result = fn()
        cpu.append((time.process_time() - c0) * 1e3)
        wall.append((time.perf_counter() - w0) * 1e3)
    return statistics.median(cpu), statistics.median(wall), result


def main():
    from cps_sim.sample_clouds import SAMPLE_POSES
    from cps_sim.simulation import build_fleet_simulation

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--renderer", default="fast")
    args = parser.parse_args()
    fleet = load_fleet(profile="light")
    levels = fleet.streams.video_levels
    robots = [r.name for r in fleet.robots if r.has_depth_camera]
    sim = build_fleet_simulation(None, "light", robots, args.renderer)
    print(f"renderer {sim.renderer}; robots {', '.join(robots)} at cps_sim's sample poses; {args.repeats} repeats")
    try:
        for name in robots:
            x, y, z, yaw_deg = SAMPLE_POSES[name]
            sim.place(name, x, y, z, math.radians(yaw_deg))
        rows = {}
        for index, level in enumerate(levels):
            per_robot = []
            for name in robots:
                camera, pose = sim.robots[name].sensor, sim.robots[name].robot.sensor_in_map()
                task = VideoTask(name, index, level.width, level.height, level.jpeg_quality)
                ours_cpu, ours_wall, frame = cost(lambda: sim.capture_video(task), args.repeats)
                render_cpu, render_wall, rgb = cost(
                    lambda: camera.render_colour(pose, level.width, level.height), args.repeats
                )
                enc_cpu, enc_wall, _ = cost(lambda: encode_jpeg(rgb, level.jpeg_quality), args.repeats)
                factor = levels[0].width // level.width

                def fine_then_shrink():
                    fine = camera.render_colour(pose, levels[0].width, levels[0].height)
                    small = np.asarray(PilImage.fromarray(fine).reduce(factor)) if factor > 1 else fine
                    return encode_jpeg(small, level.jpeg_quality)

                shrink_cpu, _, _ = cost(fine_then_shrink, args.repeats)
                jpeg_bytes = len(frame.jpeg)
                per_robot.append(
                    dict(
                        ours_cpu=ours_cpu,
                        ours_wall=ours_wall,
                        render_wall=render_wall,
                        enc_wall=enc_wall,
                        shrink_cpu=shrink_cpu,
                        jpeg=jpeg_bytes,
                        msg=compressed_image_bytes(FRAME_ID, FORMAT, jpeg_bytes),
                    )
                )
            rows[level.name] = {k: statistics.median(r[k] for r in per_robot) for k in per_robot[0]}
            rows[level.name]["per_robot_jpeg"] = [r["jpeg"] for r in per_robot]

        def old_path():
            frame = sim.capture("jackal")
            return encode_jpeg(frame.rgb, 75)

        old_cpu, _, old_jpeg = cost(old_path, args.repeats)
    finally:
        sim.close()

    print(
        f"\n{'level':<8} {'q':>3} {'CPU ms':>7} {'wall ms':>7} {'render ms':>9} {'enc ms':>7} "
        f"{'fine+shrink CPU ms':>18} {'ours/that':>9} {'JPEG B':>7} {'msg B':>7} {'prior B':>7} {'per robot B':>20}"
    )
    for level in levels:
        r = rows[level.name]
        print(
            f"{level.name:<8} {level.jpeg_quality:>3} {r['ours_cpu']:>7.2f} {r['ours_wall']:>7.2f} {r['render_wall']:>9.2f} "
            f"{r['enc_wall']:>7.2f} "
            f"{r['shrink_cpu']:>18.2f} {r['ours_cpu'] / r['shrink_cpu']:>9.2f} {r['jpeg']:>7.0f} {r['msg']:>7.0f} "
            f"{level.bytes_prior:>7.0f} {str(r['per_robot_jpeg']):>20}"
        )
    coarse = rows[levels[-1].name]
    print(
        f"\nold fixed stream (light depth capture 160x120 + cloud, Pillow q75 of its image): {old_cpu:.2f} CPU ms, "
        f"{len(old_jpeg)} B; ours at {levels[-1].name}: {coarse['ours_cpu']:.2f} CPU ms "
        f"(ours/old {coarse['ours_cpu'] / old_cpu:.2f})"
    )
    fine = rows[levels[0].name]
    need = 4 * 30 * fine["ours_cpu"] / 1e3
    need_wall = 4 * 30 * fine["ours_wall"] / 1e3
    print(
        f"4 robots x 30 fps at {levels[0].name}: {need:.2f} CPU-s per s needed, 2 cores give 2.00 "
        f"({need / 2.0:.2f}x two cores); by this run's wall time per frame (contention included) "
        f"{need_wall:.2f} s per s on 2 sensor workers ({need_wall / 2.0:.2f}x)"
    )
    for level in levels:
        r = rows[level.name]
        print(
            f"  {level.name} at 30 fps: {r['msg'] * 30 / 1e6:.3f} MB/s per robot "
            f"({r['msg'] * 30 * 8 / 1e6:.1f} Mbit/s; the link is {fleet.link.available_mbps:.0f} Mbit/s)"
        )


if __name__ == "__main__":
    main()

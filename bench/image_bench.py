#!/usr/bin/env python3
"""Camera compression benchmark: JPEG (cps_transport.image_compression, Pillow) against the raw
sensor_msgs/Image the GUI used to pull across the link, in one run.

    source ci/env.sh && python bench/image_bench.py [--repeats 20] [--no-sim]

For each sensor profile of fleet.yaml (its camera size and rate: light 160x120 at 10 Hz, paper 640x480 at 30 Hz) and JPEG
quality 50/75/90: ms per encode (what image_compressor spends per frame, rgb8 in) and decode (what
the GUI spends), bytes per frame against raw, PSNR, MB/s at the profile's camera rate, and that
against the link's reserve for unmanaged traffic and the whole link. Frames are the depth robots'
cameras rendered by cps_sim at their sample poses (a synthetic hall picture with --no-sim or when
cps_sim cannot render). Single-threaded; the machine is shared, so timings are noisy (median).
"""

import argparse
import statistics
import time

import numpy as np

from cps_fleet.fleet import load_fleet
from cps_transport.image_compression import camera_test_image, compress_image, decode_jpeg, psnr_db

QUALITIES = (50, 75, 90)


def sim_frames(profile):
    """Robot -> HxWx3 RGB camera frame rendered by cps_sim, for the depth robots of `profile`."""
    import math

    from cps_sim.sample_clouds import SAMPLE_POSES
    from cps_sim.simulation import build_fleet_simulation

    fleet = load_fleet(profile=profile)
    depth_robots = [r.name for r in fleet.robots if r.has_depth_camera]
    sim = build_fleet_simulation(None, profile, depth_robots, "egl")
    try:
        frames = {}
        for name in sim.robots:
            x, y, z, yaw_deg = SAMPLE_POSES[name]
            sim.place(name, x, y, z, math.radians(yaw_deg))
            frames[name] = np.ascontiguousarray(sim.capture(name).rgb)
        return frames
    finally:
        sim.close()


def timed_ms(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--no-sim", action="store_true", help="synthetic frames only")
    args = parser.parse_args()
    fleet = load_fleet()
    link = fleet.link
    reserve_mbytes = link.available_mbps * link.reserve_fraction / 8.0
    link_mbytes = link.available_mbps / 8.0
    print(
        f"link {link.available_mbps:.0f} Mbit/s = {link_mbytes:.2f} MB/s; reserve for unmanaged traffic "
        f"{link.reserve_fraction:.0%} = {reserve_mbytes:.3f} MB/s (one camera would have all of it)"
    )
    for profile in ("light", "paper"):
        camera = load_fleet(profile=profile).profile.depth_camera
        width, height, rate_hz = camera.width, camera.height, camera.rate_hz
        frames = {}
        if not args.no_sim:
            try:
                frames = sim_frames(profile)
            except Exception as exc:  # no EGL, no cps_sim: fall back
                print(f"  (cps_sim could not render: {exc}; synthetic frame only)")
        frames["synthetic"] = camera_test_image(width, height)
        raw_bytes = width * height * 3
        raw_mbytes = raw_bytes * rate_hz / 1e6
        print(
            f"\n{profile}: {width}x{height} rgb8 at {rate_hz:g} Hz; raw {raw_bytes} B/frame = {raw_mbytes:.2f} MB/s "
            f"= {raw_mbytes / reserve_mbytes:.1f}x the reserve, {raw_mbytes / link_mbytes:.0%} of the link (anchor)"
        )
        print(
            f"  {'frame':<10} {'q':>3} {'enc ms':>7} {'dec ms':>7} {'bytes':>7} {'raw/jpeg':>8} {'PSNR dB':>7} "
            f"{'MB/s':>6} {'x reserve':>9} {'% link':>6} {'Hz in reserve':>13}"
        )
        for name, rgb in frames.items():
            data = rgb.tobytes()
            for quality in QUALITIES:
                fmt, jpeg = compress_image("rgb8", width, height, 3 * width, data, quality)
                enc_ms = timed_ms(lambda: compress_image("rgb8", width, height, 3 * width, data, quality), args.repeats)
                dec_ms = timed_ms(lambda: decode_jpeg(jpeg), args.repeats)
                mbytes = len(jpeg) * rate_hz / 1e6
                print(
                    f"  {name:<10} {quality:>3} {enc_ms:>7.2f} {dec_ms:>7.2f} {len(jpeg):>7} {raw_bytes / len(jpeg):>8.1f} "
                    f"{psnr_db(rgb, decode_jpeg(jpeg)):>7.1f} {mbytes:>6.3f} {mbytes / reserve_mbytes:>9.2f} "
                    f"{mbytes / link_mbytes:>6.1%} {reserve_mbytes * 1e6 / len(jpeg):>13.1f}"
                )
        print(f"  format on the wire: '{fmt}'")


if __name__ == "__main__":
    main()

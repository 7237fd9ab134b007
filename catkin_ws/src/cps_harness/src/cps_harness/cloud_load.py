"""The physical twin's managed input without a simulator, for tests and benchmarks. Publishes
pre-built incompressible payloads of realistic Draco-cloud sizes as cps_msgs/CompressedPointCloud2
on /<r>/points_filtered/draco, stamped at publication, so latency = receive time - stamp.

  python -m cps_harness.cloud_load scout:34000:10 jackal:142000:30 ...   (robot:mean bytes:Hz; sizes vary +-10 %)
"""

import sys
import time

import numpy as np
import rospy

from cps_msgs.msg import CompressedPointCloud2


def main():
    rospy.init_node("cloud_load", anonymous=True)
    specs = []
    rng = np.random.default_rng(7)
    for arg in rospy.myargv(sys.argv)[1:]:
        robot, size, rate = arg.split(":")
        payloads = [rng.integers(0, 256, int(int(size) * f), dtype=np.uint8).tobytes() for f in (0.9, 1.0, 1.1, 1.0)]
        pub = rospy.Publisher(f"/{robot}/points_filtered/draco", CompressedPointCloud2, queue_size=2)
        specs.append([pub, payloads, 1.0 / float(rate), time.monotonic() + 1.0, 0])
    while not rospy.is_shutdown():
        now = time.monotonic()
        for spec in specs:
            pub, payloads, period, due, count = spec
            if now >= due:
                msg = CompressedPointCloud2(compressed_data=payloads[count % len(payloads)])
                msg.header.stamp = rospy.Time.now()
                msg.header.frame_id = "load"
                pub.publish(msg)
                spec[3] = max(due + period, now - period)
                spec[4] = count + 1
        time.sleep(max(0.0, min(s[3] for s in specs) - time.monotonic()))


if __name__ == "__main__":
    main()

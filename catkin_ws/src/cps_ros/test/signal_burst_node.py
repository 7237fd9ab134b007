"""A node that keeps rospy's locks busy (logging from its main thread, three subscribers logging
every message of a 1 kHz publisher) and writes `shutdown hook ran` to stderr from its shutdown hook.
Its output goes to a file: a pipe nobody reads would fill and block its logging.

argv[1]: `threaded` (cps_ros.shutdown.init_node) or `rospy` (rospy's own signal handlers, the anchor);
argv[2]: `spin` (wait for a signal) or `return` (main ends by itself, no signal); argv[3], optional:
a path whose existence starts the busy work after READY (so that nodes started together all import
and connect before any of them takes the CPU).
"""

import os
import sys
import threading
import time

import rospy
from std_msgs.msg import String

from cps_ros.shutdown import init_node


def main():
    handling, ending = sys.argv[1], sys.argv[2]
    if handling == "threaded":
        init_node("signal_burst")
    else:
        rospy.init_node("signal_burst")
    rospy.on_shutdown(lambda: sys.stderr.write("shutdown hook ran\n"))
    if ending == "return":
        print("READY", flush=True)
        return
    chatter = rospy.Publisher("chatter", String, queue_size=10)
    for _ in range(3):
        rospy.Subscriber("chatter", String, lambda msg: rospy.loginfo(f"heard {msg.data}"))

    def publish():
        while not rospy.is_shutdown():
            try:
                chatter.publish("x")
            except rospy.ROSException:  # closed by the shutdown
                return
            time.sleep(0.001)

    print("READY", flush=True)
    go_path = sys.argv[3] if len(sys.argv) > 3 else None
    while go_path and not os.path.exists(go_path) and not rospy.is_shutdown():
        time.sleep(0.01)
    threading.Thread(target=publish, daemon=True).start()
    while not rospy.is_shutdown():
        rospy.loginfo("main thread working")


if __name__ == "__main__":
    main()

"""Keeps the fleet's e-stop state on /fleet/estop (latched) for as long as the mission runs.

The GUI's latched publisher dies with the GUI; a mux or simulator that restarts afterwards would
then never hear the state and stay stopped, or (before they waited for it) drive. The keeper, in
the long-lived bringup process, publishes the initial state and republishes every change it hears,
so a late subscriber always gets the last state.
"""

import threading

import rospy
from std_msgs.msg import Bool

from cps_fleet import names
from cps_ros.publisher import Publisher


class EstopKeeper:
    def __init__(self, initial=False):
        self._lock = threading.Lock()
        self.active = bool(initial)
        self._pub = Publisher(names.ESTOP, Bool, queue_size=5, latch=True)
        self._pub.publish(Bool(data=self.active))
        self._sub = rospy.Subscriber(names.ESTOP, Bool, self._on_estop, queue_size=5)

    def _on_estop(self, msg):
        with self._lock:
            if msg.data == self.active:
                return
            self.active = msg.data
            self._pub.publish(Bool(data=self.active))
        rospy.logwarn("e-stop %s", "ON: every robot stops" if msg.data else "released")

    def close(self):
        self._sub.unregister()
        self._pub.unregister()

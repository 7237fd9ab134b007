"""The map server's receive side (issue 37): admission before work, and each cloud placed in the map
frame only when the insertion asks for it.

`Admission` holds every robot's clouds as they arrived in `RobotSlots` (a superseded one costs a
pointer swap) and counts them. `next_cloud` gives the insertion the next cloud to insert, the robot
whose map is oldest first, with its pose: it reads the cloud's header (deserialising the bytes; the
Draco payload stays compressed) and looks its transform up without waiting. A cloud whose transform
is not known yet goes back to its slot and the next robot is served; one still without a transform
`tf_timeout_s` after it arrived is dropped. Every cloud admission ends is counted by cause here
(superseded, missed, queue, tf, and unreadable bytes or a missing frame); the insertion counts the
rest (decoder, invalid, inserted).

The node runs it in its own process (`cps_mapping.admission_process`), so that a hundred robots'
receiving threads never compete with the insertion for one interpreter's lock; the tests and a
single process use it directly.
"""

import dataclasses
import time
from typing import Callable, Dict, List, Optional

import numpy as np

from cps_mapping.cloud_input import UnreadableMessage, read_message, sender_sequence
from cps_mapping.queues import AdmissionCounters, Arrival, RobotSlots
from cps_mapping.throttled_log import ThrottledLog

# A cloud whose transform is not known yet is tried again after this long (tf arrives at tens of Hz).
TF_RETRY_S = 0.01


class TransformUnavailable(Exception):
    """No transform fixed frame <- cloud frame at the cloud's stamp (not yet, or not at all)."""


@dataclasses.dataclass
class PlacedCloud:
    """A cloud the insertion takes: the message as it arrived (header read, payload untouched) and
    the sensor's pose in the fixed frame at its stamp."""

    robot: str
    message: object  # cps_msgs/CompressedPointCloud2 or sensor_msgs/PointCloud2
    rotation: np.ndarray  # 3 x 3
    translation_m: tuple
    stamp_s: float
    backfill: bool = False


class Admission:
    """Every robot's slot, the transform lookup and the admission counts; thread-safe."""

    def __init__(
        self,
        robots: List[str],
        transform_of: Callable,
        tf_timeout_s: float,
        frame_id: str,
        log,
        clock: Callable = time.monotonic,
        keyframe_pose_of: Optional[Callable] = None,
    ):
        """`transform_of(frame, stamp)` -> (3 x 3 rotation, translation) of `frame` in `frame_id`, or
        raises TransformUnavailable; it must not wait. `keyframe_pose_of(frame, stamp)`, the same for
        a backfill keyframe from the pose sent with it, places keyframes instead of /tf: a keyframe
        is from an outage, when no /tf crossed the link, and tf2 interpolates across the gap (issue
        39: the demo's baseline placed its keyframes metres off the robots' paths and their hits
        stood in free space). A keyframe whose pose has not come yet waits for it, up to
        `tf_timeout_s` (then dropped, counted as tf)."""
        self.robots = list(robots)
        self.keyframe_pose_of = keyframe_pose_of
        self.slots = RobotSlots(self.robots, clock=clock)
        self.transform_of, self.tf_timeout_s, self.frame_id = transform_of, tf_timeout_s, frame_id
        self.clock = clock
        self.log = ThrottledLog(log)

    def receive(self, robot, message, backfill=False):
        """A robot's cloud as received (rospy.AnyMsg or a message object): held, counted, nothing read."""
        displaced = self.slots.put(Arrival(robot, message, self.clock(), backfill), sender_sequence(message))
        if displaced is not None and displaced.backfill:  # rare (after an outage): worth a line
            self.log.warn(
                ("backfill", robot),
                f"map_server: {robot}: more than {self.slots.backfill_kept} backfill keyframes waiting, the oldest dropped",
            )

    def next_cloud(self, timeout_s: Optional[float] = None) -> Optional[PlacedCloud]:
        """The next cloud to insert with its pose, waiting up to `timeout_s` for one (None: forever);
        None on timeout or once closed."""
        deadline = None if timeout_s is None else self.clock() + timeout_s
        while True:
            remaining = None if deadline is None else max(0.0, deadline - self.clock())
            arrival = self.slots.take(timeout_s=remaining)
            if arrival is None:
                return None
            placed = self._place(arrival)
            if placed is not None:
                self.slots.served(placed.robot, placed.stamp_s)
                self.slots.count(placed.robot, clouds_placed=1)
                return placed

    def _place(self, arrival: Arrival) -> Optional[PlacedCloud]:
        robot = arrival.robot
        try:
            msg = arrival.opened or read_message(arrival.message)
        except UnreadableMessage as exc:
            self.slots.count(robot, clouds_dropped_decoder=1)
            self.log.warn(("unreadable", robot), f"map_server: {robot}: unreadable cloud dropped: {exc}")
            return None
        arrival.opened = msg
        frame = msg.header.frame_id.lstrip("/")
        if not frame:
            self.slots.count(robot, clouds_dropped_invalid=1)
            self.log.warn(("frame", robot), f"map_server: {robot}: cloud without frame_id dropped")
            return None
        try:
            place = self.keyframe_pose_of if arrival.backfill and self.keyframe_pose_of else self.transform_of
            rotation, translation = place(frame, msg.header.stamp)
        except TransformUnavailable as exc:
            if self.clock() - arrival.arrived_s < self.tf_timeout_s:
                self.slots.defer(arrival, TF_RETRY_S)  # superseded (counted there) if a newer one arrived
                return None
            self.slots.count(robot, clouds_dropped_tf=1)
            self.log.warn(
                ("tf", robot),
                f"map_server: {robot}: no transform {self.frame_id} <- '{frame}' at {msg.header.stamp.to_sec():.3f} "
                f"within {self.tf_timeout_s} s of its arrival, cloud dropped: {exc}",
            )
            return None
        return PlacedCloud(robot, msg, rotation, translation, msg.header.stamp.to_sec(), arrival.backfill)

    def snapshot(self) -> Dict[str, tuple]:
        """{robot: (AdmissionCounters, clouds waiting)}."""
        return {r: self.slots.state(r) for r in self.robots}

    def close(self):
        self.slots.close()


def merged_counts(admitted: AdmissionCounters, **inserter_counts) -> dict:
    """The robot's counts of both sides, a field counted on both (decoder, invalid) summed."""
    counts = dataclasses.asdict(admitted)
    for field, value in inserter_counts.items():
        counts[field] = counts.get(field, 0) + value
    return counts

"""The map server's receive side in its own process (issue 37), and the insertion's client of it.

Measured at 128 replayed robots with every thread in one process (one core, light profile): the
insertion thread sat in its own code 74 % of the time yet used 0.09 s of CPU per second, and the
process 0.48 of its core: ~150 receiving threads (a rospy thread per connection) handing the
interpreter's lock to each other left the insertion waiting for it, the core half idle, and 86
clouds/s inserted where 32 robots got 142. The receiving threads, the transforms and the slots
(`cps_mapping.admission.Admission`) now run in a child process, a rospy node of their own
(cps_fleet.names.admission_node: `<map server>_input`) at ~receive_nice, and the insertion thread in
the map server's process asks it for clouds over a pipe, a batch of up to BATCH at a time, and asks
for the next batch while it still inserts this one. The child dies with the map server
(PR_SET_PDEATHSIG) and ends when its pipes close. It starts as a fresh interpreter, or forked from
a fork server that imported ahead (`prepare_fast_start`: a warm spare's).
"""

import collections
import ctypes
import dataclasses
import multiprocessing
import os
import signal
import sys
import threading
from typing import List, Tuple

# Longest wait of the receive side for a cloud before it answers "none" (the insertion asks again).
REQUEST_WAIT_S = 0.5
# Clouds placed per request, at most: the receive process answers with every cloud it can place at
# once, up to BATCH, and the insertion asks for more while it still holds some. Each answer costs the
# receive process one turn at its interpreter's lock among its receiving threads (up to the 5 ms
# switch interval): one cloud per turn held the twin near 160 clouds/s however many robots sent.
BATCH = 4
READY_TIMEOUT_S = 60.0
# What each receiving thread asks the socket for at once (rospy's buff_size: its recv size, not a
# bound on a message size), rospy's default. A recv of 2**24 bytes (what this asked before) allocates
# that much afresh (mmap) for the bytes that came: ~20 us more per recv than 64 kB for a 12 kB
# cloud (a socket pair on this machine), at 128 replayed robots ~3 600 messages/s (clouds and /tf).
RECEIVE_CHUNK_BYTES = 65536
_PR_SET_PDEATHSIG = 1
# What the receive process imports: a fork server that preloaded them starts one without a fresh
# interpreter's imports (prepare_fast_start).
RECEIVE_PROCESS_IMPORTS = ("rospy", "tf2_py", "geometry_msgs.msg", "cps_mapping.admission", "cps_ros.shutdown")
# The multiprocessing start method of the receive process: "spawn" (a fresh interpreter: no forked
# rospy state) unless prepare_fast_start made it a preloaded fork server's.
_start_context = multiprocessing.get_context("spawn")


def prepare_fast_start():
    """Start a fork server that has imported what the receive process imports (multiprocessing's
    forkserver with a preload); the receive process is then forked from it instead of spawned. A map
    server's warm spare (cps_ros.spare) calls this ahead of its start: a restarted map server waited
    for its receive process's imports on the loaded twin CPU. The fork server never starts a ROS node,
    so nothing of rospy's state is forked; it ends with the process that started it.

    Called from a spare's import thread (cps_ros.spare, at SPARE_NICE) the fork server, and every
    process it forks, inherit that priority. The supervisor, as root, sets the fork server back to
    the node's priority when it starts the spare (`cps_ros.spare.take_back_priority`); where no one
    did, and the map server may not lower it itself, AdmissionClient spawns the receive process
    instead: at SPARE_NICE it would wait for a CPU on a loaded twin.

    rospy takes a node's namespace once, when it is imported (from `__ns:=` on the command line or
    ROS_NAMESPACE): the fork server imports it under this process's namespace, passed on in its
    environment (its own command line is multiprocessing's). Without it the receive process came up
    in / and subscribed to nothing the twin's bridge publishes (live, a chaos soak's killed map
    server restarted from its spare: 0 clouds received)."""
    global _start_context, _fork_server_pid
    import rosgraph.names

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([*RECEIVE_PROCESS_IMPORTS, __name__])
    before = os.environ.get(rosgraph.names.ROS_NAMESPACE)
    os.environ[rosgraph.names.ROS_NAMESPACE] = rosgraph.names.get_ros_namespace(argv=sys.argv)
    try:
        # a first child waits for the server's imports: they are done before this returns; it
        # says who its parent, the fork server, is
        parent_end, child_end = context.Pipe(duplex=False)
        first = context.Process(target=_send_parent_pid, args=(child_end,), name="fork_server_ready", daemon=True)
        first.start()
        child_end.close()
        fork_server_pid = parent_end.recv()
        first.join()
    finally:
        if before is None:
            del os.environ[rosgraph.names.ROS_NAMESPACE]
        else:
            os.environ[rosgraph.names.ROS_NAMESPACE] = before
    _start_context = context
    _fork_server_pid = fork_server_pid


_fork_server_pid = None  # prepare_fast_start's fork server


def _send_parent_pid(conn):
    conn.send(os.getppid())


def _context_for(nice):
    """The start context for a receive process at `nice`: the fork server's unless it runs above
    `nice` and this process may not set its child back (then spawn)."""
    from cps_ros import priority

    if _start_context.get_start_method() != "forkserver":
        return _start_context
    if _fork_server_pid is None:
        return multiprocessing.get_context("spawn")
    try:
        above = priority.process_nice(_fork_server_pid) > nice
    except OSError:  # the fork server gone
        return multiprocessing.get_context("spawn")
    if above and not priority.may_lower_nice_to(nice):
        return multiprocessing.get_context("spawn")
    return _start_context


@dataclasses.dataclass(frozen=True)
class AdmissionConfig:
    """What the receive process needs of the map server's settings."""

    node_name: str
    remappings: Tuple[str, ...]  # the map server's command-line remappings (__ns:=..., topic:=...)
    robots: Tuple[str, ...]
    frame_id: str
    tf_timeout_s: float
    nice: int  # the map server's ~receive_nice: when both want the core, the insertion comes first


def remappings_of(argv: List[str]) -> Tuple[str, ...]:
    """The remapping arguments of a node's argv that its receive process shares: the namespace and
    topic remaps, not its name, log file or private parameters."""

    def shared(arg):
        if ":=" not in arg or arg.startswith(("__name:=", "__log:=")):
            return False
        return arg.startswith("__") or not arg.startswith("_")  # __ns, __master...; not _private:=

    return tuple(a for a in argv if shared(a))


class AdmissionClient:
    """The receive process, seen from the insertion: `next_cloud`, `snapshot`, `close` (the
    interface of cps_mapping.admission.Admission, without `receive`: the process receives)."""

    def __init__(self, config: AdmissionConfig):
        from cps_ros import priority

        nice = priority.thread_nice() + config.nice
        context = _context_for(nice)
        self._next, child_next = context.Pipe()
        self._control, child_control = context.Pipe()
        self.process = context.Process(
            target=_run, args=(config, nice, child_next, child_control), name=config.node_name, daemon=True
        )
        self.process.start()
        child_next.close()
        child_control.close()
        self._control_lock = threading.Lock()
        self._in_flight = False
        self._placed = collections.deque()  # placed clouds received, not yet taken by the insertion
        if not self._control.poll(READY_TIMEOUT_S):
            self.process.terminate()
            raise RuntimeError(f"the receive process {config.node_name} did not start within {READY_TIMEOUT_S} s")
        self._control.recv()  # "ready": subscribed

    def next_cloud(self, timeout_s=None):
        """The next placed cloud (cps_mapping.admission.PlacedCloud), waiting up to `timeout_s`;
        None if none came. A request for the next batch is in flight while this one is inserted."""
        try:
            if not self._placed or self._in_flight:
                if not self._in_flight:
                    self._next.send(BATCH)
                    self._in_flight = True
                if self._next.poll(0 if self._placed else timeout_s):
                    self._placed.extend(self._next.recv())
                    self._in_flight = False
            if not self._in_flight and len(self._placed) < BATCH:
                self._next.send(BATCH)
                self._in_flight = True
        except (EOFError, OSError, BrokenPipeError):  # the process ended (shutdown)
            return None
        return self._placed.popleft() if self._placed else None

    def snapshot(self):
        """{robot: (AdmissionCounters, clouds waiting)} of the receive process."""
        with self._control_lock:
            self._control.send("snapshot")
            return self._control.recv()

    def close(self):
        try:
            with self._control_lock:
                self._control.send("close")
        except (OSError, BrokenPipeError):
            pass
        self.process.join(timeout=5.0)
        if self.process.is_alive():
            self.process.terminate()


def _run(config: AdmissionConfig, nice, next_conn, control_conn):
    """The receive process at `nice`: subscribers, transforms and slots; answers the insertion's
    requests."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass
    from cps_ros import priority

    try:
        priority.set_thread_nice(nice)
    except PermissionError:
        pass  # forked above `nice` without the right to lower it: _context_for spawns in that case
    import logging

    import rospy
    import tf2_py
    from geometry_msgs.msg import TransformStamped

    from cps_fleet import names
    from cps_mapping.admission import Admission, TransformUnavailable
    from cps_mapping.cloud_input import quaternion_matrix
    from cps_mapping.transforms import LazyTransforms
    from cps_ros.shutdown import init_node

    init_node(config.node_name, argv=[config.node_name, *config.remappings])
    log = logging.getLogger(f"rosout.{config.node_name}")
    transforms = LazyTransforms()  # /tf read when a cloud is placed, not in the receiving threads
    backfill_poses = BackfillPoses()

    def _pose(tf):
        t, q = tf.transform.translation, tf.transform.rotation
        return quaternion_matrix(q.x, q.y, q.z, q.w), (t.x, t.y, t.z)

    def transform_of(frame, stamp):
        try:
            return _pose(transforms.lookup(config.frame_id, frame, stamp))
        except tf2_py.TransformException as exc:
            raise TransformUnavailable(str(exc)) from exc

    def keyframe_pose_of(frame, stamp):
        tf = backfill_poses.take(frame, stamp.to_nsec())
        if tf is None:
            raise TransformUnavailable(f"the pose sent with the keyframe of '{frame}' has not come")
        return _pose(tf)

    admission = Admission(
        list(config.robots),
        transform_of,
        config.tf_timeout_s,
        config.frame_id,
        log,
        keyframe_pose_of=keyframe_pose_of,
    )
    rospy.Subscriber(names.TF, rospy.AnyMsg, transforms.received, queue_size=None, buff_size=RECEIVE_CHUNK_BYTES)
    rospy.Subscriber(names.TF_STATIC, rospy.AnyMsg, lambda m: transforms.received(m, static=True), queue_size=None)
    # rospy.AnyMsg: nothing deserialized in the receiving threads, and no subscriber queue bound
    # (queue_size None): what rospy reads reaches the slot, where it is counted.
    for robot in config.robots:
        rospy.Subscriber(
            names.managed_cloud(robot),
            rospy.AnyMsg,
            lambda msg, r: admission.receive(r, msg),
            callback_args=robot,
            queue_size=None,
            buff_size=RECEIVE_CHUNK_BYTES,
        )
        rospy.Subscriber(
            names.robot_topic(robot, names.POINTS_BACKFILL_DRACO),
            rospy.AnyMsg,
            lambda msg, r: admission.receive(r, msg, backfill=True),
            callback_args=robot,
            queue_size=None,
            buff_size=RECEIVE_CHUNK_BYTES,
        )
        rospy.Subscriber(
            names.robot_topic(robot, names.POINTS_BACKFILL_POSE), TransformStamped, backfill_poses.keep, queue_size=50
        )
    clock = {"last": rospy.Time.now()}

    def serve_next():
        while True:
            try:
                batch = next_conn.recv()
            except (EOFError, OSError):
                return
            first = admission.next_cloud(timeout_s=REQUEST_WAIT_S)
            placed = [first] if first is not None else []
            while placed and len(placed) < batch:  # what else is ready now, without waiting
                more = admission.next_cloud(timeout_s=0)
                if more is None:
                    break
                placed.append(more)
            now = rospy.Time.now()
            if now < clock["last"]:  # a replayed bag looped: its transforms start again
                log.warning(f"{config.node_name}: time went back {(clock['last'] - now).to_sec():.1f} s: tf cleared")
                transforms.clear()
            clock["last"] = now
            transforms.catch_up()
            try:
                next_conn.send(placed)
            except (OSError, BrokenPipeError):
                return

    threading.Thread(target=serve_next, name="serve_next", daemon=True).start()
    control_conn.send("ready")
    while True:
        try:
            request = control_conn.recv()
        except (EOFError, OSError):
            break
        if request == "close":
            break
        control_conn.send(admission.snapshot())
    admission.close()
    rospy.signal_shutdown("the map server closed its receive process")


class BackfillPoses:
    """Poses of backfill keyframes (geometry_msgs/TransformStamped, sent just before each) waiting
    for their cloud, by (sensor frame, stamp ns); the oldest forgotten beyond KEPT."""

    KEPT = 200

    def __init__(self):
        import collections

        self._poses = collections.OrderedDict()
        self._lock = threading.Lock()

    def keep(self, msg):
        with self._lock:
            self._poses[(msg.child_frame_id.lstrip("/"), msg.header.stamp.to_nsec())] = msg
            while len(self._poses) > self.KEPT:
                self._poses.popitem(last=False)

    def take(self, frame, stamp_ns):
        with self._lock:
            return self._poses.pop((frame, stamp_ns), None)

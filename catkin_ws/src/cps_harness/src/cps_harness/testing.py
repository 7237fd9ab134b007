"""The toolkit the packages' ROS tests share: waiting for a condition, and recording a topic.

The pytest fixtures in catkin_ws/src/conftest.py (`ros_master`, `ros`, `rospy_node`) start the
private master; this module holds what tests do on it, so that no test file keeps its own copy.
Wait for the event a test expects (a message, a counter moving) rather than sleeping and then
asserting that nothing changed.
"""

import os
import re
import threading
import time

from cps_ros.processes import RosGraph, find_node, free_port, processes_named

__all__ = ["RosGraph", "TopicRecorder", "find_node", "free_port", "link_name", "processes_named", "wait_for"]


def link_name(tag):
    """A shaped link's name of this test process's own, `<tag><pid>` (a tag of 1-3 letters keeps it
    within cps_link's 10 characters for any pid): a link a killed run left behind cannot stop the
    next run, and two checkouts testing on one machine do not meet."""
    if not re.fullmatch(r"[a-z]{1,3}", tag):
        raise ValueError(f"link tag must be 1-3 lowercase letters, got {tag!r}")
    return f"{tag}{os.getpid()}"


def wait_for(predicate, timeout_s=10.0, poll_s=0.05):
    """The first truthy value of `predicate()` within `timeout_s`, else None (assert on it)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value or time.monotonic() >= deadline:
            return value or None
        time.sleep(poll_s)


class Gate:
    """A FIFO that child processes wait at by opening it to read (`open(path).close()` blocks until
    `release`): a wait on an event, not a poll of a file. Once released it stays open (this side
    holds it open for writing), so a child that comes to it later goes through too; `close` at the
    end."""

    def __init__(self, path):
        self.path = str(path)
        os.mkfifo(self.path)
        self._fd = None

    def release(self):
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDWR)  # a FIFO opened read-write never blocks

    def close(self):
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class TopicRecorder:
    """Every message of a topic with its monotonic arrival time, the newest one, and waits on them.

    `key(msg)` (optional) also keeps the newest message per key, e.g. per robot of an array topic.
    """

    def __init__(self, topic, msg_type, key=None, queue_size=100, buff_size=2**26):
        import rospy

        self.key = key
        self.messages = []  # (arrival monotonic s, msg)
        self.by_key = {}
        self._cond = threading.Condition()
        self.sub = rospy.Subscriber(topic, msg_type, self._on, queue_size=queue_size, buff_size=buff_size)

    def _on(self, msg):
        with self._cond:
            self.messages.append((time.monotonic(), msg))
            if self.key is not None:
                self.by_key[self.key(msg)] = msg
            self._cond.notify_all()

    @property
    def latest(self):
        with self._cond:
            return self.messages[-1][1] if self.messages else None

    @property
    def count(self):
        with self._cond:
            return len(self.messages)

    def wait(self, predicate=lambda msg: True, timeout_s=20.0, what=None):
        """The newest message once `predicate(msg)` holds for it; AssertionError after `timeout_s`."""
        with self._cond:
            ok = self._cond.wait_for(lambda: bool(self.messages) and predicate(self.messages[-1][1]), timeout_s)
            if not ok:
                last = self.messages[-1][1] if self.messages else None
                raise AssertionError(
                    f"timed out after {timeout_s} s waiting for {what or 'a message'} on {self.sub.name}; last: {last}"
                )
            return self.messages[-1][1]

    def wait_count(self, count, timeout_s=20.0):
        """All messages once at least `count` have arrived; AssertionError after `timeout_s`."""
        with self._cond:
            if not self._cond.wait_for(lambda: len(self.messages) >= count, timeout_s):
                raise AssertionError(
                    f"{len(self.messages)} of {count} messages on {self.sub.name} within {timeout_s} s"
                )
            return [msg for _, msg in self.messages]

    def take(self):
        """The (arrival, msg) pairs recorded since the last take, and forget them."""
        with self._cond:
            out, self.messages = self.messages, []
        return out

    def close(self):
        self.sub.unregister()


def messages_received(node, topic, caller_id="/cps_test"):
    """How many messages `node`'s subscription to `topic` has received so far, from its own bus
    statistics (XML-RPC getBusStats, which every ROS node serves): the event a test waits for
    before it stops a node that must have had them."""
    import xmlrpc.client

    import rosgraph

    uri = rosgraph.Master(caller_id).lookupNode(node)
    _code, _message, (_published, subscribed, _services) = xmlrpc.client.ServerProxy(uri).getBusStats(caller_id)
    return sum(conn[2] for name, conns in subscribed if name == topic for conn in conns)


def answer_help(doc):
    """For the harness's nodes (loads, probes, recorders): `--help` prints `doc` and exits 0 before
    anything touches a master, as every node of the workspace does."""
    import sys

    if {"-h", "--help"} & set(sys.argv[1:]):
        print(doc.strip())
        sys.exit(0)


def run_rostest(package, test_file, timeout_s=600.0):
    """`rostest <package> <test_file>` as a user runs it (its own master on a free port, a private
    ROS_HOME); the CompletedProcess, output as text."""
    import shutil
    import subprocess
    import tempfile

    home = tempfile.mkdtemp(prefix="cps-rostest-")
    try:
        return subprocess.run(
            ["rostest", package, test_file],
            env=dict(os.environ, ROS_HOME=home),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=timeout_s,
        )
    finally:
        shutil.rmtree(home, ignore_errors=True)

"""A process group's members are found, so that stopping a node waits for its workers too."""

import os
import signal
import subprocess
import time

import pytest

from cps_ros.processes import group_members

pytestmark = pytest.mark.unit


def test_a_group_with_a_worker_is_found_whole_and_is_gone_once_killed():
    leader = subprocess.Popen(["sh", "-c", "sleep 60 & exec sleep 60"], start_new_session=True)
    try:
        deadline = time.monotonic() + 10
        while len(group_members(leader.pid)) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        members = group_members(leader.pid)
        assert leader.pid in members and len(members) == 2, members
        os.killpg(leader.pid, signal.SIGKILL)
        leader.wait(10)  # the leader's zombie is not a member; the orphaned worker is reaped by init
        while group_members(leader.pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert group_members(leader.pid) == []
    finally:
        if leader.poll() is None:
            os.killpg(leader.pid, signal.SIGKILL)
            leader.wait()


def test_a_group_nobody_is_in_has_no_members():
    assert group_members(2**22 + 1) == []  # above any pid_max


def test_cpu_seconds_grow_with_work_and_are_zero_for_a_process_that_is_gone():
    from cps_ros.processes import process_cpu_s

    before = process_cpu_s(os.getpid())
    deadline = time.process_time() + 0.2
    while time.process_time() < deadline:
        pass
    assert process_cpu_s(os.getpid()) >= before + 0.1
    assert process_cpu_s(os.getpid(), waited_children=True) >= process_cpu_s(os.getpid())
    assert process_cpu_s(2**22 + 1) == 0.0


def test_a_free_port_is_below_the_ephemeral_range_and_bindable():
    """No outgoing connection can be handed the port between the draw and the listener's bind."""
    import socket

    from cps_ros.processes import LISTEN_PORT_LOW, _ephemeral_low, free_port

    ports = {free_port() for _ in range(20)}
    assert all(LISTEN_PORT_LOW <= p < _ephemeral_low() for p in ports), ports
    assert len(ports) > 15  # drawn at random: parallel workers do not collide
    held = socket.socket()
    try:
        held.bind(("127.0.0.1", free_port()))
        held.listen(1)
        assert free_port() != held.getsockname()[1]
    finally:
        held.close()

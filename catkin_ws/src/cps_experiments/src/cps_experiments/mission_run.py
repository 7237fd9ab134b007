"""A `cps_bringup all` mission running in the background across a named shaped link, and commands
run on either side of it (tests and the benchmark). Everything it started, and the link's
namespaces, are gone when the context ends, even on failure."""

import contextlib
import os
import signal
import subprocess
import sys
import time

from cps_link.netns_link import link_down, namespace
from cps_link.netns_link import side_ip as namespace_ip
from cps_ros.processes import free_port

BRINGUP = os.path.normpath(
    os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "..", "cps_bringup", "nodes", "cps_bringup")
)


# How long a Ctrl-C'd mission gets to stop by itself before it is killed. Killed, its nodes (each in
# a session of its own) outlive it: test_zenoh_mission found them after a 60 s wait in CI, where the
# mission's orderly stop (every node SIGINT -> SIGTERM -> SIGKILL in turn, the map saved) ran longer.
STOP_TIMEOUT_S = 240.0


class BackgroundMission:
    """`with BackgroundMission(out, "cpszb", ["--robots", "scout"]) as m: m.wait_for_line("processes up")`"""

    def __init__(self, out_dir, link_name, args=(), rate="60mbit", transport="zenoh"):
        self.out_dir, self.link_name = str(out_dir), link_name
        self.port = free_port()
        self.log_path = os.path.join(self.out_dir, "bringup.log")
        self.argv = [
            sys.executable,
            BRINGUP,
            "all",
            "--out",
            self.out_dir,
            "--link",
            rate,
            "--link-name",
            link_name,
            "--port",
            str(self.port),
            "--transport",
            transport,
            *args,
        ]
        self.proc = None
        self.transport = transport
        self.helpers = []
        self.killed = False  # stop() had to kill the mission: it did not stop within its timeout

    def __enter__(self):
        os.makedirs(self.out_dir, exist_ok=True)
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                self.argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True
            )
        return self

    def __exit__(self, *exc):
        self.stop()

    def log(self):
        with open(self.log_path, errors="replace") as stream:
            return stream.read()

    def wait_for_line(self, text, timeout_s):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if text in self.log():
                return
            if self.proc.poll() is not None:
                raise AssertionError(
                    f"cps_bringup ended ({self.proc.returncode}) before '{text}':\n{self.log()[-4000:]}"
                )
            time.sleep(0.5)
        raise AssertionError(f"no '{text}' within {timeout_s} s:\n{self.log()[-4000:]}")

    def robots_master_uri(self):
        """The robots' own master (Zenoh transport), as the bringup printed it."""
        for line in self.log().splitlines():
            if "robots master " in line:
                return line.split("robots master ", 1)[1].split()[0]
        raise AssertionError(f"the bringup named no robots master:\n{self.log()[-2000:]}")

    def side_argv(self, side, argv):
        """argv run in `side`'s namespace (phys|twin) against that side's master."""
        if self.transport == "zenoh":
            master = self.robots_master_uri() if side == "phys" else f"http://127.0.0.1:{self.port}"
        else:
            master = f"http://{namespace_ip('twin')}:{self.port}"
        ros_ip = "127.0.0.1" if self.transport == "zenoh" else namespace_ip(side)
        return [
            "ip",
            "netns",
            "exec",
            namespace(self.link_name, side),
            "env",
            f"ROS_MASTER_URI={master}",
            f"ROS_IP={ros_ip}",
            *argv,
        ]

    def popen_on(self, side, argv, log_name):
        """Start argv on one side in the background; stopped with the mission."""
        log = open(os.path.join(self.out_dir, f"{log_name}.log"), "wb")
        proc = subprocess.Popen(
            self.side_argv(side, argv),
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        log.close()
        self.helpers.append(proc)
        return proc

    def set_link(self, up):
        """Cut (or restore) the link: the physical end of the veth pair down (or up)."""
        subprocess.run(
            [
                "ip",
                "-n",
                namespace(self.link_name, "phys"),
                "link",
                "set",
                f"{self.link_name}_p",
                "up" if up else "down",
            ],
            check=True,
        )

    def wait(self, timeout_s):
        """Until the mission ends by itself (--duration); its exit code."""
        return self.proc.wait(timeout_s)

    def on_twin(self, argv, timeout_s=30.0):
        """Run argv in the twin's namespace against its master; the CompletedProcess."""
        return subprocess.run(self.side_argv("twin", argv), capture_output=True, text=True, timeout=timeout_s)

    def stop(self, timeout_s=STOP_TIMEOUT_S):
        """Ctrl-C the mission (it saves the map and stops everything); kill what is left; remove the link."""
        for helper in self.helpers:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(helper.pid, signal.SIGKILL)
            helper.wait(10)
        try:
            if self.proc and self.proc.poll() is None:
                os.killpg(self.proc.pid, signal.SIGINT)
                try:
                    self.proc.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    self.killed = True  # its nodes may outlive it: a test should say so
                    os.killpg(self.proc.pid, signal.SIGKILL)
                    self.proc.wait(10)
        finally:
            with contextlib.suppress(ProcessLookupError, PermissionError, TypeError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            link_down(self.link_name)

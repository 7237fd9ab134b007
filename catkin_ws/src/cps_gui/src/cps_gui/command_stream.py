"""The operator's velocity commands at a steady rate, on a thread of their own (no Qt, no rospy).

The GUI thread sets the newest command as the operator drags or presses keys; the stream sends it
every period until told to stop, then sends one final command (zero). A Qt timer's ticks wait for
the event loop, and under load a repaint of the fleet's plots or of rviz's frame held them back: a
full run (final37) saw the GUI's own periods at 0.08-0.22 s where 0.1 was asked.

A frozen GUI must still stop its robot (the robots' dead-man stops one whose commands stop coming),
so the stream sends only while the GUI thread renews its lease: past `lease_s` without a renewal it
sends nothing until the next one.
"""

import threading
import time


class CommandSchedule:
    """What to send and when (pure; the caller serialises the calls). Times in seconds."""

    def __init__(self, period_s, lease_s):
        if not period_s > 0 or not lease_s > 0:
            raise ValueError(f"period_s and lease_s must be > 0, got {period_s} and {lease_s}")
        self.period_s, self.lease_s = period_s, lease_s
        self.target = None  # (robot, command) while driving
        self.next_s = None
        self.lease_until_s = None
        self.lapses = 0  # times the lease ran out while driving (the GUI thread held off)
        self._lapsed = False

    def drive(self, robot, command, now_s):
        """Drive `robot` with `command`; (robot, command) to send now when the stream starts or the
        robot changes, else None (sent at the next period). Renews the lease."""
        starting = self.target is None or self.target[0] != robot
        self.target = (robot, command)
        self.renew(now_s)
        if starting:
            self.next_s = now_s + self.period_s
            return self.target
        return None

    def renew(self, now_s):
        """The GUI thread is alive: the stream may send until now_s + lease_s."""
        if self.target is None:
            return
        if self._lapsed:  # back from a freeze: the next command goes at once
            self._lapsed, self.next_s = False, now_s
        self.lease_until_s = now_s + self.lease_s

    def stop(self, final=None):
        """Stop; (robot, final) to send once if it was driving and final is given, else None."""
        if self.target is None:
            return None
        robot, self.target, self._lapsed = self.target[0], None, False
        return None if final is None else (robot, final)

    def due(self, now_s):
        """((robot, command) to send now or None, seconds to wait before asking again or None: until
        told something)."""
        if self.target is None:
            return None, None
        if now_s > self.lease_until_s:
            if not self._lapsed:
                self._lapsed, self.lapses = True, self.lapses + 1
            return None, None
        if now_s < self.next_s:
            return None, min(self.next_s, self.lease_until_s) - now_s
        # the next tick one period on; ticks missed (a process held off the CPU) are not made up
        self.next_s += self.period_s
        if self.next_s <= now_s:
            self.next_s = now_s + self.period_s
        return self.target, self.next_s - now_s


class CommandStream:
    """Calls `send(robot, command)` as a CommandSchedule says, on its own thread; thread-safe."""

    def __init__(self, send, period_s, lease_s, clock=time.monotonic):
        self._send, self._clock = send, clock
        self.schedule = CommandSchedule(period_s, lease_s)
        self._cond = threading.Condition()
        self._closed = False
        self._thread = None
        self.sent = 0
        self.send_errors = 0  # sends that raised (a publisher gone at shutdown): counted, never fatal
        self.last_error = ""
        self.last_command = None

    @property
    def driving(self):
        with self._cond:
            return self.schedule.target is not None

    def drive(self, robot, command):
        with self._cond:
            if self._closed:
                raise RuntimeError("the command stream is closed")
            self._send_locked(self.schedule.drive(robot, command, self._clock()))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="teleop-commands", daemon=True)
                self._thread.start()
            self._cond.notify()

    def renew(self):
        with self._cond:
            self.schedule.renew(self._clock())
            self._cond.notify()

    def stop(self, final=None):
        """Stop; send `final` once if it was driving. Nothing of the stream is sent after this
        returns. True when it was driving."""
        with self._cond:
            was_driving = self.schedule.target is not None
            self._send_locked(self.schedule.stop(final))
            self._cond.notify()
            return was_driving

    def close(self, final=None):
        """stop(final), then end the thread."""
        self.stop(final)
        with self._cond:
            self._closed = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def _send_locked(self, what):
        if what is None:
            return
        robot, command = what
        try:
            self._send(robot, command)
            self.sent += 1
            self.last_command = command
        except Exception as exc:  # the GUI keeps its controls whatever a send does
            self.send_errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"

    def _run(self):
        with self._cond:
            while not self._closed:
                what, wait_s = self.schedule.due(self._clock())
                self._send_locked(what)
                if what is None:
                    self._cond.wait(wait_s)

"""Sensor captures in worker processes, so rendering neither blocks odometry nor holds one core.

PyBullet keeps the GIL for the whole of a render or a ray batch, so in one process a 100 ms
render stops odometry and tf for 100 ms and the fleet's sensors share a single core. Each
worker holds its own copy of the world (the hall and every robot's body, so robots see each
other) and captures any robot's sensor on request, given the poses of all robots at the
request instant. The caller (fleet_sim) sends a request to an idle worker, keeps integrating
and publishing state, and collects the result when it is ready.
"""
import dataclasses
import multiprocessing
import time
from typing import Dict, Optional, Tuple

Pose = Tuple[float, float, float, float]


def _worker_main(conn, fleet, site, renderer):
    """Serve capture requests until the parent sends None or goes away."""
    import signal

    from cps_sim.simulation import FleetSimulation

    # Ctrl-C reaches the whole process group; the parent decides when the workers stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    sim = FleetSimulation(fleet, site=site, renderer=renderer)
    conn.send(("ready", sim.renderer))
    try:
        while True:
            try:
                request = conn.recv()
            except (EOFError, OSError):
                break
            if request is None:
                break
            name, poses = request
            for other, (x, y, z, yaw) in poses.items():
                sim.place(other, x, y, z, yaw)
            started = time.time()
            frame = sim.capture(name)
            conn.send(("frame", name, frame, started, time.time()))
    finally:
        sim.close()


@dataclasses.dataclass
class _Worker:
    process: multiprocessing.Process
    conn: object
    busy_with: Optional[str] = None
    requested_at: float = 0.0


class SensorWorkerPool:
    """`count` processes, each able to capture any robot's sensor of `fleet` in `site`."""

    def __init__(self, fleet, site, renderer="fast", count=2, start_timeout_s=60.0):
        if count < 1:
            raise ValueError(f"need at least one sensor worker, got {count}")
        ctx = multiprocessing.get_context("spawn")
        self.workers = []
        for _ in range(count):
            parent, child = ctx.Pipe()
            process = ctx.Process(target=_worker_main, args=(child, fleet, site, renderer), daemon=True)
            process.start()
            child.close()
            self.workers.append(_Worker(process, parent))
        self.renderer = None
        for worker in self.workers:
            if not worker.conn.poll(start_timeout_s):
                self.close()
                raise RuntimeError(f"sensor worker did not start within {start_timeout_s} s")
            kind, renderer = worker.conn.recv()
            self.renderer = renderer

    def idle_worker(self):
        for worker in self.workers:
            if worker.busy_with is None:
                return worker
        return None

    def busy(self, name):
        return any(w.busy_with == name for w in self.workers)

    def request(self, worker, name, poses: Dict[str, Pose], now_s):
        worker.conn.send((name, poses))
        worker.busy_with = name
        worker.requested_at = now_s

    def results(self):
        """Finished captures: list of (name, frame, requested_at, started, finished)."""
        out = []
        for worker in self.workers:
            if worker.busy_with is not None and worker.conn.poll():
                try:
                    _, name, frame, started, finished = worker.conn.recv()
                except (EOFError, OSError):
                    self.check_alive()
                    raise RuntimeError(f"sensor worker {worker.process.pid} closed its pipe") from None
                out.append((name, frame, worker.requested_at, started, finished))
                worker.busy_with = None
        return out

    def check_alive(self):
        for worker in self.workers:
            if not worker.process.is_alive():
                raise RuntimeError(f"sensor worker {worker.process.pid} died with exit code {worker.process.exitcode}")

    def close(self):
        for worker in self.workers:
            try:
                # A worker blocked sending a frame must be read from before it can see the stop.
                if worker.busy_with is not None and worker.conn.poll(2.0):
                    worker.conn.recv()
                worker.conn.send(None)
            except (OSError, ValueError, EOFError):
                pass
        for worker in self.workers:
            worker.process.join(timeout=3.0)
            if worker.process.is_alive():
                worker.process.terminate()
                worker.process.join(timeout=2.0)
        self.workers = []

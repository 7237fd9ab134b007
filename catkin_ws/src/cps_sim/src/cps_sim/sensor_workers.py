"""Sensor captures in worker processes, so rendering neither blocks odometry nor holds one core.

PyBullet keeps the GIL for the whole of a render or a ray batch, so in one process a 100 ms
render stops odometry and tf for 100 ms and the fleet's sensors share a single core. Each
worker holds its own copy of the world (the hall and every robot's body, so robots see each
other) and captures any robot's sensor on request, given the poses of all robots at the
request instant. The caller (fleet_sim) sends a request to an idle worker, keeps integrating
and publishing state, and collects the result when it is ready.

A frame's arrays travel through a shared-memory block per worker, not the pipe: a 640x480
depth frame is 12 MB, which a pipe carried in ~50 ms on the loaded 2-core machine (a cap of
~20 frames/s for the whole fleet) where a copy out of shared memory takes a few ms. The pipe
carries only the layout; the worker writes the next frame only after the parent has copied
this one out (one request at a time per worker).
"""

import dataclasses
import multiprocessing
import os
import time
from multiprocessing import shared_memory
from typing import Dict, Optional, Tuple

import numpy as np

Pose = Tuple[float, float, float, float]
_ALIGN_BYTES = 64
# numpy's OpenBLAS keeps its threads spinning after every matrix product (the lidar rotates 30 000
# directions per scan): measured 3-4x the scan's own CPU time, burnt while the worker waits. The
# workers' products are small; one BLAS thread each. Read by numpy at import in the new process.
_WORKER_ENVIRONMENT = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


class _FrameBlock:
    """The worker's side: a shared-memory block that grows to the largest frame written into it."""

    def __init__(self):
        self.shm = None

    def write(self, frame):
        """(frame class, {field: (dtype, shape, offset)}, block name) after copying the frame's
        arrays into the block; non-array fields travel in the layout as values."""
        arrays, values, size = {}, {}, 0
        for field in dataclasses.fields(frame):
            value = getattr(frame, field.name)
            if isinstance(value, np.ndarray):
                arrays[field.name] = (np.ascontiguousarray(value), size)
                size += -(-value.nbytes // _ALIGN_BYTES) * _ALIGN_BYTES
            else:
                values[field.name] = value
        if self.shm is None or self.shm.size < size:
            self.close()
            self.shm = shared_memory.SharedMemory(create=True, size=max(size, 1))
        layout = {}
        for name, (array, offset) in arrays.items():
            np.ndarray(array.shape, array.dtype, buffer=self.shm.buf, offset=offset)[...] = array
            layout[name] = (array.dtype, array.shape, offset)
        return type(frame), layout, values, self.shm.name

    def close(self):
        if self.shm is not None:
            self.shm.close()
            self.shm.unlink()
            self.shm = None


class _FrameReader:
    """The parent's side: attaches to a worker's block by name and copies frames out of it."""

    def __init__(self):
        self.shm = None

    def read(self, frame_class, layout, values, block_name):
        if self.shm is None or self.shm.name != block_name:
            self.close()
            # Spawned workers share this process's resource tracker, so attaching registers
            # nothing new; the worker unlinks the block.
            self.shm = shared_memory.SharedMemory(name=block_name)
        fields = dict(values)
        for name, (dtype, shape, offset) in layout.items():
            fields[name] = np.ndarray(shape, dtype, buffer=self.shm.buf, offset=offset).copy()
        return frame_class(**fields)

    def close(self):
        if self.shm is not None:
            self.shm.close()
            self.shm = None


def _worker_main(conn, fleet, site, renderer):
    """Serve capture requests until the parent sends None or goes away."""
    import signal

    from cps_sim.simulation import FleetSimulation

    # Ctrl-C reaches the whole process group; the parent decides when the workers stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    sim = FleetSimulation(fleet, site=site, renderer=renderer)
    conn.send(("ready", sim.renderer))
    block = _FrameBlock()
    try:
        while True:
            try:
                request = conn.recv()
            except (EOFError, OSError):
                break
            if request is None:
                break
            key, task, poses = request
            for other, (x, y, z, yaw) in poses.items():
                sim.place(other, x, y, z, yaw)
            started = time.time()
            frame = sim.capture(task) if isinstance(task, str) else sim.capture_video(task)
            conn.send(("frame", key, block.write(frame), started, time.time()))
    finally:
        block.close()
        sim.close()


@dataclasses.dataclass
class _Worker:
    process: multiprocessing.Process
    conn: object
    busy_with: Optional[str] = None
    requested_at: float = 0.0
    reader: _FrameReader = dataclasses.field(default_factory=_FrameReader)


class SensorWorkerPool:
    """`count` processes, each able to capture any robot's sensor of `fleet` in `site`."""

    def __init__(self, fleet, site, renderer="fast", count=2, start_timeout_s=60.0):
        if count < 1:
            raise ValueError(f"need at least one sensor worker, got {count}")
        ctx = multiprocessing.get_context("spawn")
        self.workers = []
        saved_environment = {key: os.environ.get(key) for key in _WORKER_ENVIRONMENT}
        os.environ.update(_WORKER_ENVIRONMENT)
        try:
            for _ in range(count):
                parent, child = ctx.Pipe()
                process = ctx.Process(target=_worker_main, args=(child, fleet, site, renderer), daemon=True)
                process.start()
                child.close()
                self.workers.append(_Worker(process, parent))
        finally:
            for key, value in saved_environment.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
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

    def request(self, worker, name, poses: Dict[str, Pose], now_s, task=None):
        """Capture `name` (a robot: its sensor) on `worker`; with `task` (a cps_sim.video.VideoTask)
        render that video frame instead, `name` then being the scheduler's key for it."""
        worker.conn.send((name, name if task is None else task, poses))
        worker.busy_with = name
        worker.requested_at = now_s

    def results(self):
        """Finished captures: list of (name, frame, requested_at, started, finished)."""
        out = []
        for worker in self.workers:
            if worker.busy_with is not None and worker.conn.poll():
                try:
                    _, name, written, started, finished = worker.conn.recv()
                except (EOFError, OSError):
                    self.check_alive()
                    raise RuntimeError(f"sensor worker {worker.process.pid} closed its pipe") from None
                frame = worker.reader.read(*written)
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
            worker.reader.close()
            worker.process.join(timeout=3.0)
            if worker.process.is_alive():
                worker.process.terminate()
                worker.process.join(timeout=2.0)
        self.workers = []

"""The one CSV policy of the mission logs (stats.csv, allocation.csv, ...): a node that restarts
keeps appending to what its earlier run wrote, so a mission's history survives a crash. A log past
its size bound is rotated to `<path>.1` (one old file kept), so a long mission cannot fill the disk."""
import csv
import os
import threading


class CsvLog:
    """Appends rows to `path`. The header is written only when the file is new or empty, and every
    row is flushed at once, so a killed node loses nothing it logged. Thread-safe; rows written
    after `close` are dropped (a node's timer may still fire while it shuts down). `max_bytes`:
    past it the file is rotated (None: unbounded)."""

    def __init__(self, path, columns, max_bytes=None):
        self.path = path
        self.columns = tuple(columns)
        self.max_bytes = max_bytes
        self.rotations = 0
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        self._lock = threading.Lock()
        self._open()

    def _open(self):
        new = not os.path.exists(self.path) or os.path.getsize(self.path) == 0
        self._stream = open(self.path, "a", newline="")
        self._writer = csv.writer(self._stream)
        if new:
            self._writer.writerow(self.columns)
            self._stream.flush()

    def _rotate_if_full(self):
        if self.max_bytes is None or self._stream.tell() < self.max_bytes:
            return
        self._stream.close()
        os.replace(self.path, self.path + ".1")
        self.rotations += 1
        self._open()

    def write(self, row):
        """One row, as many values as columns."""
        row = tuple(row)
        if len(row) != len(self.columns):
            raise ValueError(f"{self.path}: a row of {len(row)} values for {len(self.columns)} columns")
        with self._lock:
            if self._stream.closed:
                return
            self._writer.writerow(row)
            self._stream.flush()
            self._rotate_if_full()

    def close(self):
        with self._lock:
            self._stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

"""The one CSV policy of the mission logs (stats.csv, allocation.csv, ...): a node that restarts
keeps appending to what its earlier run wrote, so a mission's history survives a crash. A log past
its size bound is rotated to `<path>.1` (one old file kept), so a long mission cannot fill the disk."""

import csv
import logging
import os
import threading


class CsvLog:
    """Appends rows to `path`. The header is written only when the file is new or empty, and every
    row is flushed at once, so a killed node loses nothing it logged. Thread-safe; rows written
    after `close` are dropped (a node's timer may still fire while it shuts down). `max_bytes`:
    past it the file is rotated (None: unbounded).

    A file that cannot be written (a full disk, a vanished folder: OSError) turns the log off:
    `on_failure(message)` is called once, `failed` holds the reason, later rows are counted in
    `rows_lost`, and the caller goes on (its topics keep publishing)."""

    def __init__(self, path, columns, max_bytes=None, on_failure=logging.getLogger(__name__).error):
        self.path = path
        self.columns = tuple(columns)
        self.max_bytes = max_bytes
        self.on_failure = on_failure
        self.rotations = 0
        self.failed = ""
        self.rows_lost = 0
        self._stream = None
        self._lock = threading.Lock()
        try:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            self._open()
        except OSError as exc:
            self._fail(exc)

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

    def _fail(self, exc):
        self.failed = f"{self.path}: {exc.strerror or exc}"
        self.rows_lost += 1
        self.on_failure(f"CSV log {self.failed}; logging to it is off from now on, the rest goes on")

    def write(self, row):
        """One row, as many values as columns."""
        row = tuple(row)
        if len(row) != len(self.columns):
            raise ValueError(f"{self.path}: a row of {len(row)} values for {len(self.columns)} columns")
        with self._lock:
            if self.failed:
                self.rows_lost += 1
                return
            if self._stream.closed:
                return
            try:
                self._writer.writerow(row)
                self._stream.flush()
                self._rotate_if_full()
            except OSError as exc:
                self._fail(exc)

    def close(self):
        with self._lock:
            if self._stream is None:
                return
            try:
                self._stream.close()
            except OSError:  # the buffered row that failed once fails again; already reported
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

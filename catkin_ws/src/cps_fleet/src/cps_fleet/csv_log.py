"""The one CSV policy of the mission logs (stats.csv, allocation.csv, ...): a node that restarts
keeps appending to what its earlier run wrote, so a mission's history survives a crash."""
import csv
import os
import threading


class CsvLog:
    """Appends rows to `path`. The header is written only when the file is new or empty, and every
    row is flushed at once, so a killed node loses nothing it logged. Thread-safe; rows written
    after `close` are dropped (a node's timer may still fire while it shuts down)."""

    def __init__(self, path, columns):
        self.path = path
        self.columns = tuple(columns)
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        new = not os.path.exists(path) or os.path.getsize(path) == 0
        self._stream = open(path, "a", newline="")
        self._writer = csv.writer(self._stream)
        self._lock = threading.Lock()
        if new:
            self.write(self.columns)

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

    def close(self):
        with self._lock:
            self._stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

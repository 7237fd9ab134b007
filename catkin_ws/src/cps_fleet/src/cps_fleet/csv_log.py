"""The one CSV policy of the mission logs (stats.csv, allocation.csv, ...): a node that restarts
keeps appending to what its earlier run wrote, so a mission's history survives a crash."""
import csv
import logging
import os
import threading


class CsvLog:
    """Appends rows to `path`. The header is written only when the file is new or empty, and every
    row is flushed at once, so a killed node loses nothing it logged. Thread-safe; rows written
    after `close` are dropped (a node's timer may still fire while it shuts down).

    A file that cannot be written (a full disk, a vanished folder: OSError) turns the log off:
    `on_failure(message)` is called once, `failed` holds the reason, later rows are counted in
    `rows_lost`, and the caller goes on (its topics keep publishing)."""

    def __init__(self, path, columns, on_failure=logging.getLogger(__name__).error):
        self.path = path
        self.columns = tuple(columns)
        self.on_failure = on_failure
        self.failed = ""
        self.rows_lost = 0
        self._stream = None
        self._lock = threading.Lock()
        try:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            new = not os.path.exists(path) or os.path.getsize(path) == 0
            self._stream = open(path, "a", newline="")
        except OSError as exc:
            self._fail(exc)
            return
        self._writer = csv.writer(self._stream)
        if new:
            self.write(self.columns)

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

"""CsvLog: append, header once, every row on disk at once."""

import csv

import pytest

from cps_fleet.csv_log import CsvLog

COLUMNS = ("time_s", "robot", "rate_hz")


def _rows(path):
    with open(path, newline="") as stream:
        return list(csv.reader(stream))


def test_a_restarted_writer_keeps_the_history_and_writes_the_header_once(tmp_path):
    path = tmp_path / "logs" / "allocation.csv"
    with CsvLog(str(path), COLUMNS) as log:
        log.write((1.0, "scout", 2.5))
    with CsvLog(str(path), COLUMNS) as log:
        log.write((2.0, "scout", 3.0))
    assert _rows(path) == [list(COLUMNS), ["1.0", "scout", "2.5"], ["2.0", "scout", "3.0"]]


def test_an_empty_file_gets_the_header(tmp_path):
    path = tmp_path / "stats.csv"
    path.write_text("")
    with CsvLog(str(path), COLUMNS):
        pass
    assert _rows(path) == [list(COLUMNS)]


def test_every_row_is_on_disk_at_once_and_none_after_close(tmp_path):
    path = tmp_path / "stats.csv"
    log = CsvLog(str(path), COLUMNS)
    log.write((1.0, "jackal", 30.0))
    assert _rows(path)[-1] == ["1.0", "jackal", "30.0"]
    log.close()
    log.write((2.0, "jackal", 30.0))
    assert len(_rows(path)) == 2


def test_a_row_of_the_wrong_width_is_refused(tmp_path):
    with CsvLog(str(tmp_path / "x.csv"), COLUMNS) as log, pytest.raises(ValueError, match="2 values for 3"):
        log.write((1.0, "scout"))


def test_a_log_past_its_bound_rotates_and_both_files_stay_bounded(tmp_path):
    path = tmp_path / "stats.csv"
    rows = 5000
    with CsvLog(str(path), COLUMNS, max_bytes=4000) as log:
        for k in range(rows):
            log.write((float(k), "scout", 2.5))
        rotations = log.rotations
    assert rotations > 10
    current, previous = _rows(path), _rows(str(path) + ".1")
    assert current[0] == list(COLUMNS) and previous[0] == list(COLUMNS)  # each file reads alone
    assert path.stat().st_size < 4000 + 100 and (tmp_path / "stats.csv.1").stat().st_size < 4000 + 100
    assert current[-1] == [str(float(rows - 1)), "scout", "2.5"]  # the newest rows are kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stats.csv", "stats.csv.1"]


def test_a_full_disk_turns_the_log_off_once_and_counts_the_rows_lost():
    errors = []
    log = CsvLog("/dev/full", COLUMNS, on_failure=errors.append)
    for i in range(5):
        log.write((float(i), "scout", 1.0))
    log.close()
    assert len(errors) == 1 and "No space left on device" in errors[0] and "/dev/full" in errors[0]
    assert log.failed and log.rows_lost == 6  # the header and five rows


def test_an_unwritable_folder_turns_the_log_off_instead_of_raising(tmp_path):
    (tmp_path / "file").write_text("")
    errors = []
    log = CsvLog(str(tmp_path / "file" / "stats.csv"), COLUMNS, on_failure=errors.append)
    log.write((1.0, "scout", 1.0))
    assert len(errors) == 1 and log.rows_lost == 2  # the header and the row

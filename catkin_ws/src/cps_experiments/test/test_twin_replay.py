"""The replay trials' ledger: every cloud the replay sent ends in one cause (inserted, superseded,
waiting, queue, decoder, tf, map server) or shows as unaccounted, never hidden."""

import csv

from cps_experiments.twin_replay import CAUSES, CSV_COLUMNS, ledger, write_rows_csv

from cps_msgs.msg import RobotMapStats


def _row(**counts):
    return RobotMapStats(robot="a", **counts)


def test_the_causes_sum_to_what_was_sent_and_what_no_counter_saw_is_unaccounted():
    rows = [
        _row(
            clouds_received=10,
            clouds_inserted=4,
            clouds_superseded=3,
            clouds_dropped_tf=1,
            queue_length=1,
            clouds_dropped_decoder=1,
            clouds_missed=2,
        ),
        _row(clouds_received=5, clouds_inserted=2, clouds_superseded=2, clouds_dropped_invalid=1),
    ]
    counts = ledger(17, 0, rows)
    assert sum(counts[c] for c in CAUSES) == 17
    assert (counts["queue"], counts["unaccounted"], counts["received_not_ended"]) == (2, 0, 0)
    short = ledger(20, 1, rows)  # three sent clouds no counter saw
    assert short["unaccounted"] == 3 and short["replay_dropped"] == 1 and sum(short[c] for c in CAUSES) == 20


def test_rows_are_written_with_every_column(tmp_path):
    row = {c: 1 for c in CSV_COLUMNS} | {"age_p95_s": float("inf"), "oldest_over_median": float("nan")}
    path = write_rows_csv([row], tmp_path / "rows.csv")
    with open(path) as stream:
        (read,) = list(csv.DictReader(stream))
    assert list(read) == list(CSV_COLUMNS) and read["age_p95_s"] == "inf" and read["oldest_over_median"] == ""

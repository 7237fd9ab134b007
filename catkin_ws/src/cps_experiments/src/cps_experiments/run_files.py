"""Reading a run's CSV files for its judging: every row that is whole, and what is wrong with the
file, said rather than dropped (the verdict, the ledger and the reports read them one way)."""

import csv
import os


def read_rows(path):
    """(rows as dicts, problems): the rows of a CSV, and what is wrong with the file (missing, empty,
    rows with the wrong number of fields, a last line cut off). Bad rows are kept out of the rows
    and counted in the problems, never dropped silently."""
    name = os.path.basename(path)
    if not os.path.isfile(path):
        return [], [f"{name} is missing"]
    with open(path, newline="") as stream:
        text = stream.read()
    if not text.strip():
        return [], [f"{name} is empty"]
    records = list(csv.reader(text.splitlines()))
    header, body = records[0], records[1:]
    rows, bad = [], []
    for line, record in enumerate(body, start=2):
        if len(record) != len(header):
            bad.append(line)
        else:
            rows.append(dict(zip(header, record)))
    problems = []
    if not text.endswith("\n") and body and (len(body) + 1) not in bad:
        bad.append(len(body) + 1)
        rows.pop()
    if bad:
        problems.append(
            f"{name}: {len(bad)} truncated row(s) (line {', '.join(map(str, sorted(bad)[:5]))}"
            f"{', ...' if len(bad) > 5 else ''}), not counted in the figures"
        )
    if not body:
        problems.append(f"{name} has a header and no rows")
    return rows, problems

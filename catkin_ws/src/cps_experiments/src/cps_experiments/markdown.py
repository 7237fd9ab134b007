"""Reading a mission's CSV cells, writing an experiment's table as CSV and as a markdown table."""

import csv
import math
import os


def csv_float(value):
    """A CSV cell as a float; NaN for an empty or missing cell (never an exception)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def markdown_table(headers, rows):
    """A GitHub markdown table; cells are str()-ed as given (format numbers before)."""
    lines = ["| " + " | ".join(str(h) for h in headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def write_csv(path, headers, rows):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(headers)
        writer.writerows(rows)


def write_markdown(path, title, sections):
    """`sections`: strings (paragraphs, tables, image links) joined by blank lines under `# title`."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as stream:
        stream.write(f"# {title}\n\n" + "\n\n".join(s.rstrip() for s in sections if s) + "\n")


def fmt(value, digits=2):
    return f"{value:.{digits}f}"

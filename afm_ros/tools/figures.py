"""Figures and CSV tables for every command: one way to get matplotlib (off-screen, imported only
when a figure is drawn) and one way to write a table (doubles as their shortest exact text)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib.pyplot on the off-screen Agg backend (imported here: it takes ~0.5 s)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def csv_value(value):
    """A table cell: booleans as 0/1, floats as their shortest exact text (repr), the rest as
    is."""
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return value


def write_csv(path: Path, columns, rows) -> Path:
    """A CSV file of ``columns`` (the header) and ``rows``: mappings by column name, or sequences
    in order."""
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for row in rows:
            cells = [row[c] for c in columns] if isinstance(row, dict) else row
            writer.writerow([csv_value(v) for v in cells])
    return path

"""Time series from CSV files: ``time_s,value`` rows, the power profile's and the load's."""

from __future__ import annotations

import csv
import math
from pathlib import Path


def read_rows(path: Path, unit: str, low: float, high: float) -> list[tuple[float, float]]:
    """Rows ``time_s,<unit>`` (a header row and ``#`` comments are allowed): finite numbers,
    values within ``low..high``, times starting at 0 and increasing. ``ValueError`` names the
    file and line."""
    rows: list[tuple[float, float]] = []
    with open(path, newline="") as f:
        for lineno, row in enumerate(csv.reader(f), 1):
            if not row or row[0].strip().startswith("#"):
                continue
            try:
                t, value = float(row[0]), float(row[1])
            except (ValueError, IndexError):
                if lineno == 1:
                    continue  # header
                raise ValueError(f"{path}:{lineno}: expected time_s,{unit}") from None
            if not (math.isfinite(t) and math.isfinite(value) and low <= value <= high):
                raise ValueError(
                    f"{path}:{lineno}: time_s and {unit} must be finite, {unit} {low:g}..{high:g}"
                )
            if (rows and t <= rows[-1][0]) or (not rows and t != 0):
                raise ValueError(f"{path}:{lineno}: times must start at 0 and increase")
            rows.append((t, value))
    if not rows:
        raise ValueError(f"{path}: no {unit} rows")
    return rows

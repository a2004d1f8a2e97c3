"""Columns of a stage's parquet table as numpy arrays, read row group by row group.

A long scan's points file holds tens of millions of rows: read through pandas, each string
column becomes a column of Python objects (hundreds of bytes a row), and pyarrow's memory
pool keeps what a whole-table read allocated long after it is freed. ``read_columns`` fills
preallocated arrays one row group at a time (the pool's high-water mark is one group), and
turns the ``laser`` labels into uint8 codes (1 = A, 2 = B, 0 = anything else) without
making strings of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["LASER_CODES", "column_type_problems", "frame_counts", "laser_codes_of",
           "read_columns"]

LASER_CODES = {"A": 1, "B": 2}  # 0: no laser, or one the rig does not have

# what a column of a stage's table holds, by name, as the stages write it (triangulate's
# POINTS_SCHEMA, the extractor's STRIPES_SCHEMA); every other column read holds numbers
WHOLE = ("frame", "flags")  # int64, uint8
TEXT = ("laser", "lasers")  # string


def frame_counts(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct frame numbers (sorted) of a points column and how many points each has.

    A histogram of the frame numbers where they are non-negative and not absurdly large: O(N)
    and no copy of a long scan's column (``np.unique`` sorts a copy, 16 B a point at int64);
    ``np.unique`` otherwise.
    """
    f = np.asarray(frame)
    if f.dtype.kind not in "iu":
        f = f.astype(np.int64)
    if len(f) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo, hi = int(f.min()), int(f.max())
    if lo >= 0 and hi < 100_000_000:
        counts = np.bincount(f, minlength=hi + 1)
        seen = np.flatnonzero(counts)
        return seen, counts[seen]
    seen, counts = np.unique(f, return_counts=True)
    return seen.astype(np.int64), counts


def _kind(name: str, t) -> tuple[str, bool]:
    """What column ``name`` must hold, and whether pyarrow type ``t`` holds it."""
    import pyarrow as pa

    if pa.types.is_dictionary(t):  # an encoding (pandas' categories): its values' type counts
        t = t.value_type
    if name in WHOLE:
        return "whole numbers (an integer type, as the stages write it)", pa.types.is_integer(t)
    if name in TEXT:
        return "texts (string)", pa.types.is_string(t) or pa.types.is_large_string(t)
    return ("numbers (float64, as the stages write it)",
            pa.types.is_floating(t) or pa.types.is_integer(t))


def column_type_problems(schema, columns: Sequence[str]) -> list[str]:
    """Why each of ``columns`` that the pyarrow ``schema`` has does not hold what the stages
    write there (a number stored as text, ...): one text a column, empty where all do."""
    wrong = []
    for name in columns:
        i = schema.get_field_index(name)
        if i < 0:
            continue
        want, ok = _kind(name, schema.field(i).type)
        if not ok:
            wrong.append(f"column '{name}' is {schema.field(i).type}: expected {want}")
    return wrong


def laser_codes_of(column) -> np.ndarray:
    """uint8 codes (1 = A, 2 = B, 0 = other or null) of a pyarrow array of laser labels."""
    import pyarrow.compute as pc

    lab = column.cast("string")
    out = np.zeros(len(lab), dtype=np.uint8)
    for name, code in LASER_CODES.items():
        out[np.asarray(pc.equal(lab, name).fill_null(False))] = code
    return out


def read_columns(path: str | Path, columns: Sequence[str]) -> dict[str, np.ndarray]:
    """The named columns of a parquet file (those it has) as 1-D arrays of its rows.

    ``laser`` comes as :func:`laser_codes_of` codes; every other column in its own dtype.
    Raises what pyarrow raises for a file that is not parquet, and ValueError where a column
    read does not hold what the stages write there (:func:`column_type_problems`: a number
    stored as text is not cast); callers name the file.
    """
    import pyarrow.parquet as pq

    f = pq.ParquetFile(path)
    names = set(f.schema_arrow.names)
    cols = [c for c in columns if c in names]
    wrong = column_type_problems(f.schema_arrow, cols)
    if wrong:
        raise ValueError("; ".join(wrong))
    n = f.metadata.num_rows
    out: dict[str, np.ndarray] = {}
    k = 0
    for g in range(f.num_row_groups):
        t = f.read_row_group(g, columns=cols)
        m = t.num_rows
        for c in cols:
            v = laser_codes_of(t[c]) if c == "laser" else t[c].to_numpy()
            if c not in out:
                out[c] = np.empty(n, dtype=v.dtype)
            out[c][k:k + m] = v
        k += m
    for c in cols:
        out.setdefault(c, np.empty(0))
    return out

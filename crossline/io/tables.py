"""Read and check a capture's CSV tables (``shared/DESIGN.md`` §2): the rows of a CSV with
its expected columns, an arm pose per row (position and unit quaternion), and a scan's
frames.csv (:class:`FramesTable`, :func:`read_frames_table`), each fault a problem naming the
file and its line. Split from :mod:`crossline.io.capture` (issue 21.3), which re-exports these
names and reads calibration/handeye/poses.csv with the same helpers.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crossline.geometry import transform_from_pose
from crossline.io.contract import (
    FRAME_COLUMNS,
    LASER_STATES,
    LASERS,
    QUAT_TOLERANCE,
    CaptureError,
    Problem,
    _Inside,
)

__all__ = ["FramesTable", "read_frames_table"]


# ----------------------------------------------------------------------------- CSV tables


def _read_table(
    path: Path, rel: str, columns: tuple[str, ...], problems: list[Problem]
) -> list[tuple[int, dict[str, str]]]:
    """Rows of a CSV with exactly ``columns`` as (line number, {column: text})."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        problems.append(Problem(rel, f"cannot be read ({exc.strerror})"))
        return []
    except UnicodeDecodeError:
        problems.append(Problem(rel, "not a UTF-8 text file"))
        return []
    reader = csv.reader(text.splitlines())
    try:
        header = next(reader)
    except StopIteration:
        problems.append(Problem(rel, f"empty; expected a header {','.join(columns)}"))
        return []
    except csv.Error as exc:
        problems.append(Problem(rel, f"not valid CSV: {exc}", 1))
        return []
    header = [h.strip() for h in header]
    missing = [c for c in columns if c not in header]
    if missing:
        problems.append(
            Problem(
                rel,
                f"missing column(s) {missing}; expected the header {','.join(columns)}, "
                f"found {','.join(header)}",
                1,
            )
        )
        return []
    index = {c: header.index(c) for c in columns}
    rows = []
    try:
        for lineno, fields in enumerate(reader, start=2):
            if not fields or all(not f.strip() for f in fields):
                continue
            if len(fields) != len(header):
                problems.append(
                    Problem(rel, f"has {len(fields)} fields, expected {len(header)} "
                            f"({','.join(header)}); truncated or malformed row", lineno)
                )
                continue
            rows.append((lineno, {c: fields[i].strip() for c, i in index.items()}))
    except csv.Error as exc:
        problems.append(Problem(rel, f"not valid CSV: {exc}", reader.line_num))
    return rows


def _pose(
    row: dict[str, str], lineno: int, rel: str, problems: list[Problem]
) -> np.ndarray | None:
    """x, y, z, qw, qx, qy, qz of a row as floats, or None (with problems) if invalid."""
    vals = []
    for c in ("x", "y", "z", "qw", "qx", "qy", "qz"):
        try:
            v = float(row[c])
        except ValueError:
            problems.append(Problem(rel, f"'{c}' = {row[c]!r} is not a number", lineno))
            return None
        if not math.isfinite(v):
            problems.append(Problem(rel, f"'{c}' = {row[c]} is not a finite pose value", lineno))
            return None
        vals.append(v)
    qn = math.sqrt(sum(v * v for v in vals[3:]))
    if abs(qn - 1.0) > QUAT_TOLERANCE:
        problems.append(
            Problem(rel, f"quaternion (qw, qx, qy, qz) has length {qn:.6f}, expected 1 "
                    f"(within {QUAT_TOLERANCE})", lineno)
        )
        return None
    return np.array(vals)


@dataclass(frozen=True)
class FramesTable:
    """The rows of a scan's frames.csv: frame numbers, times, laser states and arm poses."""

    frames: np.ndarray  # (N,) int
    time_s: np.ndarray  # (N,)
    lasers: np.ndarray  # (N,) str: A | B | AB | off
    T_base_tool: np.ndarray  # (N, 4, 4)


def _frames_table(
    path: Path, rel: str, problems: list[Problem], images: Path | None = None,
    rig_lasers: tuple[str, ...] = LASERS, ext: str = ".png",
) -> tuple[FramesTable, set[int], bool]:
    """Parse and check a frames.csv, each fault a problem with its line (and, with ``images``,
    a row whose frames/<frame><ext> is not there). Returns the table of the valid rows, the
    frame numbers the rows name, and whether the file has any row."""
    rows = _read_table(path, rel, FRAME_COLUMNS, problems)
    frames, times, states, poses = [], [], [], []
    seen: dict[int, int] = {}
    foreign: dict[str, list[int]] = {}  # states naming a laser the rig lacks: their lines
    last_t = -math.inf
    for lineno, row in rows:
        try:
            fr = int(row["frame"])
        except ValueError:
            problems.append(Problem(rel, f"'frame' = {row['frame']!r} is not an integer", lineno))
            continue
        if fr < 0:
            problems.append(Problem(rel, f"'frame' = {fr} is negative", lineno))
            continue
        if fr in seen:
            problems.append(Problem(rel, f"frame {fr} is duplicated (first on line {seen[fr]})",
                                    lineno))
            continue
        seen[fr] = lineno
        try:
            t = float(row["time_s"])
        except ValueError:
            problems.append(Problem(rel, f"'time_s' = {row['time_s']!r} is not a number", lineno))
            continue
        if not math.isfinite(t):
            problems.append(Problem(rel, f"'time_s' = {t} is not finite", lineno))
            continue
        if t <= last_t:
            problems.append(Problem(rel, f"time goes backwards or stands still: {t} s after "
                                         f"{last_t} s on the line before", lineno))
        last_t = max(last_t, t)
        state = row["lasers"]
        if state not in LASER_STATES:
            problems.append(Problem(rel, f"unknown laser state {state!r}; expected one "
                                         f"of {', '.join(LASER_STATES)}", lineno))
            continue
        if state != "off" and not set(state) <= set(rig_lasers):
            foreign.setdefault(state, []).append(lineno)
            continue
        pose = _pose(row, lineno, rel, problems)
        if pose is None:
            continue
        if images is not None and not (images / f"{fr:06d}{ext}").is_file():
            problems.append(Problem(rel, f"frame {fr} has no image frames/{fr:06d}{ext}", lineno))
            continue
        frames.append(fr)
        times.append(t)
        states.append(state)
        poses.append(pose)
    for state, lines in foreign.items():  # one problem per state: a scan has thousands of rows
        lacking = " and ".join(x for x in LASERS if x in state and x not in rig_lasers)
        more = (f" (and {len(lines) - 1} more row(s): lines {', '.join(map(str, lines[1:6]))}"
                f"{', ...' if len(lines) > 6 else ''})" if len(lines) > 1 else "")
        problems.append(Problem(rel, f"laser state {state!r} names laser {lacking}, which the rig "
                                     f"lacks (rig.yaml lasers: [{', '.join(rig_lasers)}]){more}",
                                lines[0]))
    P = np.array(poses).reshape(-1, 7)
    return FramesTable(np.array(frames, dtype=np.int64), np.array(times),
                       np.array(states, dtype=object),
                       transform_from_pose(P[:, :3], P[:, 3:]).reshape(-1, 4, 4)), set(seen), bool(rows)


def read_frames_table(path: str | Path, lasers: tuple[str, ...] = LASERS) -> FramesTable:
    """A scan's frames.csv on its own (its images are not looked at); CaptureError lists each
    fault. ``lasers``: the rig's lasers (a state naming another is a fault)."""
    path = Path(path)
    # named as in a capture (scans/<scan>/frames.csv under the capture folder) where it is one
    root = path.parents[2] if len(path.parents) > 2 and path.parent.parent.name == "scans" else path.parent
    rel = path.relative_to(root).as_posix()
    problems: list[Problem] = []
    if not path.is_file():
        raise CaptureError(root, [Problem(rel, "missing: every scan needs its frames.csv")])
    why = _Inside(root).why_not(path)
    if why is not None:
        raise CaptureError(root, [Problem(rel, why)])
    table, _, has_rows = _frames_table(path, rel, problems, rig_lasers=lasers)
    if not has_rows and not problems:
        problems.append(Problem(rel, "has no frames"))
    if problems:
        raise CaptureError(root, problems)
    return table

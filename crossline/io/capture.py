"""Read and validate capture folders (``shared/DESIGN.md`` §2).

``open_capture`` returns typed objects for the rig, the calibration views, the arm poses and
the scan frames; it raises :class:`CaptureError` listing *every* problem found, each naming
the file, the line and what was expected. ``check_capture`` also inspects every image
(structure, size, bit depth) and summarises the capture.

Line numbers count the CSV header as line 1, as a text editor does.
"""

from __future__ import annotations

import csv
import difflib
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from crossline.board import PATTERNS, Board
from crossline.errors import CrosslineError
from crossline.geometry import transform_from_pose
from crossline.io.images import ImageError, png_info

__all__ = [
    "ARTEFACTS",
    "FRAME_COLUMNS",
    "LASER_STATES",
    "POSE_COLUMNS",
    "Capture",
    "CaptureError",
    "FramesTable",
    "LaserView",
    "Problem",
    "Rig",
    "Scan",
    "ScanSpec",
    "ScanWindow",
    "Sensor",
    "check_capture",
    "laser_pattern",
    "open_capture",
    "read_frames_table",
    "read_rig",
]

FORMAT = "crossline-capture/1"
LASER_STATES = ("A", "B", "AB", "off")
FRAME_COLUMNS = ("frame", "time_s", "lasers", "x", "y", "z", "qw", "qx", "qy", "qz")
POSE_COLUMNS = ("image", "x", "y", "z", "qw", "qx", "qy", "qz")
# what each kind of artefact needs as nominal sizes in rig.yaml
ARTEFACTS: dict[str, tuple[str, ...]] = {
    "gauge_block": ("height",),
    "plane": (),
    "sphere": ("diameter",),
    "freeform": (),
}
QUAT_TOLERANCE = 1e-3  # |‖q‖ − 1| allowed before a quaternion is rejected
MIN_LASER_POSES = 2


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a capture: where (file, line) and what."""

    file: str
    message: str
    line: int | None = None

    def __str__(self) -> str:
        where = self.file if self.line is None else f"{self.file}, line {self.line}"
        return f"{where}: {self.message}"


class CaptureError(CrosslineError, ValueError):
    """A capture folder that does not follow the contract; ``problems`` lists each fault."""

    def __init__(self, root: Path | str, problems: list[Problem]):
        self.root = Path(root)
        self.problems = list(problems)
        lines = "\n".join(f"  - {p}" for p in self.problems)
        n = len(self.problems)
        super().__init__(f"capture {self.root}: {n} problem{'s' * (n != 1)}\n{lines}")


# ----------------------------------------------------------------------------- rig.yaml


@dataclass(frozen=True)
class Sensor:
    """Full sensor size in pixels and bit depth of its images."""

    width: int
    height: int
    bit_depth: int


@dataclass(frozen=True)
class ScanWindow:
    """The crop of the sensor that scan frames are, in full-sensor pixels."""

    x: int
    y: int
    width: int
    height: int

    @property
    def offset(self) -> tuple[int, int]:
        """(u, v) to add to a frame's pixel to get its full-sensor pixel."""
        return (self.x, self.y)


@dataclass(frozen=True)
class ScanSpec:
    """What a scan measures: the artefact kind and its nominal sizes (mm)."""

    name: str
    artefact: str
    nominal: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Rig:
    """The contents of ``rig.yaml``."""

    sensor: Sensor
    scan_window: ScanWindow
    frame_rate: float
    board: Board
    scans: dict[str, ScanSpec]
    extra: dict[str, Any] = field(default_factory=dict, repr=False)


_RIG_KEYS = ("format", "sensor", "scan_window", "frame_rate", "board", "scans")
_RIG_OPTIONAL = ("capture_date", "description", "arm", "lasers", "camera", "simulated")


def _near(key: str, known: tuple[str, ...]) -> str | None:
    match = difflib.get_close_matches(key, known, n=1, cutoff=0.75)
    return match[0] if match else None


class _RigReader:
    """Collects every problem of a rig.yaml instead of stopping at the first."""

    def __init__(self, path: Path):
        self.file = path.name if path.name == "rig.yaml" else str(path)
        self.problems: list[Problem] = []

    def bad(self, msg: str) -> None:
        self.problems.append(Problem(self.file, msg))

    def mapping(self, data: Any, where: str, keys: tuple[str, ...], optional=()) -> dict | None:
        if not isinstance(data, dict):
            self.bad(f"'{where}' must be a mapping with keys {list(keys)}, got {data!r}")
            return None
        known = keys + tuple(optional)
        for k in data:
            if k not in known:
                near = _near(str(k), known)
                if near is not None:
                    self.bad(f"unknown key '{where}.{k}' (misspelt '{where}.{near}'?)")
        for k in keys:
            if k not in data:
                self.bad(f"missing key '{where}.{k}'")
        return data

    def number(self, data: dict, where: str, key: str, kind=float, lo=None, hi=None):
        if key not in data:
            return None
        v = data[key]
        ok = isinstance(v, int | float) and not isinstance(v, bool)
        if kind is int:
            ok = ok and float(v).is_integer()
        if not ok or not math.isfinite(float(v)):
            want = "an integer" if kind is int else "a number"
            self.bad(f"'{where}.{key}' must be {want}, got {v!r}")
            return None
        v = kind(v)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            rng = f"[{lo}, {hi}]" if hi is not None else f">= {lo}"
            self.bad(f"'{where}.{key}' = {v} is out of range {rng}")
            return None
        return v


def read_rig(path: str | Path) -> Rig:
    """Parse and validate ``rig.yaml``; raise :class:`CaptureError` listing every problem."""
    path = Path(path)
    r = _RigReader(path)
    root = path.parent
    if not path.is_file():
        raise CaptureError(root, [Problem(r.file, "missing: every capture needs a rig.yaml")])
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise CaptureError(root, [Problem(r.file, f"not valid YAML: {exc}")]) from exc
    except UnicodeDecodeError as exc:
        raise CaptureError(root, [Problem(r.file, f"not a text file: {exc}")]) from exc
    if not isinstance(data, dict):
        raise CaptureError(root, [Problem(r.file, "must be a mapping of keys (see DESIGN.md §2)")])
    for k in data:
        if k not in _RIG_KEYS + _RIG_OPTIONAL:
            near = _near(str(k), _RIG_KEYS + _RIG_OPTIONAL)
            if near is not None:
                r.bad(f"unknown key '{k}' (misspelt '{near}'?)")
    for k in _RIG_KEYS:
        if k not in data:
            r.bad(f"missing key '{k}'")
    if "format" in data and data["format"] != FORMAT:
        r.bad(f"'format' must be '{FORMAT}', got {data['format']!r}")

    sensor = window = board = None
    frame_rate = r.number(data, "rig", "frame_rate", float, lo=1e-6)
    s = r.mapping(data.get("sensor", {}), "sensor", ("width", "height", "bit_depth"))
    if s is not None and "sensor" in data:
        w = r.number(s, "sensor", "width", int, lo=1)
        h = r.number(s, "sensor", "height", int, lo=1)
        b = r.number(s, "sensor", "bit_depth", int, lo=1)
        if b is not None and b not in (8, 16):
            r.bad(f"'sensor.bit_depth' must be 8 or 16, got {b}")
            b = None
        if None not in (w, h, b):
            sensor = Sensor(w, h, b)
    sw = r.mapping(data.get("scan_window", {}), "scan_window", ("x", "y", "width", "height"))
    if sw is not None and "scan_window" in data:
        vals = [r.number(sw, "scan_window", k, int, lo=0) for k in ("x", "y", "width", "height")]
        if None not in vals:
            window = ScanWindow(*vals)
            if window.width < 1 or window.height < 1:
                r.bad(f"'scan_window' must have a positive size, got {window}")
            if sensor is not None and (
                window.x + window.width > sensor.width or window.y + window.height > sensor.height
            ):
                r.bad(
                    f"'scan_window' {window.width}x{window.height} at ({window.x}, {window.y}) "
                    f"does not fit the {sensor.width}x{sensor.height} sensor"
                )
    bd = r.mapping(
        data.get("board", {}), "board", ("pattern", "cols", "rows", "spacing"),
        optional=("diameter", "circles", "accuracy_mm", "material"),
    )
    if bd is not None and "board" in data:
        pattern = bd.get("pattern")
        if "pattern" in bd and pattern not in PATTERNS:
            r.bad(f"'board.pattern' must be one of {list(PATTERNS)}, got {pattern!r}")
        cols = r.number(bd, "board", "cols", int, lo=2)
        rows = r.number(bd, "board", "rows", int, lo=2)
        spacing = r.number(bd, "board", "spacing", float, lo=1e-9)
        diameter = None
        circles = bd.get("circles", "dark")
        if pattern in ("symmetric", "asymmetric"):
            if "diameter" not in bd:
                r.bad("missing key 'board.diameter' (needed for circle grids)")
            diameter = r.number(bd, "board", "diameter", float, lo=1e-9)
            if circles not in ("dark", "light"):
                r.bad(f"'board.circles' must be 'dark' or 'light', got {circles!r}")
        if None not in (cols, rows, spacing) and pattern in PATTERNS:
            try:
                board = Board(pattern, cols, rows, spacing, diameter, circles)
            except ValueError as exc:
                if diameter is not None or pattern == "chessboard":
                    r.bad(f"'board': {exc}")
    scans: dict[str, ScanSpec] = {}
    sc = data.get("scans", {})
    if "scans" in data and not isinstance(sc, dict):
        r.bad(f"'scans' must map scan names to what they measure, got {sc!r}")
        sc = {}
    for name, spec in (sc or {}).items():
        where = f"scans.{name}"
        if not isinstance(spec, dict) or "artefact" not in spec:
            r.bad(f"'{where}' must be a mapping with an 'artefact' key, got {spec!r}")
            continue
        kind = spec["artefact"]
        if kind not in ARTEFACTS:
            r.bad(f"'{where}.artefact' must be one of {list(ARTEFACTS)}, got {kind!r}")
            continue
        nominal = {}
        for key in ARTEFACTS[kind]:
            if key not in spec:
                near = [k for k in spec if _near(str(k), (key,))]
                hint = f" (misspelt as '{near[0]}'?)" if near else ""
                r.bad(f"missing key '{where}.{key}' (a {kind} needs its nominal {key}){hint}")
                continue
            v = r.number(spec, where, key, float, lo=1e-9)
            if v is not None:
                nominal[key] = v
        for k in spec:
            if k != "artefact" and k not in ARTEFACTS[kind]:
                near = _near(str(k), ("artefact", *ARTEFACTS[kind]))
                if near is not None:
                    r.bad(f"unknown key '{where}.{k}' (misspelt '{where}.{near}'?)")
        scans[str(name)] = ScanSpec(str(name), kind, nominal)
    if r.problems:
        raise CaptureError(root, r.problems)
    extra = {k: v for k, v in data.items() if k not in _RIG_KEYS}
    return Rig(sensor, window, float(frame_rate), board, scans, extra)


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


# ----------------------------------------------------------------------------- capture


@dataclass(frozen=True)
class LaserView:
    """One board pose of a laser-plane calibration: lasers-off and laser-on images."""

    laser: str
    pose: str
    board_image: Path
    laser_image: Path


@dataclass(frozen=True)
class Scan:
    """One scan: its spec, its frames in time order, and their arm poses."""

    name: str
    root: Path
    spec: ScanSpec
    frames: np.ndarray  # (N,) int frame numbers
    time_s: np.ndarray  # (N,)
    lasers: np.ndarray  # (N,) str: A | B | AB | off
    T_base_tool: np.ndarray  # (N, 4, 4)

    def frame_path(self, frame: int) -> Path:
        """Path of a frame's PNG."""
        return self.root / "frames" / f"{int(frame):06d}.png"

    @property
    def frame_paths(self) -> list[Path]:
        """Paths of all frames, in time order."""
        return [self.frame_path(f) for f in self.frames]


@dataclass(frozen=True)
class Capture:
    """A validated capture folder."""

    root: Path
    rig: Rig
    camera_images: list[Path]
    laser_views: dict[str, list[LaserView]]
    handeye_images: list[Path]
    handeye_T_base_tool: np.ndarray  # (N, 4, 4), one per hand-eye image
    scans: dict[str, Scan]

    @property
    def truth_path(self) -> Path | None:
        """``truth.json`` if the capture is simulated, else None."""
        p = self.root / "truth.json"
        return p if p.is_file() else None

    @property
    def name(self) -> str:
        """The capture's folder name."""
        return self.root.name


def _rel(root: Path, p: Path) -> str:
    try:
        return str(p.relative_to(root))
    except ValueError:
        return str(p)


def _laser_views(root: Path, laser: str, problems: list[Problem]) -> list[LaserView]:
    d = root / "calibration" / f"laser_{laser}"
    rel = _rel(root, d)
    if not d.is_dir():
        problems.append(Problem(rel, f"missing folder: laser {laser} needs "
                                     f"<pose>_board.png and <pose>_laser.png pairs"))
        return []
    boards: dict[str, Path] = {}
    lasers: dict[str, Path] = {}
    for p in sorted(d.glob("*.png")):
        m = re.fullmatch(r"(.+)_(board|laser)\.png", p.name)
        if not m:
            problems.append(Problem(_rel(root, p), "name must be <pose>_board.png or "
                                                   "<pose>_laser.png"))
            continue
        (boards if m.group(2) == "board" else lasers)[m.group(1)] = p
    for pose in sorted(set(boards) ^ set(lasers)):
        have, want = ("board", "laser") if pose in boards else ("laser", "board")
        problems.append(Problem(rel, f"pose '{pose}' has {pose}_{have}.png but no {pose}_{want}.png"))
    poses = sorted(set(boards) & set(lasers))
    if len(poses) < MIN_LASER_POSES:
        problems.append(Problem(rel, f"has {len(poses)} complete board pose(s); the laser plane "
                                     f"needs at least {MIN_LASER_POSES}"))
    return [LaserView(laser, p, boards[p], lasers[p]) for p in poses]


def _handeye(root: Path, problems: list[Problem]) -> tuple[list[Path], np.ndarray]:
    d = root / "calibration" / "handeye"
    if not d.is_dir():
        problems.append(Problem("calibration/handeye", "missing folder"))
        return [], np.zeros((0, 4, 4))
    images = sorted(d.glob("*.png"))
    rel = "calibration/handeye/poses.csv"
    if not (d / "poses.csv").is_file():
        problems.append(Problem(rel, "missing: the arm pose of every hand-eye image is needed"))
        return images, np.zeros((0, 4, 4))
    rows = _read_table(d / "poses.csv", rel, POSE_COLUMNS, problems)
    poses: dict[str, np.ndarray] = {}
    for lineno, row in rows:
        name = row["image"]
        if name in poses:
            problems.append(Problem(rel, f"image '{name}' is listed twice", lineno))
            continue
        if not (d / name).is_file():
            problems.append(Problem(rel, f"image '{name}' has no file calibration/handeye/{name}",
                                    lineno))
        pose = _pose(row, lineno, rel, problems)
        if pose is not None:
            poses[name] = pose
    listed = {row["image"] for _, row in rows}
    for p in images:
        if p.name not in listed and rows:
            problems.append(Problem(_rel(root, p), "has no row in calibration/handeye/poses.csv"))
    if rows and len(rows) != len(images):
        problems.append(Problem(rel, f"has {len(rows)} pose rows for {len(images)} hand-eye images"))
    used = [p for p in images if p.name in poses]
    T = np.array([transform_from_pose(poses[p.name][:3], poses[p.name][3:]) for p in used])
    return used, T.reshape(-1, 4, 4)


@dataclass(frozen=True)
class FramesTable:
    """The rows of a scan's frames.csv: frame numbers, times, laser states and arm poses."""

    frames: np.ndarray  # (N,) int
    time_s: np.ndarray  # (N,)
    lasers: np.ndarray  # (N,) str: A | B | AB | off
    T_base_tool: np.ndarray  # (N, 4, 4)


def _frames_table(
    path: Path, rel: str, problems: list[Problem], images: Path | None = None
) -> tuple[FramesTable, set[int], bool]:
    """Parse and check a frames.csv, each fault a problem with its line (and, with ``images``,
    a row whose frames/<frame>.png is not there). Returns the table of the valid rows, the
    frame numbers the rows name, and whether the file has any row."""
    rows = _read_table(path, rel, FRAME_COLUMNS, problems)
    frames, times, states, poses = [], [], [], []
    seen: dict[int, int] = {}
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
        if row["lasers"] not in LASER_STATES:
            problems.append(Problem(rel, f"unknown laser state {row['lasers']!r}; expected one "
                                         f"of {', '.join(LASER_STATES)}", lineno))
            continue
        pose = _pose(row, lineno, rel, problems)
        if pose is None:
            continue
        if images is not None and not (images / f"{fr:06d}.png").is_file():
            problems.append(Problem(rel, f"frame {fr} has no image frames/{fr:06d}.png", lineno))
            continue
        frames.append(fr)
        times.append(t)
        states.append(row["lasers"])
        poses.append(pose)
    P = np.array(poses).reshape(-1, 7)
    return FramesTable(np.array(frames, dtype=np.int64), np.array(times),
                       np.array(states, dtype=object),
                       transform_from_pose(P[:, :3], P[:, 3:]).reshape(-1, 4, 4)), set(seen), bool(rows)


def read_frames_table(path: str | Path) -> FramesTable:
    """A scan's frames.csv on its own (its images are not looked at); CaptureError lists each fault."""
    path = Path(path)
    # named as in a capture (scans/<scan>/frames.csv under the capture folder) where it is one
    root = path.parents[2] if len(path.parents) > 2 and path.parent.parent.name == "scans" else path.parent
    rel = path.relative_to(root).as_posix()
    problems: list[Problem] = []
    if not path.is_file():
        raise CaptureError(root, [Problem(rel, "missing: every scan needs its frames.csv")])
    table, _, has_rows = _frames_table(path, rel, problems)
    if not has_rows and not problems:
        problems.append(Problem(rel, "has no frames"))
    if problems:
        raise CaptureError(root, problems)
    return table


def _scan(root: Path, name: str, spec: ScanSpec, problems: list[Problem]) -> Scan | None:
    d = root / "scans" / name
    rel = f"scans/{name}/frames.csv"
    if not (d / "frames.csv").is_file():
        problems.append(Problem(rel, "missing: every scan needs its frames.csv"))
        return None
    n_before = len(problems)
    table, listed, has_rows = _frames_table(d / "frames.csv", rel, problems, d / "frames")
    for p in sorted((d / "frames").glob("*.png")) if (d / "frames").is_dir() else []:
        m = re.fullmatch(r"(\d{6,})\.png", p.name)
        if not m:
            problems.append(Problem(_rel(root, p), "name must be the frame number in 6 digits, "
                                                   "e.g. 000123.png"))
        elif has_rows and int(m.group(1)) not in listed:  # an unreadable table lists no frame
            problems.append(Problem(_rel(root, p), f"has no row in {rel}"))
    if not has_rows and len(problems) == n_before:
        problems.append(Problem(rel, "has no frames"))
    if len(problems) > n_before:
        return None
    return Scan(name, d, spec, table.frames, table.time_s, table.lasers, table.T_base_tool)


def open_capture(root: str | Path) -> Capture:
    """Read a capture folder; raise :class:`CaptureError` listing every problem found.

    Only names, tables and ``rig.yaml`` are read here; :func:`check_capture` also inspects
    every image.
    """
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(root, [Problem(str(root), "is not a folder")])
    if not any(root.iterdir()):
        raise CaptureError(root, [Problem(str(root), "is empty; expected rig.yaml, calibration/ "
                                                     "and scans/ (DESIGN.md §2)")])
    rig = read_rig(root / "rig.yaml")
    problems: list[Problem] = []
    cam_dir = root / "calibration" / "camera"
    camera_images = sorted(cam_dir.glob("*.png")) if cam_dir.is_dir() else []
    if not camera_images:
        problems.append(Problem("calibration/camera", "no board views (*.png) found"))
    laser_views = {laser: _laser_views(root, laser, problems) for laser in ("A", "B")}
    he_images, he_T = _handeye(root, problems)
    scans: dict[str, Scan] = {}
    scan_dir = root / "scans"
    folders = sorted(p.name for p in scan_dir.iterdir() if p.is_dir()) if scan_dir.is_dir() else []
    for name in folders:
        if name not in rig.scans:
            problems.append(Problem(f"scans/{name}", f"is not described under 'scans:' in rig.yaml "
                                                     f"(known: {sorted(rig.scans)})"))
    for name, spec in rig.scans.items():
        if name not in folders:
            problems.append(Problem("rig.yaml", f"scan '{name}' has no folder scans/{name}"))
            continue
        scan = _scan(root, name, spec, problems)
        if scan is not None:
            scans[name] = scan
    if problems:
        raise CaptureError(root, problems)
    return Capture(root, rig, camera_images, laser_views, he_images, he_T, scans)


# ----------------------------------------------------------------------------- check


MAX_PERIOD = 64  # longest laser pattern looked for (frames); a period must repeat at least twice


def laser_pattern(states: np.ndarray | list[str]) -> dict[str, Any]:
    """The periodic laser pattern of a scan and where the sequence breaks it.

    Returns the shortest period that explains most of the sequence (e.g. ``["A", "B", "AB"]``),
    how many frames follow it, and the indices of the frames that do not.
    """
    s = list(states)
    n = len(s)
    best: dict[str, Any] = {"period": s[:1], "matching": 0, "breaks": list(range(n))}
    for p in range(1, max(1, min(MAX_PERIOD, n // 2)) + 1):
        # the most common state at each phase defines the period
        period = [Counter(s[i::p]).most_common(1)[0][0] for i in range(p)]
        breaks = [i for i in range(n) if s[i] != period[i % p]]
        if n - len(breaks) > best["matching"] + max(1, n // 50):
            best = {"period": period, "matching": n - len(breaks), "breaks": breaks}
    best["counts"] = dict(sorted(Counter(s).items()))
    return best


def check_capture(root: str | Path, images: bool = True) -> dict[str, Any]:
    """Validate a capture, images included; return its summary or raise :class:`CaptureError`."""
    cap = open_capture(root)
    problems: list[Problem] = []
    rig = cap.rig
    sensor = (rig.sensor.width, rig.sensor.height)
    window = (rig.scan_window.width, rig.scan_window.height)

    def check(p: Path, size: tuple[int, int], what: str) -> None:
        try:
            info = png_info(p)
        except ImageError as exc:
            problems.append(Problem(_rel(cap.root, p), str(exc).split(": ", 1)[-1]))
            return
        if (info.width, info.height) != size:
            problems.append(Problem(_rel(cap.root, p), f"image is {info.width}x{info.height} px, "
                                    f"expected the {what} {size[0]}x{size[1]} px"))
        if info.colour_type != 0:
            problems.append(Problem(_rel(cap.root, p), f"image is {info.colour}, expected grey"))
        if info.bit_depth not in (8, 16):
            problems.append(Problem(_rel(cap.root, p), f"image has {info.bit_depth}-bit samples, "
                                                       f"expected 8 or 16"))

    if images:
        for p in cap.camera_images + cap.handeye_images:
            check(p, sensor, "sensor")
        for views in cap.laser_views.values():
            for v in views:
                check(v.board_image, sensor, "sensor")
                check(v.laser_image, sensor, "sensor")
        for scan in cap.scans.values():
            for p in scan.frame_paths:
                check(p, window, "scan window")
    if problems:
        raise CaptureError(cap.root, problems)
    summary: dict[str, Any] = {
        "capture": cap.name,
        "sensor": {"width": rig.sensor.width, "height": rig.sensor.height,
                   "bit_depth": rig.sensor.bit_depth},
        "scan_window": {"x": rig.scan_window.x, "y": rig.scan_window.y,
                        "width": rig.scan_window.width, "height": rig.scan_window.height},
        "frame_rate": rig.frame_rate,
        "board": rig.board.to_dict(),
        "views": {
            "camera": len(cap.camera_images),
            "laser_A": len(cap.laser_views["A"]),
            "laser_B": len(cap.laser_views["B"]),
            "handeye": len(cap.handeye_images),
        },
        "scans": {},
        "simulated": cap.truth_path is not None,
        "images_checked": images,
    }
    for name, scan in cap.scans.items():
        pat = laser_pattern(scan.lasers)
        summary["scans"][name] = {
            "artefact": scan.spec.artefact,
            "nominal": scan.spec.nominal,
            "frames": len(scan.frames),
            "duration_s": float(scan.time_s[-1] - scan.time_s[0]),
            "pattern": pat["period"],
            "pattern_breaks": len(pat["breaks"]),
            "states": pat["counts"],
        }
    return summary


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable text of a :func:`check_capture` summary."""
    s = summary
    w = s["scan_window"]
    lines = [
        f"capture {s['capture']}: OK" + (" (simulated, has truth.json)" if s["simulated"] else ""),
        f"  sensor       {s['sensor']['width']}x{s['sensor']['height']} px, "
        f"{s['sensor']['bit_depth']}-bit, {s['frame_rate']:g} frames/s",
        f"  scan window  {w['width']}x{w['height']} px at ({w['x']}, {w['y']})",
        f"  board        {s['board']['pattern']} {s['board']['cols']}x{s['board']['rows']}, "
        f"spacing {s['board']['spacing']} mm",
        "  views        " + ", ".join(f"{k} {v}" for k, v in s["views"].items()),
    ]
    for name, sc in s["scans"].items():
        nominal = ", ".join(f"{k} {v:g} mm" for k, v in sc["nominal"].items())
        lines.append(
            f"  scan {name:<8}{sc['artefact']}{' (' + nominal + ')' if nominal else ''}: "
            f"{sc['frames']} frames, {sc['duration_s']:.2f} s, pattern "
            f"{'/'.join(sc['pattern'])}"
            + (f", {sc['pattern_breaks']} frame(s) break it" if sc["pattern_breaks"] else "")
        )
    return "\n".join(lines)

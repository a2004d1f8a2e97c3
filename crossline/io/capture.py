"""Read and validate capture folders (``shared/DESIGN.md`` §2).

``open_capture`` returns typed objects for the rig, the calibration views, the arm poses and
the scan frames; it raises :class:`CaptureError` listing *every* problem found, each naming
the file, the line and what was expected. ``check_capture`` also inspects every image
(structure, size, bit depth) and summarises the capture; ``allowed_stages`` says which stages
what the capture holds allows, and why not the others.

Every part of a capture is optional (camera views only, calibration without scans, ...): a
folder that is absent or empty is not a problem, one that is there but broken is. Every file a
capture names or holds (the files a simulated capture's truth.json names included) must lie
inside its folder once symbolic links are followed (a capture that reaches outside itself is
neither reproducible nor safe to process on a shared service).

Line numbers count the CSV header as line 1, as a text editor does.
"""

from __future__ import annotations

import csv
import difflib
import json
import math
import re
import reprlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np
import yaml

from crossline.board import PATTERNS, Board
from crossline.errors import CrosslineError
from crossline.geometry import transform_from_pose
from crossline.io.images import CHANNELS, IMAGE_EXTENSIONS, ImageError, image_info

__all__ = [
    "ARTEFACTS",
    "FRAME_COLUMNS",
    "LASERS",
    "LASER_STATES",
    "MESH_EXTENSIONS",
    "POSE_COLUMNS",
    "STAGES",
    "TRUTH_FILE_KEYS",
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
    "allowed_stages",
    "check_capture",
    "format_summary",
    "laser_pattern",
    "open_capture",
    "read_frames_table",
    "read_rig",
    "truth_file",
]

FORMAT = "crossline-capture/1"
LASERS = ("A", "B")
LASER_STATES = ("A", "B", "AB", "off")
DATA_BITS = (8, 10, 12, 14, 16)
MESH_EXTENSIONS = (".stl", ".ply", ".obj")
# the stages whose inputs come from the capture, in workflow order
STAGES = ("calibrate_camera", "calibrate_lasers", "calibrate_handeye", "scans")
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
MIN_CAMERA_VIEWS = 3  # Zhang's method: fewer board views do not determine the intrinsics
MIN_HANDEYE_POSES = 3  # two motions with distinct rotation axes
# the keys of a simulated capture's truth.json (under scans.<scan>) that name a file of the
# capture (crossline.sim.capture writes them as truth/<file>)
TRUTH_FILE_KEYS = ("mesh", "centrelines", "poses")


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
    """Full sensor size in pixels, the bit depth of its images' container, and optionally the
    ADC's range inside it (``data_bits``, None: inferred from the data) and the colour channel
    of colour images (``channel``, None: auto)."""

    width: int
    height: int
    bit_depth: int
    data_bits: int | None = None
    channel: str | None = None


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
    """What a scan measures: the artefact kind, its nominal sizes (mm) and, for a freeform,
    optionally its nominal mesh (path relative to the capture, as rig.yaml writes it)."""

    name: str
    artefact: str
    nominal: dict[str, float] = field(default_factory=dict)
    mesh: str | None = None
    # a freeform's placement (x, y, z, qw, qx, qy, qz; mm): its drawing's frame in the arm's
    # base frame, as probed on its datums; the nominal comparison then starts from it
    nominal_pose: tuple[float, ...] | None = None

    @property
    def T_base_nominal(self) -> np.ndarray | None:
        """The placement as a 4x4 transform (mm), or None when rig.yaml gives none."""
        if self.nominal_pose is None:
            return None
        v = np.asarray(self.nominal_pose, dtype=np.float64)
        return transform_from_pose(v[:3], v[3:])


@dataclass(frozen=True)
class Rig:
    """The contents of ``rig.yaml``."""

    sensor: Sensor
    scan_window: ScanWindow
    frame_rate: float
    board: Board
    scans: dict[str, ScanSpec]
    extra: dict[str, Any] = field(default_factory=dict, repr=False)
    lasers: tuple[str, ...] = LASERS  # sorted laser names


_RIG_KEYS = ("format", "sensor", "scan_window", "frame_rate", "board")
_RIG_OPTIONAL = ("scans", "lasers", "capture_date", "description", "arm", "camera", "simulated")


_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = 60
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict = 3, 6, 6


def _short(value: Any) -> str:
    """repr of a value read from rig.yaml, bounded (aliases can make a small file a huge tree)."""
    return _REPR.repr(value)


def _near(key: str, known: tuple[str, ...]) -> str | None:
    match = difflib.get_close_matches(key, known, n=1, cutoff=0.75)
    return match[0] if match else None


class _RigReader:
    """Collects every problem of a rig.yaml instead of stopping at the first."""

    def __init__(self, path: Path):
        self.file = path.name if path.name == "rig.yaml" else str(path)
        self.problems: list[Problem] = []
        self.lines: dict[tuple[str, ...], int] = {}

    def bad(self, msg: str, at: tuple[str, ...] | None = None) -> None:
        self.problems.append(Problem(self.file, msg, self.lines.get(at) if at else None))

    def mapping(self, data: Any, where: str, keys: tuple[str, ...], optional=()) -> dict | None:
        if not isinstance(data, dict):
            self.bad(f"'{where}' must be a mapping with keys {list(keys)}, got {_short(data)}")
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
            self.bad(f"'{where}.{key}' must be {want}, got {_short(v)}")
            return None
        v = kind(v)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            rng = f"[{lo}, {hi}]" if hi is not None else f">= {lo}"
            self.bad(f"'{where}.{key}' = {v} is out of range {rng}")
            return None
        return v


def _load_yaml(text: str) -> tuple[Any, dict[tuple[str, ...], int]]:
    """A YAML text's data (safe types only) and the line (1-based) of each mapping key of its
    first levels, by its path of keys; one parse (libyaml's where available)."""
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)(text)
    try:
        node = loader.get_single_node()
        data = loader.construct_document(node) if node is not None else None
    finally:
        loader.dispose()
    lines: dict[tuple[str, ...], int] = {}

    def walk(node: Any, path: tuple[str, ...]) -> None:
        if isinstance(node, yaml.MappingNode) and len(path) < 4:
            for k, v in node.value:
                key = (*path, str(k.value))
                lines.setdefault(key, k.start_mark.line + 1)
                walk(v, key)

    walk(node, ())
    return data, lines


def _name_problem(name: str, file_only: bool = False) -> str | None:
    """Why a file name given by a capture's file may not be used, or None."""
    if not name:
        return "is empty"
    if "\x00" in name or any(ord(c) < 32 for c in name):
        return "contains a control character"
    posix = PurePosixPath(name.replace("\\", "/"))
    if posix.is_absolute() or PureWindowsPath(name).is_absolute() or PureWindowsPath(name).drive:
        return "is an absolute path; names are relative to the capture folder, inside it"
    if ".." in posix.parts:
        return "leads out of its folder ('..'); every file of a capture lies inside it"
    if file_only and len(posix.parts) != 1:
        return "must be a file name in its folder, without a folder part"
    return None


class _Inside:
    """Whether paths under a capture folder stay inside it once symbolic links are followed."""

    def __init__(self, root: Path):
        self.root = root
        try:
            self.real = root.resolve()
        except (OSError, RuntimeError):
            self.real = root.absolute()

    def why_not(self, p: Path, parent_checked: bool = False) -> str | None:
        """Why ``p`` (a path under the capture) leads outside it, or None. With
        ``parent_checked``, its folder is known to be inside and only ``p`` itself may link."""
        try:
            if parent_checked and not p.is_symlink():
                return None
            real = p.resolve()
        except (OSError, RuntimeError) as exc:  # a loop of links
            return f"cannot be resolved ({exc})"
        if real == self.real or real.is_relative_to(self.real):
            return None
        how = "is a symbolic link" if p.is_symlink() else "lies behind a symbolic link"
        return f"{how} to {real}, outside the capture; every file of a capture lies inside its folder"


def _truth_problem(root: Path, inside: _Inside, where: str, name: Any) -> str | None:
    """Why a file name truth.json gives under the key ``where`` may not be used, or None."""
    if not isinstance(name, str):
        why = "must be a file's path relative to the capture (e.g. truth/part.ply)"
    else:
        why = _name_problem(name) or inside.why_not(root / name)
    return None if why is None else f"'{where}' = {_short(name)} {why}"


def truth_file(root: str | Path, scan: str, entry: dict[str, Any], key: str) -> Path:
    """The file of the capture ``root`` that truth.json names under ``scans.<scan>.<key>``
    (``entry``: truth.json's ``scans.<scan>``; ``key``: one of :data:`TRUTH_FILE_KEYS`), for a
    reader to open; :class:`CaptureError` naming truth.json, the key and the reason if the name
    is not a path relative to the capture that stays inside it once symbolic links are
    followed. The file need not exist (a reader skips a missing one)."""
    root = Path(root)
    name = entry[key]
    why = _truth_problem(root, _Inside(root), f"scans.{scan}.{key}", name)
    if why is not None:
        raise CaptureError(root, [Problem("truth.json", why)])
    return root / name


def _truth_files(root: Path, inside: _Inside, problems: list[Problem]) -> None:
    """A problem for each file name of truth.json (:data:`TRUTH_FILE_KEYS` of each scan) that
    leads outside the capture. An unreadable truth.json is none: the report then leaves its
    validation out, as it says."""
    try:
        truth = json.loads((root / "truth.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return
    scans = truth.get("scans") if isinstance(truth, dict) else None
    for scan, entry in (scans.items() if isinstance(scans, dict) else ()):
        for key in TRUTH_FILE_KEYS if isinstance(entry, dict) else ():
            if key in entry:
                why = _truth_problem(root, inside, f"scans.{scan}.{key}", entry[key])
                if why is not None:
                    problems.append(Problem("truth.json", why))


def read_rig(path: str | Path) -> Rig:
    """Parse and validate ``rig.yaml``; raise :class:`CaptureError` listing every problem."""
    path = Path(path)
    r = _RigReader(path)
    root = path.parent
    if not path.is_file():
        raise CaptureError(root, [Problem(r.file, "missing: every capture needs a rig.yaml")])
    inside = _Inside(root)
    why = inside.why_not(path)
    if why is not None:
        raise CaptureError(root, [Problem(r.file, why)])
    try:
        data, r.lines = _load_yaml(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise CaptureError(root, [Problem(r.file, f"not valid YAML: {exc}")]) from exc
    except UnicodeDecodeError as exc:
        raise CaptureError(root, [Problem(r.file, f"not a text file: {exc}")]) from exc
    except RecursionError as exc:
        raise CaptureError(root, [Problem(r.file, "not usable YAML: nested too deeply")]) from exc
    except OSError as exc:
        raise CaptureError(root, [Problem(r.file, f"cannot be read ({exc.strerror})")]) from exc
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
        r.bad(f"'format' must be '{FORMAT}', got {_short(data['format'])}")

    sensor = window = board = None
    frame_rate = r.number(data, "rig", "frame_rate", float, lo=1e-6)
    s = r.mapping(data.get("sensor", {}), "sensor", ("width", "height", "bit_depth"),
                  optional=("data_bits", "channel"))
    if s is not None and "sensor" in data:
        w = r.number(s, "sensor", "width", int, lo=1)
        h = r.number(s, "sensor", "height", int, lo=1)
        b = r.number(s, "sensor", "bit_depth", int, lo=1)
        if b is not None and b not in (8, 16):
            r.bad(f"'sensor.bit_depth' must be 8 or 16, got {b}")
            b = None
        data_bits = r.number(s, "sensor", "data_bits", int, lo=1)
        if data_bits is not None and data_bits not in DATA_BITS:
            r.bad(f"'sensor.data_bits' must be one of {list(DATA_BITS)}, got {data_bits}",
                  ("sensor", "data_bits"))
            data_bits = None
        if data_bits is not None and b is not None and data_bits > b:
            r.bad(f"'sensor.data_bits' = {data_bits} exceeds 'sensor.bit_depth' = {b} (the "
                  f"data lie inside the images' {b}-bit container)", ("sensor", "data_bits"))
            data_bits = None
        channel = s.get("channel")
        if channel is not None and channel not in CHANNELS:
            r.bad(f"'sensor.channel' must be one of {list(CHANNELS)}, got {_short(channel)}",
                  ("sensor", "channel"))
            channel = None
        if None not in (w, h, b):
            sensor = Sensor(w, h, b, data_bits, channel)
    lasers = LASERS
    if "lasers" in data:
        ls = data["lasers"]
        if (not isinstance(ls, list) or not ls or any(not isinstance(x, str) for x in ls)
                or len(set(ls)) != len(ls) or not set(ls) <= set(LASERS)):
            r.bad(f"'lasers' must be a list of distinct laser names from {list(LASERS)} "
                  f"(e.g. [A] for a single-line rig), got {_short(ls)}", ("lasers",))
        else:
            lasers = tuple(sorted(ls))
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
            r.bad(f"'board.pattern' must be one of {list(PATTERNS)}, got {_short(pattern)}")
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
                r.bad(f"'board.circles' must be 'dark' or 'light', got {_short(circles)}")
        if None not in (cols, rows, spacing) and pattern in PATTERNS:
            try:
                board = Board(pattern, cols, rows, spacing, diameter, circles)
            except ValueError as exc:
                if diameter is not None or pattern == "chessboard":
                    r.bad(f"'board': {exc}")
    scans: dict[str, ScanSpec] = {}
    sc = data.get("scans", {})
    if "scans" in data and not isinstance(sc, dict):
        r.bad(f"'scans' must map scan names to what they measure, got {_short(sc)}")
        sc = {}
    for name, spec in (sc or {}).items():
        where = f"scans.{name}"
        why = _name_problem(str(name), file_only=True)
        if why is not None or str(name) == ".":
            r.bad(f"scan name {str(name)!r} {why or 'is not a folder name'}: it names the folder "
                  f"scans/<scan>", ("scans", str(name)))
            continue
        if not isinstance(spec, dict) or "artefact" not in spec:
            r.bad(f"'{where}' must be a mapping with an 'artefact' key, got {_short(spec)}")
            continue
        kind = spec["artefact"]
        if not isinstance(kind, str) or kind not in ARTEFACTS:
            r.bad(f"'{where}.artefact' must be one of {list(ARTEFACTS)}, got {_short(kind)}")
            continue
        mesh = None
        if "nominal" in spec:
            at = ("scans", str(name), "nominal")
            mesh = spec["nominal"]
            if kind != "freeform":
                r.bad(f"'{where}.nominal' names a mesh, which only a freeform takes; a {kind}'s "
                      f"nominal sizes are its own keys", at)
                mesh = None
            elif not isinstance(mesh, str):
                r.bad(f"'{where}.nominal' must be a mesh file's path relative to the capture "
                      f"(e.g. part.stl), got {_short(mesh)}", at)
                mesh = None
            else:
                why = _name_problem(mesh)
                if why is None and PurePosixPath(mesh).suffix.lower() not in MESH_EXTENSIONS:
                    why = f"must be a mesh file ({', '.join(MESH_EXTENSIONS)})"
                if why is None:
                    why = inside.why_not(root / mesh)
                if why is None and not (root / mesh).is_file():
                    why = "has no file in the capture"
                if why is not None:
                    r.bad(f"'{where}.nominal' = {_short(mesh)} {why}", at)
                    mesh = None
        pose = None
        if "nominal_pose" in spec:
            at = ("scans", str(name), "nominal_pose")
            v = spec["nominal_pose"]
            if kind != "freeform" or mesh is None:
                r.bad(f"'{where}.nominal_pose' places a nominal mesh: only a freeform with a "
                      f"'nominal' takes it", at)
            elif (not isinstance(v, list) or len(v) != 7
                  or not all(isinstance(x, int | float) and not isinstance(x, bool)
                             and math.isfinite(x) for x in v)):
                r.bad(f"'{where}.nominal_pose' must be [x, y, z, qw, qx, qy, qz] (mm, the "
                      f"drawing's frame in the arm's base frame), got {_short(v)}", at)
            elif abs(math.hypot(*v[3:]) - 1.0) > 1e-3:
                r.bad(f"'{where}.nominal_pose' quaternion {v[3:]} has length "
                      f"{math.hypot(*v[3:]):.6f}; expected 1 (within 1e-3)", at)
            else:
                pose = tuple(float(x) for x in v)
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
        known = ("artefact", "nominal", "nominal_pose", *ARTEFACTS[kind])
        for k in spec:
            if k not in known:
                near = _near(str(k), known)
                if near is not None:
                    r.bad(f"unknown key '{where}.{k}' (misspelt '{where}.{near}'?)")
        scans[str(name)] = ScanSpec(str(name), kind, nominal, mesh, pose)
    if r.problems:
        raise CaptureError(root, r.problems)
    extra = {k: v for k, v in data.items() if k not in (*_RIG_KEYS, "scans", "lasers")}
    return Rig(sensor, window, float(frame_rate), board, scans, extra, lasers)


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
    """One board pose of a laser-plane calibration: the lasers-off image (None where the laser
    is always on and the board must be found despite the stripe) and the laser-on image."""

    laser: str
    pose: str
    board_image: Path | None
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
    frame_ext: str = ".png"  # the extension of this scan's frame files, as they are written

    def frame_path(self, frame: int) -> Path:
        """Path of a frame's image file."""
        return self.root / "frames" / f"{int(frame):06d}{self.frame_ext}"

    @property
    def frame_paths(self) -> list[Path]:
        """Paths of all frames, in time order."""
        return [self.frame_path(f) for f in self.frames]


@dataclass(frozen=True)
class Capture:
    """A validated capture folder. ``laser_views`` has a key for each of ``rig.lasers``; any
    set of views may be empty (see :func:`allowed_stages`)."""

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

    @property
    def lasers(self) -> tuple[str, ...]:
        """The rig's laser names (``rig.yaml`` ``lasers``)."""
        return self.rig.lasers


def _rel(root: Path, p: Path) -> str:
    try:
        return p.relative_to(root).as_posix()
    except ValueError:
        return str(p)


def _is_image(p: Path) -> bool:
    return p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".")


def _folder(root: Path, inside: _Inside, d: Path, problems: list[Problem]) -> list[Path] | None:
    """The entries of a capture folder, sorted; None if it is absent or leads outside."""
    if not d.exists() and not d.is_symlink():
        return None
    why = inside.why_not(d)
    if why is not None:
        problems.append(Problem(_rel(root, d), why))
        return None
    if not d.is_dir():
        problems.append(Problem(_rel(root, d), "must be a folder"))
        return None
    try:
        return sorted(d.iterdir())
    except OSError as exc:
        problems.append(Problem(_rel(root, d), f"cannot be listed ({exc.strerror})"))
        return None


def _usable(root: Path, inside: _Inside, p: Path, problems: list[Problem]) -> bool:
    """Whether a file found in a checked folder is a regular file inside the capture."""
    why = inside.why_not(p, parent_checked=True)
    if why is None and not p.is_file():
        why = "is not a regular file" if p.exists() else "is a broken symbolic link"
    if why is not None:
        problems.append(Problem(_rel(root, p), why))
        return False
    return True


def _images(root: Path, inside: _Inside, d: Path, problems: list[Problem]) -> list[Path]:
    """Image files directly in ``d`` (any of IMAGE_EXTENSIONS, any case), sorted."""
    entries = _folder(root, inside, d, problems) or []
    return [p for p in entries if _is_image(p) and _usable(root, inside, p, problems)]


def _laser_views(root: Path, inside: _Inside, laser: str, problems: list[Problem]) -> list[LaserView]:
    d = root / "calibration" / f"laser_{laser}"
    rel = _rel(root, d)
    images = _images(root, inside, d, problems)
    if not images:
        return []
    found: dict[tuple[str, str], list[Path]] = {}
    for p in images:
        m = re.fullmatch(r"(.+)_(board|laser)\.[^.]+", p.name)
        if not m:
            problems.append(Problem(_rel(root, p), f"name must be <pose>_board{p.suffix} or "
                                                   f"<pose>_laser{p.suffix}"))
            continue
        found.setdefault((m.group(1), m.group(2)), []).append(p)
    for (pose, kind), ps in sorted(found.items()):
        if len(ps) > 1:
            problems.append(Problem(rel, f"pose '{pose}' has {len(ps)} {kind} images "
                                         f"({', '.join(q.name for q in ps)}); one is expected"))
    boards = {pose: ps[0] for (pose, kind), ps in found.items() if kind == "board"}
    lasers = {pose: ps[0] for (pose, kind), ps in found.items() if kind == "laser"}
    for pose in sorted(set(boards) - set(lasers)):
        problems.append(Problem(rel, f"pose '{pose}' has {boards[pose].name} but no "
                                     f"{pose}_laser{boards[pose].suffix}"))
    poses = sorted(lasers)
    if len(poses) < MIN_LASER_POSES:
        problems.append(Problem(rel, f"has {len(poses)} pose(s) with a laser image; the laser "
                                     f"plane needs at least {MIN_LASER_POSES}"))
    return [LaserView(laser, p, boards.get(p), lasers[p]) for p in poses]


def _handeye(root: Path, inside: _Inside, problems: list[Problem]) -> tuple[list[Path], np.ndarray]:
    d = root / "calibration" / "handeye"
    none = np.zeros((0, 4, 4))
    entries = _folder(root, inside, d, problems)
    if entries is None:
        return [], none
    images = [p for p in entries if _is_image(p) and _usable(root, inside, p, problems)]
    by_name = {p.name: p for p in images}
    rel = "calibration/handeye/poses.csv"
    table = d / "poses.csv"
    if not table.exists() and not table.is_symlink():
        if images:
            problems.append(Problem(rel, "missing: the arm pose of every hand-eye image is needed"))
        return [], none
    if not _usable(root, inside, table, problems):
        return [], none
    rows = _read_table(table, rel, POSE_COLUMNS, problems)
    poses: dict[str, np.ndarray] = {}
    listed: set[str] = set()
    for lineno, row in rows:
        name = row["image"]
        why = _name_problem(name, file_only=True)
        if why is not None:
            problems.append(Problem(rel, f"image {name!r} {why}", lineno))
            continue
        if name in listed:
            problems.append(Problem(rel, f"image '{name}' is listed twice", lineno))
            continue
        listed.add(name)
        if name not in by_name:
            if (d / name).exists() or (d / name).is_symlink():
                if inside.why_not(d / name, parent_checked=True) is not None:
                    problems.append(Problem(rel, f"image '{name}' "
                                            f"{inside.why_not(d / name, parent_checked=True)}", lineno))
                else:
                    problems.append(Problem(rel, f"image '{name}' is not an image file "
                                            f"({', '.join(IMAGE_EXTENSIONS)})", lineno))
            else:
                problems.append(Problem(rel, f"image '{name}' has no file "
                                        f"calibration/handeye/{name}", lineno))
            continue
        pose = _pose(row, lineno, rel, problems)
        if pose is not None:
            poses[name] = pose
    for p in images:
        if p.name not in listed:
            problems.append(Problem(_rel(root, p), "has no row in calibration/handeye/poses.csv"))
    if len(rows) != len(images) and (rows or images):
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


def _scan(root: Path, inside: _Inside, name: str, spec: ScanSpec, lasers: tuple[str, ...],
          problems: list[Problem]) -> Scan | None:
    d = root / "scans" / name
    rel = f"scans/{name}/frames.csv"
    n_before = len(problems)
    if _folder(root, inside, d, problems) is None:
        if len(problems) == n_before:
            problems.append(Problem("rig.yaml", f"scan '{name}' has no folder scans/{name}"))
        return None
    table_path = d / "frames.csv"
    if not table_path.exists() and not table_path.is_symlink():
        problems.append(Problem(rel, "missing: every scan needs its frames.csv"))
        return None
    if not _usable(root, inside, table_path, problems):
        return None
    entries = _folder(root, inside, d / "frames", problems) or []
    files = [p for p in entries if _is_image(p) and _usable(root, inside, p, problems)]
    exts = sorted({p.suffix for p in files})
    if len(exts) > 1:
        problems.append(Problem(f"scans/{name}/frames", f"frames have several extensions "
                                f"({', '.join(exts)}); a scan's frames are all of one format"))
    ext = Counter(p.suffix for p in files).most_common(1)[0][0] if files else ".png"
    table, listed, has_rows = _frames_table(table_path, rel, problems, d / "frames", lasers, ext)
    for p in files:
        m = re.fullmatch(r"(\d{6,})\.[^.]+", p.name)
        if not m:
            problems.append(Problem(_rel(root, p), f"name must be the frame number in 6 digits, "
                                                   f"e.g. 000123{p.suffix}"))
        elif has_rows and int(m.group(1)) not in listed:  # an unreadable table lists no frame
            problems.append(Problem(_rel(root, p), f"has no row in {rel}"))
    if not has_rows and len(problems) == n_before:
        problems.append(Problem(rel, "has no frames"))
    if len(problems) > n_before:
        return None
    return Scan(name, d, spec, table.frames, table.time_s, table.lasers, table.T_base_tool, ext)


def open_capture(root: str | Path) -> Capture:
    """Read a capture folder; raise :class:`CaptureError` listing every problem found.

    Only names, tables and ``rig.yaml`` are read here; :func:`check_capture` also inspects
    every image. Absent or empty parts are not problems (:func:`allowed_stages` says what the
    capture allows); broken ones, and files that lead outside the capture, are.
    """
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(root, [Problem(str(root), "is not a folder")])
    if not any(root.iterdir()):
        raise CaptureError(root, [Problem(str(root), "is empty; expected rig.yaml, calibration/ "
                                                     "and scans/ (DESIGN.md §2)")])
    rig = read_rig(root / "rig.yaml")
    inside = _Inside(root)
    problems: list[Problem] = []
    truth = root / "truth.json"
    if truth.is_symlink() and inside.why_not(truth) is not None:
        problems.append(Problem("truth.json", inside.why_not(truth)))
    elif truth.is_file():
        _truth_files(root, inside, problems)
    cal = root / "calibration"
    cal_entries = _folder(root, inside, cal, problems) or []
    camera_images = _images(root, inside, cal / "camera", problems)
    for p in cal_entries:
        m = re.fullmatch(r"laser_(.*)", p.name)
        if m and m.group(1) not in rig.lasers:
            if m.group(1) in LASERS:
                problems.append(Problem(_rel(root, p), f"rig.yaml lasers: [{', '.join(rig.lasers)}] "
                                        f"but calibration/laser_{m.group(1)} exists"))
            else:
                problems.append(Problem(_rel(root, p), f"unknown laser '{m.group(1)}'; lasers are "
                                        f"named {' or '.join(LASERS)} (calibration/laser_A, ...)"))
    laser_views = {laser: _laser_views(root, inside, laser, problems) for laser in rig.lasers}
    he_images, he_T = _handeye(root, inside, problems)
    scans: dict[str, Scan] = {}
    scan_dir = root / "scans"
    entries = _folder(root, inside, scan_dir, problems)
    folders = sorted(p.name for p in entries if p.is_dir()) if entries is not None else []
    for name in folders:
        if name not in rig.scans:
            problems.append(Problem(f"scans/{name}", f"is not described under 'scans:' in rig.yaml "
                                                     f"(known: {sorted(rig.scans)})"))
    if entries is not None:  # no scans/ folder: a capture without scans
        for name, spec in rig.scans.items():
            scan = _scan(root, inside, name, spec, rig.lasers, problems)
            if scan is not None:
                scans[name] = scan
    if problems:
        raise CaptureError(root, problems)
    return Capture(root, rig, camera_images, laser_views, he_images, he_T, scans)


def allowed_stages(capture: Capture | str | Path) -> dict[str, str | None]:
    """For each of :data:`STAGES`, None if what the capture holds allows it, else why not."""
    cap = capture if isinstance(capture, Capture) else open_capture(capture)
    why: dict[str, str | None] = {}
    # the camera may also calibrate on the lasers-off board views of the other sets
    other = (sum(v.board_image is not None for vs in cap.laser_views.values() for v in vs)
             + len(cap.handeye_images))
    n_board = len(cap.camera_images) + other
    if n_board == 0:
        why["calibrate_camera"] = ("no calibration/camera views (nor lasers-off board views in "
                                   "calibration/laser_*/ or calibration/handeye/ to use instead)")
    elif n_board < MIN_CAMERA_VIEWS:
        why["calibrate_camera"] = (f"{n_board} board view(s) in all; the camera needs at least "
                                   f"{MIN_CAMERA_VIEWS}")
    else:
        why["calibrate_camera"] = None
    needs_camera = "needs calibrate_camera" if why["calibrate_camera"] else None
    lasers = [f"no calibration/laser_{x} views" for x in cap.rig.lasers if not cap.laser_views.get(x)]
    why["calibrate_lasers"] = "; ".join(lasers + [needs_camera] * bool(needs_camera)) or None
    n_he = len(cap.handeye_images)
    handeye = []
    if n_he == 0:
        handeye.append("no calibration/handeye views with arm poses")
    elif n_he < MIN_HANDEYE_POSES:
        handeye.append(f"calibration/handeye has {n_he} view(s) with arm poses; the hand-eye "
                       f"calibration needs at least {MIN_HANDEYE_POSES}")
    why["calibrate_handeye"] = "; ".join(handeye + [needs_camera] * bool(needs_camera)) or None
    if not cap.rig.scans:
        why["scans"] = "rig.yaml describes no scans"
    elif not cap.scans:
        why["scans"] = "no scans/ folder"
    else:
        missing = [f"{k} ({why[k]})" for k in STAGES[:3] if why[k]]
        why["scans"] = "needs " + "; ".join(missing) if missing else None
    return why


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
    formats: Counter[str] = Counter()

    def check(p: Path, size: tuple[int, int], what: str) -> None:
        rel = _rel(cap.root, p)
        try:
            info = image_info(p)
        except ImageError as exc:
            problems.append(Problem(rel, str(exc).split(": ", 1)[-1]))
            return
        formats[info.format] += 1
        if (info.width, info.height) != size:
            problems.append(Problem(rel, f"image is {info.width}x{info.height} px, "
                                    f"expected the {what} {size[0]}x{size[1]} px"))
        if info.bit_depth not in (8, 16):
            problems.append(Problem(rel, f"image has {info.bit_depth}-bit samples, expected 8 or 16"))
        elif info.bit_depth != rig.sensor.bit_depth:
            problems.append(Problem(rel, f"{info.format} image has {info.bit_depth}-bit samples, "
                                    f"expected {rig.sensor.bit_depth} (rig.yaml sensor.bit_depth)"))

    if images:
        for p in cap.camera_images + cap.handeye_images:
            check(p, sensor, "sensor")
        for views in cap.laser_views.values():
            for v in views:
                if v.board_image is not None:
                    check(v.board_image, sensor, "sensor")
                check(v.laser_image, sensor, "sensor")
        for scan in cap.scans.values():
            for p in scan.frame_paths:
                check(p, window, "scan window")
    if problems:
        raise CaptureError(cap.root, problems)
    stages = allowed_stages(cap)
    summary: dict[str, Any] = {
        "capture": cap.name,
        "sensor": {"width": rig.sensor.width, "height": rig.sensor.height,
                   "bit_depth": rig.sensor.bit_depth, "data_bits": rig.sensor.data_bits,
                   "channel": rig.sensor.channel},
        "lasers": list(rig.lasers),
        "scan_window": {"x": rig.scan_window.x, "y": rig.scan_window.y,
                        "width": rig.scan_window.width, "height": rig.scan_window.height},
        "frame_rate": rig.frame_rate,
        "board": rig.board.to_dict(),
        "views": {
            "camera": len(cap.camera_images),
            **{f"laser_{x}": len(cap.laser_views[x]) for x in rig.lasers},
            "handeye": len(cap.handeye_images),
        },
        "laser_views_without_board": {
            f"laser_{x}": sum(v.board_image is None for v in cap.laser_views[x]) for x in rig.lasers
        },
        "image_formats": dict(sorted(formats.items())),
        "stages": {k: {"allowed": w is None, "why": w} for k, w in stages.items()},
        "scans": {},
        "simulated": cap.truth_path is not None,
        "images_checked": images,
    }
    for name, scan in cap.scans.items():
        pat = laser_pattern(scan.lasers)
        summary["scans"][name] = {
            "artefact": scan.spec.artefact,
            "nominal": scan.spec.nominal,
            "mesh": scan.spec.mesh,
            "nominal_pose": None if scan.spec.nominal_pose is None else list(scan.spec.nominal_pose),
            "frames": len(scan.frames),
            "frame_format": scan.frame_ext.lstrip(".").lower(),
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
    sen = s["sensor"]
    depth = f"{sen['bit_depth']}-bit" + (f" ({sen['data_bits']} data bits)" if sen.get("data_bits") else "")
    lines = [
        f"capture {s['capture']}: OK" + (" (simulated, has truth.json)" if s["simulated"] else ""),
        f"  sensor       {sen['width']}x{sen['height']} px, {depth}, {s['frame_rate']:g} frames/s"
        + (f", {sen['channel']} channel" if sen.get("channel") else ""),
        f"  lasers       {', '.join(s['lasers'])}",
        f"  scan window  {w['width']}x{w['height']} px at ({w['x']}, {w['y']})",
        f"  board        {s['board']['pattern']} {s['board']['cols']}x{s['board']['rows']}, "
        f"spacing {s['board']['spacing']} mm",
        "  views        " + ", ".join(f"{k} {v}" for k, v in s["views"].items()),
    ]
    no_board = {k: n for k, n in s.get("laser_views_without_board", {}).items() if n}
    if no_board:
        lines.append("               laser always on (no lasers-off twin): "
                     + ", ".join(f"{k} {n} pose(s)" for k, n in no_board.items()))
    if s.get("image_formats"):
        lines.append("  images       " + ", ".join(f"{k} {n}" for k, n in s["image_formats"].items()))
    for name, sc in s["scans"].items():
        nominal = ", ".join(f"{k} {v:g} mm" for k, v in sc["nominal"].items())
        if sc.get("mesh"):
            nominal = ", ".join(filter(None, [nominal, f"mesh {sc['mesh']}"]))
        if sc.get("nominal_pose"):
            nominal += ", placed by nominal_pose"
        lines.append(
            f"  scan {name:<8}{sc['artefact']}{' (' + nominal + ')' if nominal else ''}: "
            f"{sc['frames']} frames, {sc['duration_s']:.2f} s, pattern "
            f"{'/'.join(sc['pattern'])}"
            + (f", {sc['pattern_breaks']} frame(s) break it" if sc["pattern_breaks"] else "")
        )
    stages = s.get("stages", {})
    allowed = [k for k, v in stages.items() if v["allowed"]]
    lines.append("  stages       allows " + (", ".join(allowed) if allowed else "none"))
    for k, v in stages.items():
        if not v["allowed"]:
            lines.append(f"               not {k}: {v['why']}")
    return "\n".join(lines)

"""Read and validate a capture's ``rig.yaml`` (``shared/DESIGN.md`` §2): the dataclasses it
becomes (:class:`Sensor`, :class:`ScanWindow`, :class:`ScanSpec` for what each scan measures,
:class:`Rig`) and :func:`read_rig`, which collects every problem of the file (with its line)
instead of stopping at the first. Split from :mod:`crossline.io.capture` (issue 21.3), which
re-exports these names.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import yaml

from crossline.board import PATTERNS, Board
from crossline.geometry import transform_from_pose
from crossline.io.contract import (
    ARTEFACTS,
    DATA_BITS,
    FORMAT,
    LASERS,
    MESH_EXTENSIONS,
    CaptureError,
    Problem,
    _Inside,
    _name_problem,
    _short,
)
from crossline.io.images import CHANNELS

__all__ = ["Rig", "ScanSpec", "ScanWindow", "Sensor", "read_rig"]

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

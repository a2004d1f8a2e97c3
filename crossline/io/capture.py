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

Its parts live in modules beside this one (issue 21.3): ``contract`` (the constants,
:class:`Problem`, :class:`CaptureError` and the checks that every file stays inside the
capture), ``rig`` (``rig.yaml``: :func:`read_rig` and its dataclasses) and ``tables`` (the CSV
tables: :func:`read_frames_table`). This one keeps the capture itself (listing its folders,
:func:`open_capture`, :func:`allowed_stages`, :func:`check_capture`) and re-exports the names
its importers use.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from crossline.geometry import transform_from_pose
from crossline.io.contract import (
    ARTEFACTS,
    FRAME_COLUMNS,
    LASER_STATES,
    LASERS,
    MESH_EXTENSIONS,
    MIN_CAMERA_VIEWS,
    MIN_HANDEYE_POSES,
    MIN_LASER_POSES,
    POSE_COLUMNS,
    STAGES,
    TRUTH_FILE_KEYS,
    CaptureError,
    Problem,
    _Inside,
    _name_problem,
    _truth_files,
    truth_file,
)
from crossline.io.images import IMAGE_EXTENSIONS, ImageError, image_info
from crossline.io.rig import Rig, ScanSpec, ScanWindow, Sensor, read_rig
from crossline.io.tables import FramesTable, _frames_table, _pose, _read_table, read_frames_table

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

"""The capture contract's shared ground (``shared/DESIGN.md`` §2): its constants (format,
laser names and states, table columns, artefact kinds, the fewest views each calibration
needs), :class:`Problem` and :class:`CaptureError`, and the rule that every file a capture names
or holds lies inside its folder once symbolic links are followed (file names checked, paths
resolved, and the files a simulated capture's truth.json names, :func:`truth_file`). Split from
:mod:`crossline.io.capture` (issue 21.3); the rig.yaml, table and capture readers build on it.
"""

from __future__ import annotations

import json
import reprlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

from crossline.errors import CrosslineError

__all__ = [
    "ARTEFACTS", "FRAME_COLUMNS", "LASERS", "LASER_STATES", "MESH_EXTENSIONS", "POSE_COLUMNS",
    "STAGES", "TRUTH_FILE_KEYS", "CaptureError", "Problem", "truth_file",
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
    "ball_bar": ("diameter", "length"),  # two balls, nominal centre-to-centre distance
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


# ----------------------------------------------------------------------------- inside the capture


_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = 60
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict = 3, 6, 6


def _short(value: Any) -> str:
    """repr of a value read from rig.yaml, bounded (aliases can make a small file a huge tree)."""
    return _REPR.repr(value)


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

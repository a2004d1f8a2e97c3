"""Broken copies of a good capture, one fault each (issue 6): shared by workflow tests."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from crossline.imageio import read_image, write_png


def _rewrite(path: Path, data: bytes | str) -> None:
    """Replace a (possibly hard-linked) file without touching the original it links to."""
    path.unlink()
    if isinstance(data, str):
        path.write_text(data)
    else:
        path.write_bytes(data)


def _blank_png(path: Path, level: int = 0) -> None:
    img = read_image(path)
    path.unlink()
    write_png(path, np.full_like(img, level))


def _edit_csv(path: Path, line: int, column: str, value: str) -> None:
    rows = path.read_text().splitlines()
    header = rows[0].split(",")
    cells = rows[line - 1].split(",")
    cells[header.index(column)] = value
    rows[line - 1] = ",".join(cells)
    _rewrite(path, "\n".join(rows) + "\n")


def break_capture(good: Path, dest: Path, fault: str) -> Path:
    """A copy of ``good`` at ``dest`` (hard links, files rewritten only where broken)."""
    if fault == "empty":
        dest.mkdir(parents=True)
        return dest
    shutil.copytree(good, dest, copy_function=os.link)
    if fault == "corrupt_png":
        png = sorted((dest / "scans/plate/frames").glob("*.png"))[5]
        _rewrite(png, png.read_bytes()[: png.stat().st_size // 2])
    elif fault == "nan_pose":
        _edit_csv(dest / "calibration/handeye/poses.csv", 4, "y", "nan")
    elif fault == "misspelt_rig_key":
        rig = dest / "rig.yaml"
        _rewrite(rig, rig.read_text().replace("frame_rate:", "frame_rat:"))
    elif fault == "few_views":
        # the camera calibrates on every board image: all but two camera views go blank
        cal = dest / "calibration"
        boards = sorted((cal / "camera").glob("*.png"))[2:] + sorted(cal.glob("laser_*/*_board.png"))
        for png in boards + sorted((cal / "handeye").glob("*.png")):
            _blank_png(png, 128)
    elif fault == "scan_faults":
        # gauge: every A frame switched to B (AB frames have no A reference);
        # plate: lasers never reach the part (frames black)
        frames = dest / "scans/gauge/frames.csv"
        rows = frames.read_text().splitlines()
        _rewrite(frames, "\n".join(r.replace(",A,", ",B,") for r in rows) + "\n")
        for png in (dest / "scans/plate/frames").glob("*.png"):
            _blank_png(png, 0)
    else:
        raise ValueError(f"unknown fault {fault!r}")
    return dest

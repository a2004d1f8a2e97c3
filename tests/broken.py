"""Broken copies of a good capture, one fault each (issue 6): shared by workflow tests."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from crossline.camera import Camera
from crossline.geometry import invert_transform, make_transform
from crossline.io.atomic import write_json
from crossline.io.images import read_image, write_png
from crossline.sim import arm as sim_arm
from crossline.sim import capture as sim_capture
from crossline.sim.presets import PRESETS
from crossline.sim.views import board_outline_points


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


def _degenerate_handeye(dest: Path, tilt_deg: float = 15.0, roll_deg: float = 15.0) -> None:
    """Re-render the hand-eye views so that every arm motion turns about one axis.

    The camera stays at one point above the board, tilted by ``tilt_deg`` from the board's
    normal and aimed at its centre, and only rolls about its optical axis (from -roll_deg to
    +roll_deg, within the +-40 deg that keeps a symmetric grid's labelling resolvable), as
    near as the whole board stays in every view: each view is detected, but the rotation axes
    of all motion pairs coincide (up to the arm's noise), so X is not determined about that
    axis. Rendered with the simulator's own hand-eye job (same preset, seed, bit depth, arm
    noise and per-image random streams as the good capture), so images and poses.csv agree;
    truth.json follows.
    """
    truth = json.loads((dest / "truth.json").read_text())
    rig = PRESETS[truth["preset"]]
    seed, bits = int(truth["seed"]), int(truth["sensor"]["bit_depth"])
    he = dest / "calibration/handeye"
    n = len(list(he.glob("*.png")))
    s = rig.sensor
    cam = Camera(np.array(s.K), np.array(s.dist), (s.width, s.height))
    Tbb = rig.T_base_board
    centre = Tbb[:3, :3] @ sim_capture._board_centre(rig) + Tbb[:3, 3]
    t, a = np.radians(tilt_deg), np.radians(30.0)
    towards_cam = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
    R = [sim_arm.view_rotation(-towards_cam, Tbb[:3, 0], r)
         for r in np.radians(np.linspace(-roll_deg, roll_deg, n))]
    cal = rig.quick_calibration if truth["quick"] else rig.calibration
    outline = board_outline_points(rig.board)
    for dist in cal.handeye_distance_mm + np.arange(0.0, 90.0, 3.0):
        T_base_cam = make_transform(np.array(R), centre + towards_cam * dist)
        T_cam_board = invert_transform(T_base_cam) @ Tbb
        uv = cam.project(np.einsum("vij,nj->vni", T_cam_board[:, :3, :3], outline)
                         + T_cam_board[:, None, :3, 3])
        if np.all((uv > 20) & (uv < np.array(cam.image_size) - 21)):
            break
    else:  # pragma: no cover - every preset's board fits at some distance
        raise ValueError(f"{rig.name}: the board does not fit the frame rolled by +-{roll_deg} deg")
    T_tool_true = sim_arm.tool_from_cam(T_base_cam, rig.T_tool_cam)
    T_tool_rep, dp, dth = sim_arm.noise_calibration(T_tool_true, rig.arm, sim_capture._rng(seed, 90))
    for png in he.glob("*.png"):
        png.unlink()
    plan = sim_capture.Plan(rig, seed, bits, dest)
    threads = cv2.getNumThreads()  # the simulator's job sets OpenCV to one thread
    rows, truth_he = [], {}
    try:
        for i in range(n):
            name = f"pose_{i:02d}.png"
            job = ("handeye", i, invert_transform(T_base_cam[i]), f"calibration/handeye/{name}")
            sim_capture._run(plan, job)
            rows.append(",".join([name, *sim_capture._pose_row(T_tool_rep[i])]) + "\n")
            truth_he[name] = {"T_base_tool": T_tool_true[i], "T_cam_board": T_cam_board[i],
                              "error_position_mm": dp[i], "error_rotation_rad": dth[i]}
    finally:
        cv2.setNumThreads(threads)
    _rewrite(he / "poses.csv", "image,x,y,z,qw,qx,qy,qz\n" + "".join(rows))
    truth["calibration"]["handeye"] = truth_he
    (dest / "truth.json").unlink()
    write_json(dest / "truth.json", truth)


def break_capture(good: Path, dest: Path, fault: str) -> Path:
    """A copy of ``good`` at ``dest`` (hard links, files rewritten only where broken).

    ``outside_link`` also writes ``<dest>-outside/`` beside ``dest``; ``no_handeye``,
    ``laser_always_on`` and ``camera_only`` are partial captures, not faults."""
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
        # gauge: every frame's laser state written as off (a lost trigger log), so no centre
        # has a laser; plate: lasers never reach the part (frames black)
        frames = dest / "scans/gauge/frames.csv"
        rows = frames.read_text().splitlines()
        _rewrite(frames, "\n".join(r.replace(",AB,", ",off,").replace(",A,", ",off,")
                                   .replace(",B,", ",off,") for r in rows) + "\n")
        for png in (dest / "scans/plate/frames").glob("*.png"):
            _blank_png(png, 0)
    elif fault == "degenerate_handeye":
        _degenerate_handeye(dest)
    elif fault == "table_faults":
        # one fault per file, all found by one check: a truncated row, a missing column, an
        # unknown laser state, a non-unit quaternion, a pose row too few
        plate = dest / "scans/plate/frames.csv"
        text = plate.read_text()
        _rewrite(plate, text[: text.rstrip().rfind(",")])
        ball = dest / "scans/ball/frames.csv"
        _rewrite(ball, "\n".join(",".join(r.split(",")[:-1]) for r in ball.read_text().splitlines()) + "\n")
        _edit_csv(dest / "scans/gauge/frames.csv", 3, "lasers", "C")
        _edit_csv(dest / "scans/gauge/frames.csv", 5, "qw", "0.5")
        poses = dest / "calibration/handeye/poses.csv"
        _rewrite(poses, "\n".join(poses.read_text().splitlines()[:-1]) + "\n")
    elif fault == "nan_frame_pose":
        # a scan frame's arm pose lost (the arm's log wrote nan)
        _edit_csv(dest / "scans/plate/frames.csv", 4, "x", "nan")
    elif fault == "wrong_size":
        png = dest / "scans/part/frames/000002.png"
        small = read_image(png)[:-8]
        png.unlink()
        write_png(png, small)
    elif fault == "wrong_size_view":
        # calibration views 8 rows short: one camera view, one hand-eye view and every laser-on
        # image (a laser pose with an image of another size is skipped, so all of them)
        views = [dest / "calibration/camera/view_03.png", dest / "calibration/handeye/pose_02.png",
                 *sorted((dest / "calibration").glob("laser_*/*_laser.png"))]
        for png in views:
            small = read_image(png)[:-8]
            png.unlink()
            write_png(png, small)
    elif fault == "laser_views_blank":
        # no laser view usable: laser A never fired (its laser-on images black), laser B's
        # lasers-off views show no board (grey)
        for png in (dest / "calibration/laser_A").glob("*_laser.png"):
            _blank_png(png, 0)
        for png in (dest / "calibration/laser_B").glob("*_board.png"):
            _blank_png(png, 128)
    elif fault == "board_views_blank":
        # the board is found in no lasers-off view of the laser poses (grey images)
        for png in (dest / "calibration").glob("laser_*/*_board.png"):
            _blank_png(png, 128)
    elif fault == "rig_wrong_type":
        rig = dest / "rig.yaml"
        text = rig.read_text()
        assert "frame_rate: 80.0" in text
        _rewrite(rig, text.replace("frame_rate: 80.0", "frame_rate: fast"))
    elif fault == "outside_name":
        # issue 23.1: a hand-eye image named outside the capture
        _edit_csv(dest / "calibration/handeye/poses.csv", 3, "image", "../../../../../../tmp/evil.png")
    elif fault == "outside_link":
        # a camera view that is a symbolic link to a file outside the capture
        outside = dest.parent / f"{dest.name}-outside"
        outside.mkdir(exist_ok=True)
        view = sorted((dest / "calibration/camera").glob("*.png"))[1]
        shutil.copy(view, outside / "evil.png")
        view.unlink()
        view.symlink_to(outside / "evil.png")
    elif fault == "stray_laser":
        # rig.yaml names one laser, the capture holds the other's views and frames
        rig = dest / "rig.yaml"
        _rewrite(rig, rig.read_text() + "lasers: [A]\n")
    # partial captures (issue 18.1): not faults, check passes and says what the capture allows
    elif fault == "no_handeye":
        shutil.rmtree(dest / "calibration/handeye")
    elif fault == "laser_always_on":
        for png in (dest / "calibration").glob("laser_*/*_board.png"):
            png.unlink()
    elif fault == "camera_only":
        for d in [*(dest / "calibration").glob("laser_*"), dest / "calibration/handeye", dest / "scans"]:
            shutil.rmtree(d)
        rig = dest / "rig.yaml"
        text = rig.read_text()
        _rewrite(rig, text[: text.index("\nscans:") + 1] if "\nscans:" in text else text)
    else:
        raise ValueError(f"unknown fault {fault!r}")
    return dest

"""The virtual rig's capture folders: contract, calibration images OpenCV can use, truth, determinism."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from crossline.board import Board
from crossline.camera import Camera
from crossline.errors import CrosslineError
from crossline.geometry import invert_transform, transform_from_pose
from crossline.io.capture import check_capture, open_capture
from crossline.sim import simulate
from crossline.sim.presets import PRESETS, CalibrationSpec

TRUTH_KEYS = {"camera", "lasers", "T_tool_cam", "T_base_board", "scans"}
CENTRELINE_COLUMNS = ["frame", "laser", "u", "v", "x_cam", "y_cam", "z_cam", "visible"]


def _board(root: Path) -> Board:
    b = yaml.safe_load((root / "rig.yaml").read_text())["board"]
    return Board(b["pattern"], b["cols"], b["rows"], b["spacing"], b.get("diameter"),
                 b.get("circles", "dark"))


def _find_grid(img: np.ndarray, board: Board) -> np.ndarray | None:
    """cv2.findCirclesGrid with a blob detector sized for the board's ~30-80 px circles."""
    p = cv2.SimpleBlobDetector_Params()
    p.filterByArea, p.minArea, p.maxArea = True, 80.0, 60000.0
    p.filterByCircularity = p.filterByConvexity = p.filterByInertia = False
    p.blobColor = 0 if board.circles == "dark" else 255
    det = cv2.SimpleBlobDetector_create(p)
    kind = cv2.CALIB_CB_SYMMETRIC_GRID if board.pattern == "symmetric" else cv2.CALIB_CB_ASYMMETRIC_GRID
    for flags in (kind, kind | cv2.CALIB_CB_CLUSTERING):  # clustering copes with strong perspective
        ok, centres = cv2.findCirclesGrid(img, board.pattern_size, flags=flags, blobDetector=det)
        if ok:
            return centres.reshape(-1, 2)
    return None


def _calibration_images(root: Path) -> list[Path]:
    cal = root / "calibration"
    return (sorted((cal / "camera").glob("*.png")) + sorted((cal / "handeye").glob("*.png"))
            + sorted(cal.glob("laser_*/*_board.png")))


@pytest.mark.slow
@pytest.mark.parametrize("which", ["paper", "compact"])
def test_quick_capture_passes_the_capture_check(which, quick_capture, quick_capture_compact):
    summary = check_capture(quick_capture if which == "paper" else quick_capture_compact)
    spec = PRESETS[which].quick_calibration
    v = summary["views"]
    assert (v["camera"], v["laser_A"], v["laser_B"], v["handeye"]) == (
        spec.camera_views, spec.laser_poses, spec.laser_poses, spec.handeye_views)
    assert set(summary["scans"]) == {"gauge", "plate", "ball", "part"}
    for s in summary["scans"].values():
        assert s["frames"] == PRESETS[which].quick_frames
        assert s["pattern"] == ["A", "B", "AB"] and s["pattern_breaks"] == 0
    assert summary["simulated"]


@pytest.mark.parametrize("which", sorted(PRESETS))
def test_full_presets_render_the_views_the_method_needs(which):
    """Full captures: >= 15 camera views, >= 3 poses per laser, >= 8 hand-eye views."""
    spec = PRESETS[which].calibration
    assert spec.camera_views >= 15 and spec.laser_poses >= 3 and spec.handeye_views >= 8
    assert len(spec.laser_depths_mm) == spec.laser_poses


@pytest.mark.slow
@pytest.mark.parametrize("which", ["paper", "compact"])
def test_opencv_finds_the_grid_in_every_calibration_view(which, quick_capture, quick_capture_compact):
    root = quick_capture if which == "paper" else quick_capture_compact
    board = _board(root)
    missed = [p.name for p in _calibration_images(root)
              if _find_grid(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), board) is None]
    assert not missed


@pytest.mark.slow
def test_true_board_points_project_onto_the_rendered_circle_centroids(quick_capture):
    """Fronto-parallel views: the intensity-weighted centroid of each dark blob is within 0.2 px."""
    truth = json.loads((quick_capture / "truth.json").read_text())
    cam = Camera(np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"]),
                 tuple(truth["camera"]["image_size"]))
    board = _board(quick_capture)
    views = truth["calibration"]["camera"]
    fronto = [n for n, v in views.items()
              if np.degrees(np.arccos(np.clip(np.array(v["T_cam_board"])[2, 2], -1, 1))) < 1.0]
    assert len(fronto) >= 2
    for name in fronto:
        T = np.array(views[name]["T_cam_board"])
        P = board.object_points() @ T[:3, :3].T + T[:3, 3]
        uv = cam.project(P)
        img = cv2.imread(str(quick_capture / "calibration" / "camera" / name),
                         cv2.IMREAD_UNCHANGED).astype(np.float64)
        R = board.diameter / 2 * cam.fx / P[:, 2].mean()
        assert 25 < R < 45  # ~70 px circles
        r = int(R + 12)
        Y, X = np.mgrid[-r : r + 1, -r : r + 1]
        errs = []
        for u, v in uv:
            cu, cv_ = round(u), round(v)
            win = img[cv_ - r : cv_ + r + 1, cu - r : cu + r + 1]
            dist = np.hypot(X + cu - u, Y + cv_ - v)
            light = np.median(win[(dist > R + 5) & (dist < R + 11)])
            m = dist < R + 4
            w = (light - win)[m]
            errs.append([(w * (X[m] + cu)).sum() / w.sum() - u, (w * (Y[m] + cv_)).sum() / w.sum() - v])
        assert np.abs(np.array(errs)).max() < 0.2, name


@pytest.mark.slow
def test_board_views_are_exposed_like_a_real_capture(quick_capture):
    """The light board reads ~180-220 DN in the middle of the frame; the background is darker."""
    img = cv2.imread(str(quick_capture / "calibration" / "camera" / "view_00.png"), cv2.IMREAD_UNCHANGED)
    h, w = img.shape
    centre = img[h // 2 - 200 : h // 2 + 200, w // 2 - 200 : w // 2 + 200]
    light = np.percentile(centre, 90)
    assert 180 <= light <= 225
    assert np.percentile(img, 2) < 0.5 * light


@pytest.mark.slow
def test_truth_follows_the_contract(quick_capture):
    truth = json.loads((quick_capture / "truth.json").read_text())
    assert TRUTH_KEYS <= set(truth)
    assert set(truth["lasers"]) == {"A", "B"}
    for laser in truth["lasers"].values():
        assert abs(np.linalg.norm(laser["normal"]) - 1) < 1e-12
        # the emitter lies on its plane
        assert abs(np.dot(laser["normal"], laser["emitter_cam"]) + laser["d"]) < 1e-9
    X = np.array(truth["T_tool_cam"])
    assert np.allclose(X[:3, :3] @ X[:3, :3].T, np.eye(3), atol=1e-12)
    sc = truth["scans"]
    assert sc["gauge"]["height"] == 20.0
    assert len(sc["gauge"]["plate_plane_base"]) == 4 and len(sc["gauge"]["top_plane_base"]) == 4
    top, plate = np.array(sc["gauge"]["top_plane_base"]), np.array(sc["gauge"]["plate_plane_base"])
    assert np.allclose(top[:3], plate[:3]) and abs(plate[3] - top[3] - 20.0) < 1e-9
    assert len(sc["plate"]["plane_base"]) == 4
    assert sc["ball"]["diameter"] == 25.0 and len(sc["ball"]["center_base"]) == 3
    assert sc["part"]["mesh"] == "truth/part.ply" and (quick_capture / "truth" / "part.ply").is_file()
    cap = open_capture(quick_capture)
    for name, scan in cap.scans.items():
        cl = pd.read_parquet(quick_capture / sc[name]["centrelines"])
        assert list(cl.columns[: len(CENTRELINE_COLUMNS)]) == CENTRELINE_COLUMNS
        assert set(cl["frame"]) <= set(scan.frames.tolist())
        # every laser that is on in a frame has centreline rows, and no other laser does
        on = {(int(f), ls) for f, s in zip(scan.frames, scan.lasers, strict=True) if s != "off"
              for ls in s}
        assert set(zip(cl["frame"].astype(int), cl["laser"], strict=True)) <= on
        assert cl["visible"].sum() > 100 * len(scan.frames)
        w = cap.rig.scan_window
        assert cl["u"].between(w.x, w.x + w.width - 1).all()
        poses = pd.read_parquet(quick_capture / sc[name]["poses"])
        T_true = transform_from_pose(poses[["x", "y", "z"]].to_numpy(),
                                     poses[["qw", "qx", "qy", "qz"]].to_numpy())
        # the reported poses differ from the true ones by the arm's noise (~6 um per axis)
        dp = scan.T_base_tool[:, :3, 3] - T_true[:, :3, 3]
        assert 1e-4 < np.abs(dp).max() < 0.05
        rel = invert_transform(T_true) @ scan.T_base_tool
        ang = np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
        assert ang.max() < 2e-4


@pytest.mark.slow
def test_gauge_scan_sees_top_face_and_plate_in_the_same_frames(quick_capture):
    truth = json.loads((quick_capture / "truth.json").read_text())
    cl = pd.read_parquet(quick_capture / truth["scans"]["gauge"]["centrelines"])
    vis = cl[cl["visible"]]
    top_plane = np.array(truth["scans"]["gauge"]["top_plane_base"])
    both = vis.groupby(["frame", "laser"])["surface"].agg(
        lambda s: {"gauge_block", "surface_plate"} <= set(s))
    assert both.mean() > 0.5
    assert top_plane[2] > 0.99


def _tiny(preset: str = "paper"):
    rig = PRESETS[preset]
    cal = CalibrationSpec(camera_views=1, laser_poses=1, handeye_views=1,
                          depth_range_mm=rig.calibration.depth_range_mm,
                          laser_depths_mm=rig.calibration.laser_depths_mm,
                          handeye_distance_mm=rig.calibration.handeye_distance_mm)
    return replace(rig, quick_calibration=cal, quick_frames=3)


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_same_seed_same_bytes_whatever_the_number_of_processes(tmp_path):
    a = simulate(tmp_path / "a", preset=_tiny(), quick=True, scans=["gauge"], progress=False)
    b = simulate(tmp_path / "b", preset=_tiny(), quick=True, scans=["gauge"], progress=False,
                 threads=2)
    da, db = _digest(a), _digest(b)
    assert len(da) > 8 and da == db
    c = simulate(tmp_path / "c", preset=_tiny(), seed=1, quick=True, scans=["gauge"], progress=False)
    assert _digest(c)["scans/gauge/frames/000000.png"] != da["scans/gauge/frames/000000.png"]


def test_refuses_to_overwrite_and_leaves_nothing_half_written(tmp_path, monkeypatch):
    out = tmp_path / "cap"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(CrosslineError, match="not empty"):
        simulate(out, preset=_tiny(), quick=True, progress=False)
    assert (out / "keep.txt").read_text() == "mine"
    with pytest.raises(CrosslineError, match="laser pattern"):
        simulate(tmp_path / "x", pattern=["A", "C"], progress=False)
    with pytest.raises(CrosslineError, match=r"camera view 0: the 30x20 chessboard \(163 x 113 mm with its "
                                             r"margin\) does not fit the camera's frame at 152 mm"):
        simulate(tmp_path / "x", board=Board("chessboard", 30, 20, 5.0), quick=True, progress=False)
    assert not (tmp_path / "x").exists() and not list(tmp_path.glob("x.partial-*"))
    # a render that fails half way leaves neither the capture nor its partial folder
    import crossline.sim.capture as capmod

    def boom(*args, **kwargs):
        raise RuntimeError("power cut")

    monkeypatch.setattr(capmod, "_run", boom)
    with pytest.raises(RuntimeError, match="power cut"):
        simulate(tmp_path / "y", preset=_tiny(), quick=True, scans=["plate"], progress=False)
    assert not (tmp_path / "y").exists()
    assert not list(tmp_path.glob("y.partial-*"))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_written_pngs_read_back_identically_with_every_decoder(tmp_path, dtype):
    """crossline's PNGs (Average filter, Huffman-only zlib; the simulator's frames) are plain
    PNGs: OpenCV, the project's fast decoder and its chunk checker read them, pixel for pixel."""
    from crossline.io.images import png_info, read_image, write_png
    from crossline.scan.frames import decode_png, fast_decoder_available

    rng = np.random.default_rng(6)
    top = np.iinfo(dtype).max
    img = np.clip(rng.normal(0.3 * top, 0.05 * top, (101, 333)), 0, top).astype(dtype)
    img[40:45] = top  # a saturated stripe and a dark corner: the unfilter at its extremes
    img[:7, :9] = 0
    path = tmp_path / "f.png"
    write_png(path, img)
    data = path.read_bytes()
    assert np.array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED), img)
    for decoder in ["opencv", "auto"] + (["fast"] if fast_decoder_available() else []):
        assert np.array_equal(decode_png(data, decoder=decoder), img)
    assert np.array_equal(read_image(path, img.shape), img)
    png_info(path)  # chunks and CRCs are valid
    write_png(tmp_path / "g.png", img)
    assert (tmp_path / "g.png").read_bytes() == data  # same array, same bytes

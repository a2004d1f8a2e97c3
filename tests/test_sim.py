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
from crossline.sim.random_rig import RANDOM_PRESETS, SENSORS, random_rig, stripe_segment

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
    # the freeform's drawing: rig.yaml names part.stl, the design surface in the part's own
    # frame; carried into the base frame by T_base_nominal it lies on the truth mesh
    import open3d as o3d

    cap_rig = yaml.safe_load((quick_capture / "rig.yaml").read_text())
    assert cap_rig["scans"]["part"]["nominal"] == "part.stl"
    nominal = o3d.io.read_triangle_mesh(str(quick_capture / "part.stl"))
    Vn = np.asarray(nominal.vertices)
    assert len(nominal.triangles) > 10000 and abs(Vn[:, 2].min()) < 1e-6  # z = 0 on the table
    T = np.array(sc["part"]["T_base_nominal"])
    truth_mesh = o3d.io.read_triangle_mesh(str(quick_capture / "truth" / "part.ply"))
    c = np.asarray(truth_mesh.vertices).mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((np.asarray(truth_mesh.vertices) - c).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(truth_mesh.triangles).astype(np.uint32)))
    Vb = Vn @ T[:3, :3].T + T[:3, 3] - c
    d = scene.compute_distance(o3d.core.Tensor(Vb.astype(np.float32))).numpy()
    assert d.max() < 2e-3, d.max()
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


# ----------------------------------------------------------------------------- random rigs and options

RIG_KEYS = {"format", "sensor", "scan_window", "frame_rate", "board"}


def _camera(rig) -> Camera:
    s = rig.sensor
    return Camera(np.array(s.K), np.array(s.dist), (s.width, s.height))


def _tiny_rig(rig, frames: int = 3, laser_poses: int = 1):
    """A rig's capture in its smallest form: one view of each kind, a few frames per scan."""
    cal = replace(rig.quick_calibration, camera_views=1, laser_poses=laser_poses, handeye_views=1)
    return replace(rig, quick_calibration=cal, quick_frames=frames)


def _direction_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Direction (0-180 deg, image u right, v down) of the principal axis of points."""
    P = np.column_stack([u, v]).astype(np.float64)
    P -= P.mean(0)
    d = np.linalg.eigh(P.T @ P)[1][:, -1]
    return float(np.degrees(np.arctan2(d[1], d[0])) % 180.0)


def _angle_diff(a: float, b: float) -> float:
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


@pytest.mark.parametrize("small", [False, True])
def test_random_rigs_are_rigs_an_engineer_could_build(small):
    """Twelve draws: every quantity within its stated range, independently recomputed where
    it can be (triangulation angle, stripe direction, the stripes crossing the window)."""
    rigs = [random_rig(seed, small=small) for seed in range(12)]
    dists, kinds, patterns, boards = [], set(), set(), set()
    for seed, rig in enumerate(rigs):
        s, d = rig.sensor, rig.draw
        mp = s.width * s.height / 1e6
        assert (s.width, s.height) in {(w, h) for w, h, _ in SENSORS}
        assert 1.0 <= mp <= 12.0 and (mp <= 2.4 or not small)
        assert s.data_bits in (8, 10, 12, 16) and s.bit_depth == (8 if s.data_bits == 8 else 16)
        x, y, w, h = s.scan_window
        assert 0 <= x and x + w <= s.width and 0 <= y and y + h <= s.height and w >= 0.8 * s.width - 16
        cam = _camera(rig)
        D = d["working_distance_mm"]
        assert 70 <= D <= 400 and 40 <= d["field_mm"] <= 150
        assert 0.002 <= abs(d["corner_distortion"]) <= 0.05
        dists.append(np.sign(d["corner_distortion"]))
        for name, las in rig.lasers.items():
            n = np.asarray(las.normal)
            # the stripe through the sensor's middle region at depth D: its direction as drawn,
            # and the angle between its plane and the viewing rays there
            seg = stripe_segment(cam, las, D)
            mid = seg[np.argmin(np.linalg.norm(seg - [cam.cx, cam.cy], axis=1))]
            assert np.linalg.norm(mid - [cam.cx, cam.cy]) < 0.13 * s.height + 2
            near = seg[np.linalg.norm(seg - mid, axis=1) < 40]
            assert _angle_diff(_direction_deg(near[:, 0], near[:, 1]), d["stripe_angle_deg"][name]) < 1.0
            ray = cam.rays(mid[None])[0]
            tri = np.degrees(np.arcsin(abs(n @ ray)))
            assert 19.9 <= tri <= 45.1 and abs(tri - d["triangulation_deg"][name]) < 0.5
            # both stripes cross the scan window over the measuring range
            for z in d["window_depths_mm"]:
                seg = stripe_segment(cam, las, z, s.scan_window)
                assert np.linalg.norm(seg[-1] - seg[0]) >= 0.8 * min(w, h), (seed, name, z)
            assert 3.0 * 0.9 <= 4 * np.hypot(las.waist_mm / 2 / np.sqrt(1 - (n @ ray) ** 2) * cam.fx / D,
                                              s.psf_sigma_px) <= 12.0 * 1.1
            assert 0.2 * 0.8 <= las.peak_electrons * 0.8 / s.full_well_e <= 1.0 * 1.2
        cross = _angle_diff(*d["stripe_angle_deg"].values())
        assert 49.9 <= cross <= 90.0
        kinds.add(d["cross"])
        b = rig.board.board
        boards.add((b.pattern, b.circles if b.pattern != "chessboard" else None))
        ex, ey = b.extent()
        frame_h = rig.calibration.depth_range_mm[0] * s.height / cam.fy
        assert 0.25 <= max(ex, ey) / frame_h <= 0.9  # the board fills a sensible part of the view
        assert b.rows != b.cols or b.pattern == "asymmetric"
        patterns.add(rig.pattern)
        for spec in rig.scans:
            assert abs(spec.distance_mm - D) <= 0.5 * d["measuring_range_mm"] + 1e-9
        assert 0.005 <= rig.arm.precision_mm <= 0.06
    assert {-1.0, 1.0} <= set(dists)  # barrel and pincushion
    assert len(kinds) >= 2 and len(patterns) >= 3 and len(boards) >= 3
    # same seed, same rig; another seed, another rig
    assert repr(random_rig(3, small=small)) == repr(rigs[3])
    assert repr(rigs[4]) != repr(rigs[3])


def _rig_yaml(root: Path) -> dict:
    return yaml.safe_load((root / "rig.yaml").read_text())


def _images(root: Path, sub: str) -> list[Path]:
    return sorted(p for p in (root / sub).rglob("*") if p.suffix in (".png", ".jpg", ".tif", ".bmp"))


@pytest.mark.slow
def test_random_rig_captures_follow_the_contract_and_repeat_byte_for_byte(tmp_path):
    """Two small random rigs: rig.yaml and truth.json keys, data within the ADC's bits, the
    stripes at the drawn angles; the same seed renders the same bytes in 1 or 2 processes."""
    found_bits = set()
    for seed in (6, 7):  # 12 and 8 bits, 1.3 and 1.0 MP
        rig = _tiny_rig(random_rig(seed, small=True), laser_poses=2)  # the reader's minimum
        root = simulate(tmp_path / f"r{seed}", preset=rig, seed=seed, quick=True,
                        scans=["plate"], progress=False)
        ry = _rig_yaml(root)
        assert RIG_KEYS | {"scans"} <= set(ry) and "lasers" not in ry
        bits = rig.sensor.data_bits
        assert ry["sensor"]["bit_depth"] == rig.sensor.bit_depth
        assert ry["sensor"].get("data_bits", ry["sensor"]["bit_depth"]) == bits
        assert ("data_bits" in ry["sensor"]) == (bits not in (8, 16))
        truth = json.loads((root / "truth.json").read_text())
        assert TRUTH_KEYS <= set(truth) and truth["rig_draw"]["seed"] == seed
        assert truth["preset"] == "random-small"
        check = check_capture(root)
        assert check["views"]["camera"] == 1 and check["scans"]["plate"]["frames"] == 3
        top = 0
        for p in _images(root, "calibration") + _images(root, "scans"):
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            assert img.dtype == (np.uint8 if bits == 8 else np.uint16)
            top = max(top, int(img.max()))
        assert 2 ** (bits - 2) < top <= 2**bits - 1  # the ADC's range, not the container's
        found_bits.add(bits)
        # the stripes run at the drawn angles (the plate and the view are tilted by < 30 deg)
        cl = pd.read_parquet(root / "truth" / "plate_centrelines.parquet")
        cl = cl[cl["visible"] & (cl["surface"] == "plate")]
        for laser, want in truth["rig_draw"]["stripe_angle_deg"].items():
            c = cl[cl["laser"] == laser]
            c = c[c["frame"] == c["frame"].iloc[0]]
            assert len(c) > 100
            assert _angle_diff(_direction_deg(c["u"], c["v"]), want) < 15.0, (seed, laser)
    assert len(found_bits) == 2
    # a board view and scan frames, in one process and in two
    twice = [simulate(tmp_path / f"again{t}", preset=_tiny_rig(random_rig(7, small=True), frames=2),
                      seed=7, quick=True, scans=["plate"], parts=["camera", "scans"], progress=False,
                      threads=t) for t in (1, 2)]
    assert len(_digest(twice[0])) >= 6 and _digest(twice[0]) == _digest(twice[1])
    # through the name: the same rig as the function's
    named = simulate(tmp_path / "named", preset="random-small", seed=7, quick=True, frames=1,
                     scans=["plate"], parts=["scans"], progress=False)
    assert json.loads((named / "truth.json").read_text())["rig_draw"] == random_rig(7, small=True).draw
    assert set(RANDOM_PRESETS) == {"random", "random-small"}


@pytest.mark.slow
def test_one_laser_colour_jpeg_capture(tmp_path):
    """lasers=("A",), JPEG, a red laser on a colour sensor: rig.yaml says so, no laser B
    anywhere, every frame A, frames decode to the window's size in colour, the stripe mainly
    in red and the board in every channel."""
    rig = _tiny_rig(random_rig(4, small=True))
    root = simulate(tmp_path / "c", preset=rig, seed=4, quick=True, scans=["plate"], lasers=("A",),
                    image_format="jpeg", jpeg_quality=90, colour="red", parts=["camera", "lasers", "scans"],
                    progress=False)
    ry = _rig_yaml(root)
    assert ry["lasers"] == ["A"] and ry["sensor"]["channel"] == "red"
    assert ry["sensor"]["bit_depth"] == 8 and "data_bits" not in ry["sensor"]
    assert not (root / "calibration" / "laser_B").exists() and not (root / "calibration" / "handeye").exists()
    truth = json.loads((root / "truth.json").read_text())
    assert set(truth["lasers"]) == {"A"} and 600 <= truth["lasers"]["A"]["wavelength_nm"] <= 700
    assert truth["capture_options"]["image_format"] == "jpeg"
    frames = pd.read_csv(root / "scans" / "plate" / "frames.csv")
    assert set(frames["lasers"]) == {"A"} and len(frames) == 3
    files = sorted((root / "scans" / "plate" / "frames").iterdir())
    assert [p.name for p in files] == [f"{k:06d}.jpg" for k in range(3)]
    x, y, w, h = rig.sensor.scan_window
    for p in files:
        assert p.read_bytes()[:2] == b"\xff\xd8"  # a JPEG
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert img.shape == (h, w, 3) and img.dtype == np.uint8
    cl = pd.read_parquet(root / "truth" / "plate_centrelines.parquet")
    assert set(cl["laser"]) == {"A"}
    c = cl[cl["visible"] & (cl["frame"] == 1)]
    img = cv2.imread(str(files[1]))[:, :, ::-1].astype(np.float64)  # red, green, blue
    rows = np.clip(np.rint(c["v"].to_numpy()).astype(int) - y, 0, h - 1)
    cols = c["u"].to_numpy() - x
    lift = img[rows, cols] - np.median(img.reshape(-1, 3), axis=0)
    red, green, blue = np.median(lift, axis=0)
    # JPEG's half-resolution chroma lends a thin red line some green and blue: still mainly red
    assert red > 20 and green < 0.25 * red and blue < 0.25 * red
    view = cv2.imread(str(root / "calibration" / "camera" / "view_00.jpg"))
    contrast = np.percentile(view, 99, axis=(0, 1)) - np.percentile(view, 1, axis=(0, 1))
    assert contrast.min() > 0.6 * contrast.max() and contrast.min() > 15  # the board in every channel
    lp = sorted(p.name for p in (root / "calibration" / "laser_A").iterdir())
    assert lp == ["pose_00_board.jpg", "pose_00_laser.jpg"]


@pytest.mark.slow
def test_laser_always_on_calibration_only_tiff_of_12_bit_data(tmp_path):
    """laser_always_on, calibration_only, TIFF with 12-bit data in 16-bit samples."""
    rig = _tiny_rig(random_rig(8, small=True))
    root = simulate(tmp_path / "t", preset=rig, seed=8, quick=True, laser_always_on=True,
                    calibration_only=True, image_format="tiff", data_bits=12, progress=False)
    ry = _rig_yaml(root)
    view = cv2.imread(str(root / "calibration" / "camera" / "view_00.tif"), cv2.IMREAD_UNCHANGED)
    assert "scans" not in ry and not (root / "scans").exists()
    assert ry["sensor"]["bit_depth"] == 16 and ry["sensor"]["data_bits"] == 12
    for laser in "AB":
        names = sorted(p.name for p in (root / "calibration" / f"laser_{laser}").iterdir())
        assert names == ["pose_00_laser.tif"]
        img = cv2.imread(str(root / "calibration" / f"laser_{laser}" / names[0]), cv2.IMREAD_UNCHANGED)
        assert img.dtype == np.uint16 and img.max() <= 4095
        # one image holds the board in room light (half the camera views' light) and the stripe
        black = rig.sensor.black_dn(12)
        light = (np.percentile(img, 99) - black) / (np.percentile(view, 99) - black)
        assert 0.3 < light < 0.8 and img.max() > 1.5 * np.percentile(img, 99)
    assert (root / "calibration" / "camera" / "view_00.tif").is_file()
    poses = (root / "calibration" / "handeye" / "poses.csv").read_text().splitlines()
    assert poses[1].startswith("pose_00.tif,")
    truth = json.loads((root / "truth.json").read_text())
    assert truth["scans"] == {} and truth["sensor"]["data_bits"] == 12
    assert truth["capture_options"]["laser_always_on"] is True


def test_arm_noise_scale_multiplies_the_reported_pose_errors(tmp_path):
    """The same draws, K times larger: reported-minus-true poses of a scan and the model's sigma."""
    errs = {}
    for k in (1.0, 10.0):
        root = simulate(tmp_path / f"k{k:g}", preset=_tiny_rig(random_rig(7, small=True), frames=4),
                        seed=7, quick=True,
                        scans=["gauge"], parts=["scans"], image_format="bmp", arm_noise_scale=k,
                        progress=False)
        assert sorted(p.name for p in root.iterdir()) == ["rig.yaml", "scans", "truth", "truth.json"]
        assert next((root / "scans" / "gauge" / "frames").iterdir()).suffix == ".bmp"
        truth = json.loads((root / "truth.json").read_text())
        errs[k] = (pd.read_parquet(root / "truth" / "gauge_poses.parquet")[["err_x", "err_y", "err_rz"]]
                   .to_numpy(), truth["arm_noise"]["sigma_axis_mm"])
    assert np.allclose(errs[10.0][0], 10.0 * errs[1.0][0], rtol=1e-9, atol=0)
    assert errs[10.0][1] == pytest.approx(10.0 * errs[1.0][1])
    assert np.abs(errs[1.0][0]).max() > 0


def test_options_are_refused_with_what_was_expected(tmp_path):
    with pytest.raises(CrosslineError, match=r"lasers \['B'\]"):
        simulate(tmp_path / "x", lasers=("B",), progress=False)
    with pytest.raises(CrosslineError, match="laser pattern"):
        simulate(tmp_path / "x", lasers=("A",), pattern=["A", "AB"], progress=False)
    with pytest.raises(CrosslineError, match="8-bit data only"):
        simulate(tmp_path / "x", image_format="jpeg", bit_depth=16, progress=False)
    with pytest.raises(CrosslineError, match="colour 'purple'"):
        simulate(tmp_path / "x", colour="purple", progress=False)
    with pytest.raises(CrosslineError, match="parts"):
        simulate(tmp_path / "x", parts=["camera", "arm"], progress=False)
    with pytest.raises(CrosslineError, match="data bits"):
        simulate(tmp_path / "x", bit_depth=8, data_bits=12, progress=False)
    with pytest.raises(CrosslineError, match="unknown preset"):
        simulate(tmp_path / "x", preset="randm", progress=False)
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_true_stripe_profiles_match_the_images(tmp_path):
    """The true centre lines' profile columns (peak_e, sigma_px, background_e) describe the
    stripe the images hold: a Gaussian fitted to each single-laser frame's column profile (in
    electrons) has, at the median, the truth's peak, sigma (the PSF added) and background
    within 10 % (speckle and noise scatter single profiles by more)."""
    from scipy.optimize import curve_fit

    rig = _tiny_rig(random_rig(0, small=True), frames=6)
    root = simulate(tmp_path / "r", preset=rig, seed=0, quick=True, scans=["plate"],
                    parts=["scans"], progress=False)
    sensor = json.loads((root / "truth.json").read_text())["sensor"]
    x0, y0, _, h = sensor["scan_window"]
    gain, black, psf = sensor["gain_e_per_dn"], sensor["black_level_dn"], sensor["psf_sigma_px"]
    frames = pd.read_csv(root / "scans" / "plate" / "frames.csv")
    cl = pd.read_parquet(root / "truth" / "plate_centrelines.parquet")
    cl = cl[cl["visible"] & (cl["surface"] == "plate")]
    ratios = []
    for _, f in frames[frames["lasers"].isin(["A", "B"])].iterrows():
        img = cv2.imread(str(root / "scans" / "plate" / "frames" / f"{int(f['frame']):06d}.png"),
                         cv2.IMREAD_UNCHANGED).astype(np.float64)
        e = (img - black) * gain
        c = cl[(cl["frame"] == f["frame"]) & (cl["laser"] == f["lasers"])]
        for _, r in c.iloc[::5].iterrows():
            st = float(np.hypot(r["sigma_px"], psf))
            half = int(6 * st) + 3
            k = int(np.rint(r["v"] - y0))
            if k - half < 0 or k + half >= h:
                continue
            y = np.arange(k - half, k + half + 1, dtype=np.float64)
            p = e[k - half : k + half + 1, int(r["u"]) - x0]
            fit, _ = curve_fit(lambda y, a, m, s, b: b + a * np.exp(-0.5 * ((y - m) / s) ** 2), y, p,
                               p0=[p.max(), r["v"] - y0, st, r["background_e"]])
            ratios.append((fit[0] / (r["peak_e"] * r["sigma_px"] / st),
                           abs(fit[2]) / np.sqrt(st * st + 1 / 12), fit[3] / r["background_e"]))
    assert len(ratios) > 60
    peak, sigma, background = np.median(ratios, axis=0)
    assert peak == pytest.approx(1.0, abs=0.1) and sigma == pytest.approx(1.0, abs=0.1)
    assert background == pytest.approx(1.0, abs=0.1)

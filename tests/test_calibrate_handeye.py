"""Hand-eye calibration: conventions, Chou & Kamel, OpenCV's methods, the refinement, errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets
from crossline.calibrate.handeye import (
    OPENCV_METHODS,
    HandEye,
    check_motion,
    chou_kamel,
    motion_pairs,
    opencv_handeye,
    point_uncertainty,
    resolve_labellings,
    solve_handeye,
)
from crossline.calibrate.synthetic import look_at, render_view, sample_rays, view_poses
from crossline.camera import Camera
from crossline.errors import CalibrationError
from crossline.geometry import (
    invert_transform,
    make_transform,
    matrix_to_rotvec,
    orthonormalize,
    rotation_angle,
    rotvec_to_matrix,
    transform_points,
)

PAPER = Camera(
    np.array([[5145.362, 0, 1517.375], [0, 5153.664, 1023.363], [0, 0, 1]]),
    np.array([-0.09903, 0.195427, -0.000065974, -0.0000978477, 0.41673]),
    (3072, 2048),
)
BOARD = Board("symmetric", 15, 11, 3.75, 1.875, "dark")
X_TRUE = np.array([[-0.42684, 0.66270, -0.61532, 4.1373], [-0.904314, -0.3163, 0.286604, 21.393],
                   [-0.004728, 0.678785, 0.73432, 112.962], [0.0, 0.0, 0.0, 1.0]])
X_TRUE[:3, :3] = orthonormalize(X_TRUE[:3, :3])
T_BASE_BOARD = make_transform(rotvec_to_matrix(np.radians([180.0, 0.0, 18.0])), [430.0, -150.0, 4.0])
P = BOARD.object_points()


def _rig(n: int = 10, seed: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Board poses seen by the camera, the arm poses that put it there, and exact centroids."""
    T_cam_board = view_poses(BOARD, n, 145.0, max_tilt_deg=35.0, seed=seed, roll_deg=40.0)
    T_base_tool = T_BASE_BOARD @ invert_transform(T_cam_board) @ invert_transform(X_TRUE)
    pts = np.array([
        PAPER.project(P @ T[:3, :3].T + T[:3, 3])
        + centroid_offsets(PAPER, BOARD, matrix_to_rotvec(T[:3, :3]), T[:3, 3])
        for T in T_cam_board
    ])
    return T_cam_board, T_base_tool, pts


def _volume_rms(X: np.ndarray) -> float:
    """RMS distance (mm) between points 115-185 mm ahead carried by X and by the true X."""
    g = np.stack(np.meshgrid(np.linspace(-30, 30, 5), np.linspace(-20, 20, 5), np.linspace(115, 185, 5)),
                 -1).reshape(-1, 3)
    return float(np.sqrt(np.mean(np.sum((transform_points(X, g) - transform_points(X_TRUE, g)) ** 2, 1))))


def test_motion_pair_convention() -> None:
    """A = inv(T_base_tool_j) T_base_tool_i and B = T_cam_board_j inv(T_cam_board_i) satisfy AX = XB."""
    Tc, Tb, _ = _rig(4)
    A, B = motion_pairs(Tb, Tc, [(0, 1), (2, 3), (1, 3)])
    assert np.allclose(A @ X_TRUE, X_TRUE @ B, atol=1e-9)
    # the swapped (wrong) convention does not
    assert not np.allclose(invert_transform(A) @ X_TRUE, X_TRUE @ B, atol=1e-3)


def test_chou_kamel_exact() -> None:
    """Exact motions: Chou & Kamel recovers X to numerical precision."""
    Tc, Tb, _ = _rig(8)
    pairs = [(i, j) for i in range(8) for j in range(i + 1, 8)]
    X = chou_kamel(*motion_pairs(Tb, Tc, pairs))
    assert np.allclose(X, X_TRUE, atol=1e-9)


@pytest.mark.parametrize("method", sorted(OPENCV_METHODS))
def test_opencv_methods_exact(method: str) -> None:
    """OpenCV's solvers get the same X from the same absolute poses (their convention checked)."""
    Tc, Tb, _ = _rig(8)
    assert np.allclose(opencv_handeye(Tb, Tc, method), X_TRUE, atol=1e-6)


def test_solve_exact_correspondences() -> None:
    """Exact centroids: every method and the refinement recover X; no pair is rejected."""
    _Tc, Tb, pts = _rig(10)
    he = solve_handeye(PAPER, BOARD, pts, Tb, [f"pose_{k:02d}.png" for k in range(10)])
    assert he.method == "refined"
    assert np.allclose(he.T_tool_cam, X_TRUE, atol=1e-8)
    assert _volume_rms(he.T_tool_cam) < 1e-8
    assert np.allclose(he.extra["T_base_board"], T_BASE_BOARD, atol=1e-7)
    for name in ("chou_kamel", *OPENCV_METHODS, "reprojection"):
        assert _volume_rms(np.array(he.extra["methods"][name]["T_tool_cam"])) < 1e-6, name
    assert he.extra["pairs"]["used"] == 45 and he.extra["pairs"]["rejected"] == 0
    assert he.extra["reprojection_rms_px"] < 1e-8


def test_flipped_symmetric_views_are_resolved() -> None:
    """Views labelled 180° turned (as a rolled camera's detection would be) are relabelled."""
    _Tc, Tb, pts = _rig(10)
    flipped = pts.copy()
    for k in (3, 7):
        flipped[k] = pts[k][::-1]  # the symmetric grid's other labelling
    he = solve_handeye(PAPER, BOARD, flipped, Tb, [f"pose_{k:02d}.png" for k in range(10)])
    turns = [b["labelling_turn_deg"] for b in he.extra["board_poses"]]
    assert np.allclose(np.abs(turns), [0, 0, 0, 180, 0, 0, 0, 180, 0, 0])
    assert np.allclose(he.T_tool_cam, X_TRUE, atol=1e-8)
    # the first view keeps its labelling: flipping it flips every other view instead
    flipped0 = pts.copy()
    flipped0[0] = pts[0][::-1]
    Tc0 = np.array([cv2_pose(p) for p in flipped0])
    Tr, idx = resolve_labellings(Tb, Tc0, BOARD)
    assert idx[0] == 0 and np.all(idx[1:] == 1)
    Tbb = Tb @ X_TRUE @ Tr
    assert np.allclose(Tbb, Tbb[0], atol=1e-2)  # a wrong labelling would be ~50 mm off


def cv2_pose(points: np.ndarray) -> np.ndarray:
    """T_cam_board by PnP on exact projected centres (bias removed) for a labelling test."""
    _, rvec, tvec = cv2.solvePnP(P, points, PAPER.K, PAPER.dist, flags=cv2.SOLVEPNP_IPPE)
    _ok, rvec, tvec = cv2.solvePnP(P, points, PAPER.K, PAPER.dist, rvec, tvec, True)
    return make_transform(rotvec_to_matrix(rvec.ravel()), tvec.ravel())


def test_noisy_within_the_predicted_uncertainty() -> None:
    """Image noise 0.02 px and arm noise like the paper's arm: X within 3 sigma of its estimate.

    The refinement's own covariance predicts the error; the refined X is also at least as good
    as the plain reprojection refinement, which treats the arm poses as exact.
    """
    _Tc, Tb, pts = _rig(12, seed=11)
    sig_mm = 0.02 / (2 * np.sqrt(3))
    worse = 0
    for seed in range(3):
        rng = np.random.default_rng(seed)
        noisy = pts + rng.normal(0.0, 0.02, pts.shape)
        Tn = make_transform(Tb[:, :3, :3] @ rotvec_to_matrix(rng.normal(0, 2e-5, (12, 3))),
                            Tb[:, :3, 3] + rng.normal(0, sig_mm, (12, 3)))
        he = solve_handeye(PAPER, BOARD, noisy, Tn, [str(k) for k in range(12)])
        m = he.extra["methods"]
        unc = m["refined"]["uncertainty"]
        g = np.stack(np.meshgrid(np.linspace(-30, 30, 5), np.linspace(-20, 20, 5),
                                 np.linspace(115, 185, 5)), -1).reshape(-1, 3)
        predicted = np.sqrt(np.mean(point_uncertainty(he.T_tool_cam, np.array(unc["covariance_X"]), g) ** 2))
        err = _volume_rms(he.T_tool_cam)
        assert err < 3.0 * predicted, (err, predicted)
        assert 0.001 < predicted < 0.02
        noise = m["refined"]["noise_model"]
        assert 0.5 * sig_mm < noise["arm_sigma_mm"] < 2.0 * sig_mm
        assert abs(noise["image_sigma_px"] - 0.02) < 0.002
        worse += err > _volume_rms(np.array(m["reprojection"]["T_tool_cam"]))
    assert worse == 0


def test_degenerate_motion_is_an_error() -> None:
    """All arm rotations about one axis: X is not determined; the error says so."""
    Tc0 = view_poses(BOARD, 1, 145.0, max_tilt_deg=0.0, seed=1)[0]
    axis = np.array([0.0, 0.0, 1.0])
    spins = [make_transform(rotvec_to_matrix(axis * a), np.zeros(3))
             for a in np.radians([0.0, 20.0, 40.0, -25.0, 60.0])]
    T_base_cam = [T_BASE_BOARD @ invert_transform(Tc0) @ s for s in spins]
    Tb = np.array([T @ invert_transform(X_TRUE) for T in T_base_cam])
    Tc = invert_transform(X_TRUE) @ invert_transform(Tb) @ T_BASE_BOARD
    A, _ = motion_pairs(Tb, Tc, [(i, j) for i in range(5) for j in range(i + 1, 5)])
    with pytest.raises(CalibrationError, match=r"^degenerate hand-eye motion: all 10 rotating motion "
                                               r"pairs turn about nearly the same axis"):
        check_motion(A)
    pts = np.array([PAPER.project(P @ T[:3, :3].T + T[:3, 3]) for T in Tc])
    with pytest.raises(CalibrationError, match="degenerate hand-eye motion"):
        solve_handeye(PAPER, BOARD, pts, Tb, [str(k) for k in range(5)])


def test_pure_translation_is_degenerate() -> None:
    """An arm that only translates the camera cannot give X's rotation."""
    Tb = np.array([make_transform(np.eye(3), [10.0 * k, 0.0, 0.0]) for k in range(4)])
    A, _ = motion_pairs(Tb, Tb, [(0, 1), (1, 2), (2, 3)])
    with pytest.raises(CalibrationError,
                       match=r"^degenerate hand-eye motion: only 0 of 3 motion pairs rotate"):
        check_motion(A)


def test_inconsistent_pose_pairs_are_rejected_and_counted() -> None:
    """One arm pose off by 1°: its pairs' rotation angles disagree; they are rejected and
    counted, the view is left out of the absolute-pose solutions, and X stays exact."""
    _Tc, Tb, pts = _rig(10)
    bad = Tb.copy()
    bad[6] = bad[6] @ make_transform(rotvec_to_matrix(np.radians([1.0, 0.5, 0.0])), np.zeros(3))
    he = solve_handeye(PAPER, BOARD, pts, bad, [f"pose_{k:02d}.png" for k in range(10)])
    p = he.extra["pairs"]
    assert p["rejected"] >= 7 and p["used"] + p["rejected"] == 45
    assert all("pose_06.png" in r["pair"] for r in p["rejected_pairs"])
    assert p["rejected_views"] == [{"image": "pose_06.png", "rejected_pairs": 9, "pairs": 9}]
    assert he.extra["board_poses"][6]["used"] is False
    for name in ("chou_kamel", "tsai", "refined"):
        assert _volume_rms(np.array(he.extra["methods"][name]["T_tool_cam"])) < 1e-6, name


def test_handeye_save_load(tmp_path) -> None:
    """handeye.json round trip keeps X, the method and the extras."""
    he = HandEye(X_TRUE, "refined", {"methods": {"chou_kamel": {"T_tool_cam": X_TRUE}}, "n": 3})
    he.save(tmp_path / "handeye.json")
    back = HandEye.load(tmp_path / "handeye.json")
    assert np.array_equal(back.T_tool_cam, X_TRUE) and back.method == "refined"
    assert back.extra["n"] == 3 and np.allclose(back.extra["methods"]["chou_kamel"]["T_tool_cam"], X_TRUE)


@pytest.mark.slow
def test_rolled_camera_view_rendered_and_resolved() -> None:
    """Rendered views, one taken with the camera rolled ~180°: detection labels it turned, the
    stage relabels it, and X comes out exact (small camera, exact arm poses)."""
    from crossline.calibrate.detect import detect_board

    cam = Camera(np.array([[2000.0, 0, 480.0], [0, 2000.0, 360.0], [0, 0, 1]]), np.zeros(5), (960, 720))
    board = Board("symmetric", 7, 5, 5.0, 2.5, "dark")
    rays = sample_rays(cam, 2)
    ex, ey = board.extent()
    c = np.array([ex / 2, ey / 2, 0.0])
    views = [(15, 0.0, 0.0), (20, 1.5, 10.0), (25, 3.0, -15.0), (15, 4.5, 178.0), (22, 2.2, 30.0)]
    Tc, imgs = [], []
    for tilt, az, roll in views:
        t = np.radians(tilt)
        eye = c + 150.0 * np.array([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), -np.cos(t)])
        spin = make_transform(rotvec_to_matrix([0, 0, np.radians(roll)]), np.zeros(3))
        T_board_cam = look_at(eye, c) @ spin
        Tc.append(invert_transform(T_board_cam))
        imgs.append(render_view(cam, board, Tc[-1], rays=rays))
    Tc = np.array(Tc)
    Tb = T_BASE_BOARD @ invert_transform(Tc) @ invert_transform(X_TRUE)
    dets = [detect_board(im, board) for im in imgs]
    assert all(d.found for d in dets)
    he = solve_handeye(cam, board, np.array([d.points for d in dets]), Tb, [str(k) for k in range(5)])
    turns = np.abs([b["labelling_turn_deg"] for b in he.extra["board_poses"]])
    assert turns[3] == 180.0 and np.all(turns[[0, 1, 2, 4]] == 0.0)
    # limited by the render (2x2 supersampling); a wrong labelling would be off by degrees
    assert rotation_angle(he.T_tool_cam[:3, :3].T @ X_TRUE[:3, :3]) < np.radians(0.05)
    assert np.linalg.norm(he.T_tool_cam[:3, 3] - X_TRUE[:3, 3]) < 0.1

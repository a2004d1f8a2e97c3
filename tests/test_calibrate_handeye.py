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
    arm_noise_estimate,
    check_motion,
    chou_kamel,
    motion_pairs,
    opencv_handeye,
    point_uncertainty,
    refine_handeye,
    resolve_labellings,
    solve_handeye,
)
from crossline.calibrate.pose import board_pose
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
                                               r"pairs turn about nearly the same axis \(largest angle "
                                               r"between rotation axes 0\.00 deg < 5 deg\), so X = "
                                               r"T_tool_cam is not determined about that axis\. "
                                               r"Re-take the hand-eye views \(calibration/handeye\) "
                                               r"rotating the scanner about at least two different axes"):
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


# ----------------------------------------------------------------------------- the ML estimate's statistics


def _ml_trials(trials: int, arm_mm: float, arm_rad: float, sigma_px: float, views: int = 10) -> dict:
    """Many noise draws on exact correspondences: the stage's chain (PnP, Chou-Kamel, the pose
    comparison's arm sigmas, plain refinement, ML refinement with re-estimated sigmas).

    Arm noise as the simulator draws it for calibration poses (independent per view: position
    in the base frame, rotation in the flange frame); Gaussian image noise; no centre bias.
    Returns per trial the refined X's chi-square against its covariance, the volume RMS of the
    refined, plain and Chou-Kamel X, the predicted volume RMS, and the sigmas.
    """
    Tc = view_poses(BOARD, views, 145.0, max_tilt_deg=35.0, seed=11, roll_deg=40.0)
    Tb = T_BASE_BOARD @ invert_transform(Tc) @ invert_transform(X_TRUE)
    exact = np.array([PAPER.project(P @ T[:3, :3].T + T[:3, 3]) for T in Tc])
    grid = np.stack(np.meshgrid(np.linspace(-30, 30, 5), np.linspace(-20, 20, 5), np.linspace(115, 185, 5)),
                    -1).reshape(-1, 3)
    pairs = [(i, j) for i in range(views) for j in range(i + 1, views)]
    out: dict[str, list] = {k: [] for k in ("chi2", "refined", "plain", "chou_kamel", "predicted",
                                            "arm_mm", "arm_rad", "arm_mm_initial")}
    for t in range(trials):
        rng = np.random.default_rng([t, 3])
        pts = exact + rng.normal(0.0, sigma_px, exact.shape)
        Tn = make_transform(Tb[:, :3, :3] @ rotvec_to_matrix(rng.normal(0.0, arm_rad, (views, 3))),
                            Tb[:, :3, 3] + rng.normal(0.0, arm_mm, (views, 3)))
        Tcm = np.array([board_pose(PAPER, BOARD, p, bias_correction=False).T_cam_board for p in pts])
        X0 = chou_kamel(*motion_pairs(Tn, Tcm, pairs))
        s_mm, s_rad, Tbb0 = arm_noise_estimate(X0, Tn, Tcm)
        plain = refine_handeye(PAPER, BOARD, pts, Tn, X0, Tbb0, bias_correction=False)
        ml = refine_handeye(PAPER, BOARD, pts, Tn, plain.X, plain.T_base_board, sigma_px=sigma_px,
                            arm_sigma_mm=s_mm, arm_sigma_rad=s_rad, bias_correction=False,
                            estimate_sigmas=True)
        D = invert_transform(ml.X) @ X_TRUE  # X_true = X exp(e)
        e = np.r_[matrix_to_rotvec(D[:3, :3]), D[:3, 3]]
        out["chi2"].append(float(e @ np.linalg.solve(ml.covariance_X, e)))
        out["refined"].append(_volume_rms(ml.X))
        out["plain"].append(_volume_rms(plain.X))
        out["chou_kamel"].append(_volume_rms(X0))
        out["predicted"].append(float(np.sqrt(np.mean(point_uncertainty(ml.X, ml.covariance_X, grid) ** 2))))
        out["arm_mm"].append(ml.sigmas["arm_mm"])
        out["arm_rad"].append(ml.sigmas["arm_rad"])
        out["arm_mm_initial"].append(s_mm)
    return {k: np.array(v) for k, v in out.items()}


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(v**2)))


# Over K trials the mean of a chi-square with 6 degrees of freedom has sd sqrt(12 / K) (0.63 for
# K = 30): [3.75, 9.6] is > 3.5 sd from 6 either way; a covariance off by more than 1.6x in
# variance puts the expected mean outside it (at 1.6x exactly, on its edge).
CHI2_MEAN_RANGE = (6.0 / 1.6, 6.0 * 1.6)


def test_ml_error_matches_its_covariance_when_the_arm_dominates() -> None:
    """Arm noise like the paper's arm (0.0058 mm, 2e-5 rad per axis), images 0.01 px, 30 draws:
    the refined X's error is what its covariance predicts (mean chi-square of its 6 parameters
    near 6; RMS volume error within 0.75-1.3 of the predicted), and the ML fit beats the plain
    reprojection fit, which takes the arm poses as exact, by far."""
    arm_mm = 0.02 / (2 * np.sqrt(3))
    r = _ml_trials(30, arm_mm, 2e-5, 0.01)
    assert CHI2_MEAN_RANGE[0] < r["chi2"].mean() < CHI2_MEAN_RANGE[1], r["chi2"].mean()
    ratio = _rms(r["refined"]) / _rms(r["predicted"])
    assert 0.75 < ratio < 1.3, ratio
    assert _rms(r["refined"]) < 0.7 * _rms(r["plain"]), (_rms(r["refined"]), _rms(r["plain"]))
    # the re-estimated arm sigmas are the simulator's (30 draws of 10 views: a few %)
    assert abs(np.median(r["arm_mm"]) / arm_mm - 1) < 0.15
    assert abs(np.median(r["arm_rad"]) / 2e-5 - 1) < 0.15


@pytest.mark.slow
def test_ml_with_estimated_sigmas_beats_the_plain_fit_when_the_images_dominate() -> None:
    """A very precise arm (0.0003 mm, 1e-6 rad) and noisy images (0.05 px), 30 draws.

    Comparing each view's image-implied flange pose with the reported one charges the board
    poses' own error to the arm: that estimate is > 5x the true arm sigma, and an ML fit
    weighted with it would trust the arm too little. With the variance components the arm
    sigmas come out near the truth, the ML fit beats the plain one, and its covariance
    predicts its error.
    """
    r = _ml_trials(30, 0.0003, 1e-6, 0.05)
    assert np.median(r["arm_mm_initial"]) > 5 * 0.0003
    assert 0.5 < np.median(r["arm_mm"]) / 0.0003 < 2.0
    assert 0.5 < np.median(r["arm_rad"]) / 1e-6 < 2.0
    assert _rms(r["refined"]) < 0.85 * _rms(r["plain"]), (_rms(r["refined"]), _rms(r["plain"]))
    assert CHI2_MEAN_RANGE[0] < r["chi2"].mean() < CHI2_MEAN_RANGE[1], r["chi2"].mean()
    ratio = _rms(r["refined"]) / _rms(r["predicted"])
    assert 0.75 < ratio < 1.3, ratio


# ----------------------------------------------------------------------------- a noisy arm (issue 18.6)


@pytest.mark.slow
def test_ten_times_the_arm_noise_rendered(quick_capture) -> None:
    """The paper rig's rendered hand-eye views with the arm's reported-pose error 10x the
    simulator's (its own error draws scaled: 0.058 mm, 2e-4 rad per axis), true camera.

    The pair tolerance follows the data: every motion pair stays (a fixed cut would have to be
    re-tuned per arm). The chosen X's board consistency is within the margin its own
    uncertainty explains of the best OpenCV method's and within 1 % of it (the least-scatter X
    is fitted to these views' arm errors: in-sample, the refined X cannot be expected below it;
    against truth it is the better one, see benchmarks/results/handeye_noise.txt). X's error
    against truth is within 3 sigma of its covariance's prediction (the arm dominates, so the
    prediction scales with the arm noise; the covariance's calibration is tested over 30 draws
    above), and not worse than 1.25x the best of OpenCV's methods against truth.
    """
    import json

    from crossline.calibrate.camera import detect_views
    from crossline.io.capture import open_capture

    cap = open_capture(quick_capture)
    truth = json.loads((quick_capture / "truth.json").read_text())
    cam = Camera(np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"]),
                 (cap.rig.sensor.width, cap.rig.sensor.height))
    names = [p.name for p in cap.handeye_images]
    dets = detect_views(cap.handeye_images, cap.rig.board, (cap.rig.sensor.height, cap.rig.sensor.width), 2)
    assert all(d.found for d in dets)
    t = truth["calibration"]["handeye"]
    T_true = np.array([t[n]["T_base_tool"] for n in names])
    dp = np.array([t[n]["error_position_mm"] for n in names])
    dth = np.array([t[n]["error_rotation_rad"] for n in names])
    T_rep = make_transform(T_true[:, :3, :3] @ rotvec_to_matrix(10.0 * dth), T_true[:, :3, 3] + 10.0 * dp)
    he = solve_handeye(cam, cap.rig.board, np.array([d.points for d in dets]), T_rep, names)
    pairs, sel, m = he.extra["pairs"], he.extra["selection"], he.extra["methods"]
    assert pairs["used"] >= 0.9 * pairs["total"], pairs
    # the cut is k robust sigmas of the mismatches actually seen, not a fixed angle
    assert pairs["mismatch_rms_deg"] < pairs["angle_tolerance_deg"] < 10 * pairs["mismatch_rms_deg"]
    opencv = {k: m[k]["board_consistency_mm"] for k in OPENCV_METHODS}
    best = min(opencv, key=opencv.get)
    assert sel["best_opencv"] == best
    c = m[he.method]["board_consistency_mm"]
    assert c <= opencv[best] + sel["margin_mm"] and c <= 1.01 * opencv[best], (c, opencv[best], sel)
    X_t = np.array(truth["T_tool_cam"])
    g = np.stack(np.meshgrid(np.linspace(-30, 30, 5), np.linspace(-20, 20, 5), np.linspace(115, 185, 5)),
                 -1).reshape(-1, 3)

    def err(X: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((transform_points(X, g) - transform_points(X_t, g)) ** 2, 1))))

    C = np.array(m["refined"]["uncertainty"]["covariance_X"])
    predicted = float(np.sqrt(np.mean(point_uncertainty(he.T_tool_cam, C, g) ** 2)))
    e = err(he.T_tool_cam)
    assert e < 3.0 * predicted, (e, predicted)
    assert e <= 1.25 * min(err(np.array(m[k]["T_tool_cam"])) for k in OPENCV_METHODS)


def test_selection_keeps_the_refined_x_within_its_uncertainty_and_not_beyond() -> None:
    """The final choice by board consistency: a refined X off by its own 1 sigma stays (the
    least-scatter X is fitted to the views' noise, being lower says nothing); one off by 20
    sigma loses to the method whose consistency is best, and the table says by how much."""
    from crossline.calibrate.handeye import consistency_margin, consistency_mm, select_estimate

    Tc, Tb, _ = _rig(10, seed=3)
    rng = np.random.default_rng(4)
    Tn = make_transform(Tb[:, :3, :3] @ rotvec_to_matrix(rng.normal(0, 2e-4, (10, 3))),
                        Tb[:, :3, 3] + rng.normal(0, 0.05, (10, 3)))
    cov = np.diag([1e-4] * 3 + [0.02] * 3) ** 2  # rad, mm
    e = rng.standard_normal(6)
    one_sigma = X_TRUE @ make_transform(rotvec_to_matrix(e[:3] * 1e-4), e[3:] * 0.02)
    far = X_TRUE @ make_transform(rotvec_to_matrix(e[:3] * 2e-3), e[3:] * 0.4)
    for X_ref, want in ((one_sigma, "refined"), (far, "park")):
        methods = {name: {"T_tool_cam": X, "board_consistency_mm": consistency_mm(X, Tn, Tc, BOARD)}
                   for name, X in (("refined", X_ref), ("park", X_TRUE),
                                   ("tsai", X_TRUE @ make_transform(np.eye(3), [0.3, 0, 0])))}
        sel = select_estimate(methods, cov, Tn, Tc, BOARD)
        assert sel["method"] == want, sel
        assert sel["best_opencv"] == "park"
        c = methods[want]["board_consistency_mm"]
        assert sel["vs_best_opencv_mm"] == pytest.approx(c - methods["park"]["board_consistency_mm"])
    # the margin against draws of X's error about the least-scatter X (exact arm poses: X_TRUE,
    # consistency 0): its mean and its 99 % quantile
    m = consistency_margin(X_TRUE, cov, Tb, Tc, BOARD)
    draws = np.array([
        consistency_mm(X_TRUE @ make_transform(rotvec_to_matrix(d[:3]), d[3:]), Tb, Tc, BOARD) ** 2
        for d in rng.multivariate_normal(np.zeros(6), cov, 600)
    ])
    assert m["expected_mm2"] == pytest.approx(draws.mean(), rel=0.1)
    assert m["margin_mm2"] == pytest.approx(np.quantile(draws, 0.99), rel=0.25)

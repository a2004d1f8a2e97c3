"""Camera calibration (Zhang + float64 bundle adjustment + perspective-bias correction).

Synthetic correspondences: board points projected with a known camera (the paper's), either
as exact projected centres or as the imaged area centroids a real detector measures
(projection + perspective bias), with or without noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets
from crossline.calibrate.camera import _project_views, calibrate_camera, solve_views
from crossline.calibrate.detect import Detection
from crossline.calibrate.synthetic import view_poses
from crossline.camera import Camera
from crossline.errors import CalibrationError
from crossline.geometry import matrix_to_rotvec

PAPER = Camera(
    np.array([[5145.362, 0, 1517.375], [0, 5153.664, 1023.363], [0, 0, 1]]),
    np.array([-0.09903, 0.195427, -0.000065974, -0.0000978477, 0.41673]),
    (3072, 2048),
)
BOARD = Board("symmetric", 15, 11, 3.75, 1.875, "dark")
POSES = view_poses(BOARD, 15, 150.0, max_tilt_deg=40.0, seed=3)
P = BOARD.object_points()
CENTRES = np.array([PAPER.project(P @ T[:3, :3].T + T[:3, 3]) for T in POSES])
OFFSETS = np.array([centroid_offsets(PAPER, BOARD, matrix_to_rotvec(T[:3, :3]), T[:3, 3]) for T in POSES])


def _volume(cam: Camera, n: int = 15) -> np.ndarray:
    """Camera-frame points over the field of view at 115-185 mm (the paper's working volume)."""
    u, v = np.meshgrid(np.linspace(0, 3071, n), np.linspace(0, 2047, n))
    xy = cam.undistort(np.column_stack([u.ravel(), v.ravel()]))
    return np.concatenate([np.column_stack([xy * z, np.full(len(xy), z)]) for z in (115.0, 150.0, 185.0)])


def _projection_rms(est: Camera, true: Camera = PAPER) -> float:
    Q = _volume(true)
    return float(np.sqrt(np.mean(np.sum((est.project(Q) - true.project(Q)) ** 2, axis=1))))


def test_exact_centres_recover_the_camera() -> None:
    """Exact projected centres, no bias correction: truth to numerical precision."""
    fit = calibrate_camera(CENTRES, BOARD, PAPER.image_size, bias_correction=False)
    assert np.allclose(fit.camera.K, PAPER.K, atol=1e-7, rtol=0)
    assert np.allclose(fit.camera.dist, PAPER.dist, atol=1e-9, rtol=0)
    assert fit.rms_px < 1e-9
    assert np.allclose(fit.T_cam_board, POSES, atol=1e-9)


def test_bias_correction_removes_the_perspective_bias() -> None:
    """Exact area centroids: biased focal length without the correction, truth with it."""
    biased = calibrate_camera(CENTRES + OFFSETS, BOARD, PAPER.image_size, bias_correction=False)
    # the bias is nearly invisible in the residuals, but shifts the focal length
    assert biased.rms_px < 1e-3
    assert abs(biased.camera.fx - PAPER.fx) > 0.1
    fit = calibrate_camera(CENTRES + OFFSETS, BOARD, PAPER.image_size, bias_correction=True)
    assert np.allclose(fit.camera.K, PAPER.K, atol=1e-6, rtol=0)
    assert _projection_rms(fit.camera) < 1e-6
    assert np.allclose(fit.offsets, OFFSETS, atol=1e-8)
    assert len(fit.bias_history) >= 3 and fit.bias_history[-1]["change_px"] < 1e-6


def _crb_projection_rms(sigma: float) -> float:
    """Expected projection RMS error over the volume for centre noise ``sigma`` (px per axis).

    Cramér–Rao: covariance of all parameters sigma² (JᵀJ)⁻¹ from a finite-difference Jacobian
    of the projections, propagated to the working volume's projections.
    """
    V = len(POSES)
    x0 = np.concatenate([[PAPER.fx, PAPER.fy, PAPER.cx, PAPER.cy], PAPER.dist,
                         np.concatenate([np.r_[matrix_to_rotvec(T[:3, :3]), T[:3, 3]] for T in POSES])])
    f0 = _project_views(x0, P, V, PAPER.image_size).ravel()
    J = np.empty((f0.size, x0.size))
    for k in range(x0.size):
        h = 1e-6 * max(1.0, abs(x0[k]))
        dx = np.zeros_like(x0)
        dx[k] = h
        J[:, k] = (_project_views(x0 + dx, P, V, PAPER.image_size).ravel() - f0) / h
    C = np.linalg.inv(J.T @ J)[:9, :9] * sigma**2
    Q = _volume(PAPER)

    def proj(p: np.ndarray) -> np.ndarray:
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]])
        return Camera(K, p[4:9], PAPER.image_size).project(Q).ravel()

    g0 = proj(x0[:9])
    G = np.empty((g0.size, 9))
    for k in range(9):
        h = 1e-6 * max(1.0, abs(x0[k]))
        dx = np.zeros(9)
        dx[k] = h
        G[:, k] = (proj(x0[:9] + dx) - g0) / h
    return float(np.sqrt(np.trace(G @ C @ G.T) / len(Q)))


def test_noisy_centroids_within_the_noise_bound() -> None:
    """0.02 px noise on the centroids: the error is within 3x its Cramér–Rao bound."""
    sigma = 0.02
    expected = _crb_projection_rms(sigma)
    errs = []
    for seed in range(3):
        noisy = CENTRES + OFFSETS + np.random.default_rng(seed).normal(0.0, sigma, CENTRES.shape)
        fit = calibrate_camera(noisy, BOARD, PAPER.image_size)
        errs.append(_projection_rms(fit.camera))
        assert abs(fit.rms_px - sigma * np.sqrt(2)) < 0.1 * sigma * np.sqrt(2)
    assert 0.01 < expected < 0.2
    assert max(errs) < 3.0 * expected, (errs, expected)


def _detections(points: np.ndarray) -> list[Detection]:
    return [Detection(p) for p in points]


def test_view_without_board_is_skipped_with_its_reason() -> None:
    """A view whose board was not found is listed as unused, with the detector's reason."""
    names = [f"calibration/camera/view_{k:02d}.png" for k in range(len(POSES))]
    dets = _detections(CENTRES + OFFSETS)
    dets[4] = Detection(None, "board not found: no 15x11 symmetric grid of dark circles detected")
    fit, used, views = solve_views(names, dets, BOARD, PAPER.image_size)
    assert names[4] not in used and len(used) == len(POSES) - 1
    v = views[4]
    assert v["image"] == names[4] and v["used"] is False
    assert v["reason"] == "board not found: no 15x11 symmetric grid of dark circles detected"
    assert np.allclose(fit.camera.K, PAPER.K, atol=1e-5)


def test_outlier_view_is_skipped_with_its_reason() -> None:
    """A view with 0.5 px noise among views with 0.01 px is dropped as an RMS outlier."""
    rng = np.random.default_rng(7)
    pts = CENTRES + OFFSETS + rng.normal(0.0, 0.01, CENTRES.shape)
    pts[2] += rng.normal(0.0, 0.5, pts[2].shape)
    names = [f"v{k}" for k in range(len(POSES))]
    _fit, used, views = solve_views(names, _detections(pts), BOARD, PAPER.image_size, outlier_factor=3.0)
    assert "v2" not in used and len(used) == len(POSES) - 1
    assert views[2]["reason"].startswith("RMS residual ")
    assert "is an outlier (> 3 x median" in views[2]["reason"]
    assert all(v["used"] for k, v in enumerate(views) if k != 2)


def test_too_few_usable_views_names_every_view() -> None:
    """Fewer usable views than min_views: an error listing each view and why."""
    names = [f"calibration/camera/view_{k:02d}.png" for k in range(7)]
    dets = _detections((CENTRES + OFFSETS)[:7])
    for k in (1, 3, 5):
        dets[k] = Detection(None, "board not found: no 15x11 symmetric grid of dark circles detected")
    with pytest.raises(CalibrationError) as exc:
        solve_views(names, dets, BOARD, PAPER.image_size, min_views=6)
    msg = str(exc.value)
    assert msg.startswith("camera calibration needs at least 6 usable views, got 4 of 7:")
    for k in (1, 3, 5):
        assert f"  - calibration/camera/view_{k:02d}.png: board not found" in msg
    for k in (0, 2, 4, 6):
        assert f"  - calibration/camera/view_{k:02d}.png: used" in msg


def test_predicted_projection_error_matches_cramer_rao_and_the_scatter() -> None:
    """The fit's own covariance (block normal matrix at the estimate) predicts the projection
    error: as the dense Cramér–Rao bound computed here at the truth, and as the RMS of the
    actual errors over noisy repeats."""
    from crossline.calibrate.camera import PARAMETERS, grid_pixels, projection_uncertainty

    sigma = 0.05
    rng = np.random.default_rng(12)
    sensor = grid_pixels((0, 0, *PAPER.image_size), 15)
    predicted, actual, cx, cx_std = [], [], [], []
    for _ in range(40):
        fit = calibrate_camera(CENTRES + rng.normal(0.0, sigma, CENTRES.shape), BOARD, PAPER.image_size,
                               bias_correction=False)
        assert abs(fit.sigma_px - sigma) < 0.05 * sigma  # residual sigma, degrees of freedom counted
        C = fit.covariance
        assert C.shape == (9, 9) and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0)
        predicted.append(projection_uncertainty(fit.camera, C, sensor))
        actual.append(_projection_rms(fit.camera))  # over the sensor (the volume's directions)
        cx.append(fit.camera.cx)
        cx_std.append(np.sqrt(C[PARAMETERS.index("cx"), PARAMETERS.index("cx")]))
    crb = _crb_projection_rms(sigma)
    assert abs(np.median(predicted) - crb) < 0.05 * crb, (np.median(predicted), crb)
    # 40 repeats: the RMS of the actual errors within 25 % of the prediction (chi-square scatter)
    rms_actual = float(np.sqrt(np.mean(np.square(actual))))
    assert abs(rms_actual - crb) < 0.25 * crb, (rms_actual, crb)
    assert abs(np.std(cx) - np.median(cx_std)) < 0.3 * np.median(cx_std)

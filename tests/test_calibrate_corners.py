"""Sub-pixel chessboard corners: the X-junction fit against exact and rendered corners."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.special import erf

from crossline.board import Board
from crossline.calibrate.corners import refine_chessboard_corners
from crossline.calibrate.detect import board_symmetries, detect_board
from crossline.calibrate.synthetic import look_at, render_view, sample_rays
from crossline.camera import Camera
from crossline.geometry import invert_transform

CAM = Camera(np.array([[1700.0, 0, 399.2], [0, 1703.0, 300.6], [0, 0, 1]]),
             np.array([-0.1, 0.15, 2e-4, -1e-4, 0.0]), (800, 600))
BOARD = Board("chessboard", 8, 6, 5.0)


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=-1))))


def _pixel_step(x: np.ndarray, sigma: float) -> np.ndarray:
    """A step blurred by a Gaussian and integrated over a 1 px wide pixel (exact)."""

    def F(t):  # antiderivative of erf(t / (sqrt 2 sigma))
        z = t / sigma
        return t * erf(z / np.sqrt(2)) + sigma * np.sqrt(2 / np.pi) * np.exp(-0.5 * z * z)

    return F(x + 0.5) - F(x - 0.5)


@pytest.mark.parametrize("phase", [0.0, 0.13, 0.25, 0.5, 0.71])
def test_exact_on_an_ideal_pixel_integrated_corner(phase: float) -> None:
    """A 3x3-corner checker, blurred and pixel-integrated exactly, at any sub-pixel phase.

    The model's blur is a Gaussian at pixel centres, the image's a Gaussian integrated over
    the pixel: the fit must not care (point symmetry), to 1e-3 px.
    """
    board = Board("chessboard", 3, 3, 5.0)
    yy, xx = np.mgrid[0:300, 0:300].astype(np.float64)
    lines = 90.0 + 60.0 * np.arange(3) + phase
    gx = np.prod([_pixel_step(xx - c, 0.6) for c in lines], axis=0)
    gy = np.prod([_pixel_step(yy - c, 0.6) for c in lines], axis=0)
    img = 100.0 + 80.0 * gx * gy + 0.05 * (xx - 150.0)  # with a shading gradient
    true = np.array([[x, y] for y in lines for x in lines])
    start = true + np.array([0.4, -0.3])
    got, ok = refine_chessboard_corners(img, board, start)
    assert ok.all()
    assert np.abs(got - true).max() < 1e-3


@pytest.fixture(scope="module")
def rays() -> np.ndarray:
    return sample_rays(CAM, 6)


@pytest.mark.parametrize("pose", [(110.0, 30.0, 0.4, 12.0), (125.0, 45.0, 2.2, -25.0)])
def test_rendered_corners_beat_opencv(pose, rays: np.ndarray) -> None:
    """Tilted, distorted board views (6x6 supersampling, turned in the image so that no edge
    runs along the pixel grid, where the render's supersampling would quantise it): the
    corners within 0.01 px RMS of the projected true corners, at least three times closer than
    OpenCV's cornerSubPix."""
    distance, tilt, azimuth, roll = pose
    ex, ey = BOARD.extent()
    c = np.array([ex / 2, ey / 2, 0.0])
    t = np.radians(tilt)
    eye = c + distance * np.array([np.sin(t) * np.cos(azimuth), np.sin(t) * np.sin(azimuth), -np.cos(t)])
    T_board_cam = look_at(eye, c)
    r = np.radians(roll)
    T_board_cam[:3, :3] = T_board_cam[:3, :3] @ np.array([[np.cos(r), -np.sin(r), 0],
                                                        [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    T = invert_transform(T_board_cam)
    img = render_view(CAM, BOARD, T, rays=rays, blur_sigma=0.7, gradient=0.3)
    P = BOARD.object_points()
    proj = CAM.project(P @ T[:3, :3].T + T[:3, 3])
    det = detect_board(img, BOARD)
    assert det.found, det.reason
    best = min(board_symmetries(BOARD), key=lambda p: _rms(det.points[p] - proj))
    ours = _rms(det.points[best] - proj)
    crude = detect_board(img, BOARD, refine=False).points
    sub = cv2.cornerSubPix(img, crude.astype(np.float32).reshape(-1, 1, 2), (11, 11), (-1, -1),
                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)).reshape(-1, 2)
    theirs = _rms(sub[best] - proj)
    assert ours < 0.01
    assert ours < theirs / 3


def test_sixteen_bit_image_gives_the_same_corners() -> None:
    """Bit depth does not matter: the 8-bit image scaled to 16 bits gives the same corners."""
    yy, xx = np.mgrid[0:200, 0:200].astype(np.float64)
    lines = np.array([70.3, 130.3])
    gx = np.prod([_pixel_step(xx - c, 0.8) for c in lines], axis=0)
    gy = np.prod([_pixel_step(yy - c, 0.8) for c in lines], axis=0)
    img8 = np.clip(np.round(120 + 90 * gx * gy + np.random.default_rng(1).normal(0, 2, xx.shape)), 0, 255)
    board = Board("chessboard", 2, 2, 5.0)
    start = np.array([[x, y] for y in lines for x in lines]) + 0.2
    a, ok8 = refine_chessboard_corners(img8.astype(np.uint8), board, start)
    b, ok16 = refine_chessboard_corners((img8 * 257).astype(np.uint16), board, start)
    assert ok8.all() and ok16.all()
    assert np.abs(a - b).max() < 1e-6


def test_a_window_without_a_corner_is_flagged_and_left_alone() -> None:
    """Where the image holds no X-junction the corner is flagged and returned unchanged."""
    yy, xx = np.mgrid[0:200, 0:200].astype(np.float64)
    lines = np.array([70.0, 130.0])
    gx = np.prod([_pixel_step(xx - c, 0.8) for c in lines], axis=0)
    gy = np.prod([_pixel_step(yy - c, 0.8) for c in lines], axis=0)
    img = 120 + 90 * gx * gy + np.random.default_rng(2).normal(0, 2, xx.shape)
    img[100:, 100:] = 120.0  # the corner at (130, 130) painted over, without noise
    board = Board("chessboard", 2, 2, 5.0)
    start = np.array([[x, y] for y in lines for x in lines]) + 0.2
    got, ok = refine_chessboard_corners(img, board, start)
    assert ok.tolist() == [True, True, True, False]
    assert np.array_equal(got[3], start[3])
    assert np.abs(got[:3] - start[:3] + 0.2).max() < 0.01  # the others: noise of 2 DN


def test_circle_grid_is_refused() -> None:
    with pytest.raises(ValueError, match="needs a chessboard"):
        refine_chessboard_corners(np.zeros((50, 50)), Board("symmetric", 2, 2, 5.0, 2.0), np.zeros((4, 2)))


def test_full_sensor_chessboard_is_found_and_refined() -> None:
    """A 3072 x 2048 view: found on the reduced image, then refined at full size.

    This path crashed in OpenCV's cornerSubPix (an (N, 1, 2) view with a zero stride).
    """
    cam = Camera(np.array([[5145.0, 0, 1517.4], [0, 5153.7, 1023.4], [0, 0, 1]]), np.zeros(5), (3072, 2048))
    board = Board("chessboard", 12, 9, 4.0)
    ex, ey = board.extent()
    c = np.array([ex / 2, ey / 2, 0.0])
    eye = c + 150.0 * np.array([np.sin(0.4), 0.2, -np.cos(0.4)])
    T = invert_transform(look_at(eye, c, up=(0.3, -1.0, 0.0)))  # turned: no edge along the grid
    img = render_view(cam, board, T, supersample=3, blur_sigma=0.7)
    det = detect_board(img, board)
    assert det.found, det.reason
    P = board.object_points()
    proj = cam.project(P @ T[:3, :3].T + T[:3, 3])
    best = min(board_symmetries(board), key=lambda p: _rms(det.points[p] - proj))
    assert _rms(det.points[best] - proj) < 0.02  # 3x3 supersampling of the render allows no less

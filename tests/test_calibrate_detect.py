"""Board detection, sub-pixel circle centres and the perspective-bias model.

Images are rendered by crossline.calibrate.synthetic (a small independent ray tracer) for a
small camera so that each render takes about a second.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets, polygon_centroids
from crossline.calibrate.detect import (
    blob_detector,
    board_symmetries,
    canonical_labelling,
    detect_board,
    labelling_error,
)
from crossline.calibrate.synthetic import look_at, render_view, sample_rays
from crossline.camera import Camera
from crossline.geometry import invert_transform, make_transform, matrix_to_rotvec, rotvec_to_matrix

CAM = Camera(np.array([[1800.0, 0, 505.0], [0, 1805.0, 380.0], [0, 0, 1]]),
             np.array([-0.12, 0.2, 3e-4, -2e-4, 0.1]), (1024, 768))


@pytest.fixture(scope="module")
def rays() -> np.ndarray:
    """Sub-pixel rays of CAM, computed once (the slow part of rendering)."""
    return sample_rays(CAM, 3)


def _view(board: Board, distance: float, tilt_deg: float, azimuth: float, roll_deg: float = 0.0):
    ex, ey = board.extent()
    c = np.array([ex / 2, ey / 2, 0.0])
    t = np.radians(tilt_deg)
    eye = c + distance * np.array([np.sin(t) * np.cos(azimuth), np.sin(t) * np.sin(azimuth), -np.cos(t)])
    roll = make_transform(rotvec_to_matrix([0, 0, np.radians(roll_deg)]), np.zeros(3))
    T_board_cam = look_at(eye, c) @ roll
    return invert_transform(T_board_cam)


def _truth(board: Board, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    P = board.object_points()
    proj = CAM.project(P @ T[:3, :3].T + T[:3, 3])
    return proj, centroid_offsets(CAM, board, matrix_to_rotvec(T[:3, :3]), T[:3, 3])


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=-1))))


BOARDS = {
    "symmetric-dark": Board("symmetric", 9, 7, 5.0, 2.5, "dark"),
    "asymmetric-light": Board("asymmetric", 4, 9, 4.0, 3.0, "light"),
}


@pytest.mark.parametrize("name", sorted(BOARDS))
def test_circle_centres_are_area_centroids(name: str, rays: np.ndarray) -> None:
    """Refined centres match the true imaged area centroids to about 0.01 px.

    The render's own error (3x3 supersampling of hard edges, 8-bit rounding) is of that order;
    the mean error, which is what a bias would show, is far smaller.
    """
    board = BOARDS[name]
    T = _view(board, 110.0, 30.0, 0.7)
    img = render_view(CAM, board, T, rays=rays, blur_sigma=0.7, gradient=0.3, ambient=6.0)
    det = detect_board(img, board)
    assert det.found, det.reason
    proj, off = _truth(board, T)
    # the perspective bias is clearly present in this view ...
    assert _rms(off) > 0.02
    # ... and the detected centres are the biased centroids, not the projected centres
    assert _rms(det.points - (proj + off)) < 0.25 * _rms(off)
    assert _rms(det.points - (proj + off)) < 0.02
    assert np.abs(np.mean(det.points - (proj + off), axis=0)).max() < 0.003


@pytest.mark.parametrize(("distance", "tilt"), [(180.0, 20.0), (120.0, 40.0)])
def test_small_dense_light_circles_are_refined(distance: float, tilt: float, rays: np.ndarray) -> None:
    """Circles 4.5-7 px in radius with a gap of 1.3 radii (random-small rig 13's board: 1.5 mm
    spacing, 0.9 mm light circles): the first window's slack is cut to leave a background ring
    between neighbours (before, every such view was refused: "circles too close together or
    too small for a background annulus"), and the centres are the area centroids still."""
    board = Board("symmetric", 13, 8, 1.5, 0.899, "light")
    T = _view(board, distance, tilt, 0.7)
    img = render_view(CAM, board, T, rays=rays, blur_sigma=0.7, gradient=0.3, ambient=6.0)
    det = detect_board(img, board)
    assert det.found, det.reason
    proj, off = _truth(board, T)
    assert _rms(det.points - (proj + off)) < 0.03
    assert np.abs(np.mean(det.points - (proj + off), axis=0)).max() < 0.003


def test_chessboard_corners(rays: np.ndarray) -> None:
    """Chessboard corners (findChessboardCornersSB) land on the projected corners."""
    board = Board("chessboard", 8, 6, 5.0)
    T = _view(board, 120.0, 25.0, 2.0)
    img = render_view(CAM, board, T, rays=rays, blur_sigma=0.8)
    det = detect_board(img, board)
    assert det.found, det.reason
    proj, _ = _truth(board, T)
    best = min(board_symmetries(board), key=lambda p: _rms(det.points[p] - proj))
    assert _rms(det.points[best] - proj) < 0.1


def test_big_circles_need_the_geometry_sized_blob_detector(rays: np.ndarray) -> None:
    """Circles of ~100 px (7800 px²) are lost by OpenCV's default detector, found by ours."""
    board = Board("symmetric", 5, 4, 6.0, 3.0, "dark")
    T = _view(board, 55.0, 10.0, 0.3)
    img = render_view(CAM, board, T, rays=rays)
    proj, _ = _truth(board, T)
    d = np.linalg.norm(proj[1] - proj[0]) * board.diameter / board.spacing
    assert np.pi / 4 * d**2 > 5000.0  # above OpenCV's default maxArea
    ok, _ = cv2.findCirclesGrid(img, board.pattern_size, flags=cv2.CALIB_CB_SYMMETRIC_GRID)
    assert not ok
    ok, _ = cv2.findCirclesGrid(img, board.pattern_size, flags=cv2.CALIB_CB_SYMMETRIC_GRID,
                                blobDetector=blob_detector(board, CAM.image_size))
    assert ok
    assert detect_board(img, board).found


def test_board_not_found_gives_a_reason() -> None:
    """An image without the board: no points and a reason naming the pattern looked for."""
    board = BOARDS["symmetric-dark"]
    det = detect_board(np.full((768, 1024), 120, np.uint8), board)
    assert not det.found
    assert det.reason == "board not found: no 9x7 symmetric grid of dark circles detected"


def test_labelling_is_right_handed_and_deterministic(rays: np.ndarray) -> None:
    """A camera rolled by 180° gets the labelling that starts at the image's top-left too.

    The board frame is right-handed with z away from the camera, so the pose found from the
    labelled points has the board in front of the camera, z axis pointing away from it.
    """
    board = BOARDS["symmetric-dark"]
    for roll in (0.0, 180.0):
        T = _view(board, 110.0, 20.0, 1.0, roll_deg=roll)
        det = detect_board(render_view(CAM, board, T, rays=rays), board)
        assert det.found
        first = det.points[0]
        assert first.sum() == min(det.points[p][0].sum() for p in board_symmetries(board))
        _ok, rvec, tvec = cv2.solvePnP(board.object_points(), det.points, CAM.K, CAM.dist)
        R = rotvec_to_matrix(rvec.ravel())
        assert tvec[2, 0] > 0 and R[2, 2] > 0.5  # board z points away from the camera


def test_mirrored_detection_is_relabelled() -> None:
    """A left-handed point order (as a detector may return) is turned right-handed."""
    board = BOARDS["symmetric-dark"]
    T = _view(board, 110.0, 20.0, 1.0)
    proj, _ = _truth(board, T)
    mirrored = proj.reshape(board.rows, board.cols, 2)[:, ::-1].reshape(-1, 2)
    fixed = canonical_labelling(mirrored, board)
    assert any(np.allclose(fixed, proj[p]) for p in board_symmetries(board))


def test_board_symmetries() -> None:
    """Symmetric grids and chessboards have a 180° labelling ambiguity, square ones 90°."""
    assert len(board_symmetries(Board("symmetric", 15, 11, 3.75, 1.875))) == 2
    assert len(board_symmetries(Board("symmetric", 5, 5, 3.0, 1.0))) == 4
    assert len(board_symmetries(Board("asymmetric", 4, 11, 3.0, 2.0))) == 1
    assert len(board_symmetries(Board("chessboard", 9, 6, 5.0))) == 2
    b = Board("symmetric", 15, 11, 3.75, 1.875)
    assert np.array_equal(board_symmetries(b)[1], np.arange(b.n_points)[::-1])


def test_polygon_centroids() -> None:
    """Area centroids of a square and of a triangle, either orientation."""
    sq = np.array([[0.0, 0], [2, 0], [2, 2], [0, 2]])
    assert np.allclose(polygon_centroids(sq), [1.0, 1.0])
    tri = np.array([[0.0, 0], [3, 0], [0, 3]])
    assert np.allclose(polygon_centroids(tri[::-1]), [1.0, 1.0])


def test_centroid_offsets_match_the_analytic_conic() -> None:
    """Without distortion a circle images as an exact ellipse: its centre from the conic.

    The circle x² + y² = R² on the board maps by the homography H = K [r1 r2 t] to the conic
    C = H⁻ᵀ Q H⁻¹ with Q = diag(1, 1, −R²); the ellipse's centre is −C₂₂⁻¹ c (its linear part).
    """
    cam = Camera(CAM.K, np.zeros(5), CAM.image_size)
    board = Board("symmetric", 4, 3, 6.0, 4.0)
    T = _view(board, 60.0, 40.0, 0.4)
    off = centroid_offsets(cam, board, matrix_to_rotvec(T[:3, :3]), T[:3, 3], samples=720)
    R = board.diameter / 2
    for k, p in enumerate(board.object_points()):
        Tk = T @ make_transform(np.eye(3), p)  # circle k at the origin of its own frame
        H = cam.K @ np.column_stack([Tk[:3, 0], Tk[:3, 1], Tk[:3, 3]])
        Hi = np.linalg.inv(H)
        C = Hi.T @ np.diag([1.0, 1.0, -R * R]) @ Hi
        centre = -np.linalg.solve(C[:2, :2], C[:2, 2])
        proj = cam.project(Tk[:3, 3][None])[0]
        assert np.allclose(proj + off[k], centre, atol=2e-4), (k, proj + off[k], centre)
    assert np.abs(off).max() > 0.05  # a real bias, not a trivially zero one


def test_no_bias_on_a_fronto_parallel_board_on_axis() -> None:
    """A board parallel to the image plane, distortion-free: circles image as circles."""
    cam = Camera(CAM.K, np.zeros(5), CAM.image_size)
    board = Board("symmetric", 4, 3, 6.0, 4.0)
    off = centroid_offsets(cam, board, np.zeros(3), np.array([-9.0, -6.0, 80.0]))
    assert np.abs(off).max() < 1e-9


def test_asymmetric_grid_that_opencv_labels_in_the_wrong_row_order(rays: np.ndarray) -> None:
    """A 5 x 8 asymmetric grid: OpenCV's finder returns every circle with its rows out of order
    in some rolls (a homography leaves 0.67 spacings); the detection is right in every roll."""
    board = Board("asymmetric", 5, 8, 4.0, 2.4, "light")
    wrong_in_opencv = 0
    for roll in (0.0, 90.0, 200.0):
        T = _view(board, 120.0, 15.0, 0.7, roll_deg=roll)
        img = render_view(CAM, board, T, rays=rays)
        ok, c = cv2.findCirclesGrid(img, board.pattern_size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID,
                                    blobDetector=blob_detector(board, CAM.image_size))
        wrong_in_opencv += bool(ok) and labelling_error(c.reshape(-1, 2).astype(np.float64), board) > 0.5
        det = detect_board(img, board)
        assert det.found, det.reason
        proj, _ = _truth(board, T)
        assert min(_rms(det.points[p] - proj) for p in board_symmetries(board)) < 0.1, roll
    assert wrong_in_opencv >= 1  # the case this guards against does occur

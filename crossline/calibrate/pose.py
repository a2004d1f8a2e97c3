"""Board poses from one view (PnP), with the perspective bias of circle centres removed."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets
from crossline.camera import Camera
from crossline.geometry import make_transform, matrix_to_rotvec, rotvec_to_matrix

__all__ = ["BoardPose", "board_pose", "project_board"]


@dataclass(frozen=True)
class BoardPose:
    """``T_cam_board`` of one view, the bias-corrected points it was fitted to and its residuals."""

    T_cam_board: np.ndarray
    points: np.ndarray  # (N, 2) measured points minus the predicted bias
    offsets: np.ndarray  # (N, 2) predicted bias that was removed
    residuals: np.ndarray  # (N, 2) corrected points minus projected board points

    @property
    def rms_px(self) -> float:
        """RMS reprojection error (px) of the view, over its measured points."""
        r2 = np.sum(self.residuals**2, axis=1)
        return float(np.sqrt(np.mean(r2[np.isfinite(r2)])))


def project_board(camera: Camera, board: Board, T_cam_board: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of the board's points seen at ``T_cam_board``."""
    P = board.object_points()
    return camera.project(P @ T_cam_board[:3, :3].T + T_cam_board[:3, 3])


def _pnp(camera: Camera, board: Board, pts: np.ndarray, guess: np.ndarray | None) -> np.ndarray:
    obj = board.object_points()
    use = np.isfinite(pts).all(axis=1)
    if not use.all():  # points not measured (NaN rows): the pose from the others
        obj, pts = obj[use], pts[use]
    if guess is None:
        ok, rvec, tvec = cv2.solvePnP(obj, pts, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            ok, rvec, tvec = cv2.solvePnP(obj, pts, camera.K, camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    else:
        rvec = matrix_to_rotvec(guess[:3, :3]).reshape(3, 1)
        tvec = guess[:3, 3].reshape(3, 1).copy()
        ok = True
    if not ok:
        raise ValueError("solvePnP failed")
    ok, rvec, tvec = cv2.solvePnP(
        obj, pts, camera.K, camera.dist, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
    )
    rvec, tvec = cv2.solvePnPRefineLM(
        obj, pts, camera.K, camera.dist, rvec, tvec,
        (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-14),
    )
    return make_transform(rotvec_to_matrix(rvec.ravel()), tvec.ravel())


def board_pose(
    camera: Camera,
    board: Board,
    points: np.ndarray,
    *,
    bias_correction: bool = True,
    iterations: int = 5,
    tol_px: float = 1e-5,
) -> BoardPose:
    """``T_cam_board`` from measured points (N, 2) by PnP (iterative, LM-refined); rows of
    NaN are points not measured, left out of the fit (and NaN in the result's arrays).

    With ``bias_correction``, alternate: pose → predicted centroid offsets → pose on the
    corrected points, until the correction changes by less than ``tol_px``.
    """
    pts = np.asarray(points, dtype=np.float64)
    offsets = np.zeros_like(pts)
    T = _pnp(camera, board, pts, None)
    if bias_correction and board.pattern != "chessboard":
        for _ in range(iterations):
            new = centroid_offsets(camera, board, matrix_to_rotvec(T[:3, :3]), T[:3, 3])
            change = float(np.abs(new - offsets).max())
            offsets = new
            T = _pnp(camera, board, pts - offsets, T)
            if change < tol_px:
                break
    corrected = pts - offsets
    return BoardPose(T, corrected, offsets, corrected - project_board(camera, board, T))

"""Hand-eye AX = XB solvers: the motion pairs, Chou & Kamel's quaternion method, OpenCV's five.

For a motion pair (i, j), ``A = inv(T_base_tool_j) @ T_base_tool_i`` and
``B = T_cam_board_j @ inv(T_cam_board_i)`` satisfy ``A X = X B`` (step 3 of
:mod:`crossline.calibrate.handeye`'s docstring). ``chou_kamel`` solves it from the pairs (the
paper's method), ``opencv_handeye`` by ``cv2.calibrateHandEye`` from the poses, and
``pair_residuals`` scores an X on the pairs. Split from ``crossline.calibrate.handeye``
(issue 21.3), which re-exports these names.
"""

from __future__ import annotations

import cv2
import numpy as np

from crossline.geometry import (
    invert_transform,
    make_transform,
    matrix_to_quat,
    orthonormalize,
    rotation_angle,
)

__all__ = ["OPENCV_METHODS", "chou_kamel", "motion_pairs", "opencv_handeye", "pair_residuals"]

OPENCV_METHODS = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}


def motion_pairs(
    T_base_tool: np.ndarray, T_cam_board: np.ndarray, pairs: list[tuple[int, int]]
) -> tuple[np.ndarray, np.ndarray]:
    """``A`` and ``B`` (P, 4, 4) of the motion pairs (i, j): ``A X = X B`` (module docstring)."""
    i = np.array([p[0] for p in pairs])
    j = np.array([p[1] for p in pairs])
    A = invert_transform(T_base_tool[j]) @ T_base_tool[i]
    B = T_cam_board[j] @ invert_transform(T_cam_board[i])
    return A, B


def _quat_left(q: np.ndarray) -> np.ndarray:
    """Matrices (..., 4, 4) with ``L(p) q = p ⊗ q`` (Hamilton product, scalar first)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([w, -x, -y, -z], -1),
        np.stack([x, w, -z, y], -1),
        np.stack([y, z, w, -x], -1),
        np.stack([z, -y, x, w], -1),
    ], -2)


def _quat_right(q: np.ndarray) -> np.ndarray:
    """Matrices (..., 4, 4) with ``R(p) q = q ⊗ p``."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([w, -x, -y, -z], -1),
        np.stack([x, w, z, -y], -1),
        np.stack([y, -z, w, x], -1),
        np.stack([z, y, -x, w], -1),
    ], -2)


def chou_kamel(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X from motion pairs by Chou & Kamel's quaternion method (rotation by SVD, then translation).

    For each pair ``q_A ⊗ q_X = q_X ⊗ q_B``, i.e. ``(L(q_A) − R(q_B)) q_X = 0``; stacked over all
    pairs, ``q_X`` is the right singular vector of the smallest singular value. Both
    quaternions of a pair are taken with a non-negative scalar part (equal rotation angles
    give equal scalar parts). The translation solves ``(R_A − I) t_X = R_X t_B − t_A`` in the
    least-squares sense.
    """
    qa = matrix_to_quat(A[:, :3, :3])
    qb = matrix_to_quat(B[:, :3, :3])
    M = (_quat_left(qa) - _quat_right(qb)).reshape(-1, 4)
    _, _, Vt = np.linalg.svd(M)
    qx = Vt[-1]
    from crossline.geometry import quat_to_matrix

    Rx = quat_to_matrix(qx / np.linalg.norm(qx))
    C = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    d = (np.einsum("ij,pj->pi", Rx, B[:, :3, 3]) - A[:, :3, 3]).reshape(-1)
    tx, *_ = np.linalg.lstsq(C, d, rcond=None)
    return make_transform(orthonormalize(Rx), tx)


def opencv_handeye(T_base_tool: np.ndarray, T_cam_board: np.ndarray, method: str) -> np.ndarray:
    """X by ``cv2.calibrateHandEye`` with one of :data:`OPENCV_METHODS`."""
    R, t = cv2.calibrateHandEye(
        list(T_base_tool[:, :3, :3]), list(T_base_tool[:, :3, 3:]),
        list(T_cam_board[:, :3, :3]), list(T_cam_board[:, :3, 3:]),
        method=OPENCV_METHODS[method],
    )
    return make_transform(orthonormalize(R), t.ravel())


def pair_residuals(X: np.ndarray, A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair: rotation residual of ``AX`` vs ``XB`` (rad) and translation residual (mm)."""
    L = A @ X
    Rr = X @ B
    rot = rotation_angle(np.swapaxes(L[:, :3, :3], 1, 2) @ Rr[:, :3, :3])
    return rot, np.linalg.norm(L[:, :3, 3] - Rr[:, :3, 3], axis=1)

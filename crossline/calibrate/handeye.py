"""Hand-eye calibration: ``X = T_tool_cam`` from arm poses and board views (AX = XB).

Conventions (DESIGN.md §1): the arm reports ``T_base_tool``; PnP gives ``T_cam_board``; the
board is fixed, so for every view ``T_base_board = T_base_tool_i @ X @ T_cam_board_i``. For
a motion pair (i, j)::

    A = inv(T_base_tool_j) @ T_base_tool_i,   B = T_cam_board_j @ inv(T_cam_board_i),   A X = X B

(the paper's eq. 20–23). Steps:

1. Board poses by PnP on bias-corrected centres; on a board that looks the same turned in its
   plane (symmetric grid, chessboard), each view's labelling is one of several; the one used
   is chosen so that every view agrees on one board frame (:func:`resolve_labellings`): first
   by rotation consistency of motion pairs (a rotation angle is invariant under a change of
   frame, so ``θ(A) = θ(B)`` for the right labelling; a wrong one adds a half turn about the
   board normal), then confirmed with the first X: each view's implied ``T_base_board`` must
   agree with the others'.
2. The tolerance on ``θA − θB`` comes from the data: its spread is set by the arm's and the
   board poses' rotation noise (the same for every pair to first order: the noise projected on
   the pair's rotation axis), estimated robustly as σ = 1.4826 · median |θA − θB| over all
   pairs (a wrong view spoils its own V − 1 pairs, a minority). Pairs beyond ``k σ`` (``k``
   from the configuration) are rejected and counted; a view in more rejected than accepted
   pairs is left out; motion whose rotation axes are all nearly parallel is a
   :class:`CalibrationError`.
3. Chou & Kamel (1991), the paper's method: ``q_A ⊗ q_X = q_X ⊗ q_B`` stacked for every pair,
   ``q_X`` the right singular vector of the smallest singular value; then the translation by
   linear least squares from ``(R_A − I) t_X = R_X t_B − t_A``. OpenCV's five methods
   (Tsai, Park, Horaud, Andreff, Daniilidis) are run alongside.
4. Refinement: X and ``T_base_board`` jointly, minimising the reprojection error (px) of every
   board point in every view through ``T_cam_board_i = inv(X) inv(T_base_tool_i) T_base_board``
   with the calibrated camera (scipy least squares), the circle-centre bias re-predicted from
   the current estimate between rounds. First with the arm poses taken as exact
   ("reprojection"), then by maximum likelihood ("refined"): each view's arm pose gets a
   correction weighted by the arm's standard deviations against the image residuals, the
   image and arm sigmas estimated from the residuals by variance components (Förstner). The
   covariance of X that follows predicts its error (checked over many noise draws in the
   tests and in benchmarks/bench_handeye.py). The refinement starts from the algebraic
   solution (Chou–Kamel or OpenCV's) with the best board consistency.
5. The final estimate is chosen on the views, with every method scored alike by its board
   consistency (:func:`consistency_mm`, the scatter of the board's points in the base frame).
   That score is in-sample: an X fitted to the arm's noise of these views lowers it while
   moving away from the truth, so the least-scatter X is not the most accurate one (the
   benchmark shows it). The refined X is kept unless another method's consistency is better
   by more than X's own uncertainty explains: the excess of squared consistency that an error
   of X distributed as its covariance causes, ``δᵀ H δ`` with ``H`` the consistency's Gauss–
   Newton matrix, has a quantile (Welch–Satterthwaite, 99 %) that sets the margin. Beyond it
   the refinement's noise model does not fit the data and the method with the best
   consistency wins. ``selection`` in handeye.json says which won, the margin, and how it
   compares with the best OpenCV method.
"""

from __future__ import annotations

import itertools
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets
from crossline.calibrate.detect import board_symmetries
from crossline.calibrate.lm import dense_normal, levenberg_marquardt
from crossline.calibrate.pose import board_pose
from crossline.camera import Camera
from crossline.errors import CalibrationError
from crossline.geometry import (
    invert_transform,
    make_transform,
    matrix_to_quat,
    matrix_to_rotvec,
    orthonormalize,
    rotation_angle,
    rotvec_to_matrix,
    transform_points,
)
from crossline.io.atomic import write_json

__all__ = [
    "OPENCV_METHODS",
    "HandEye",
    "check_motion",
    "chou_kamel",
    "consistency_margin",
    "consistency_mm",
    "mismatch_sigma",
    "motion_pairs",
    "opencv_handeye",
    "pair_residuals",
    "point_uncertainty",
    "refine_handeye",
    "resolve_labellings",
    "run_calibrate_handeye",
    "select_estimate",
    "symmetry_transforms",
]

log = logging.getLogger(__name__)

OPENCV_METHODS = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
MIN_PAIR_ROTATION_DEG = 1.0  # pairs rotating less say nothing about the rotation axis
MIN_AXIS_SPREAD_DEG = 5.0  # rotation axes must span at least this angle
MISMATCH_K = 4.0  # default cut on |theta_A - theta_B|, in robust sigmas of all pairs' mismatches
# floor of that sigma (rad): far below any real rotation noise, it keeps exact (synthetic)
# data, whose mismatches are rounding, from rejecting pairs on rounding
MISMATCH_SIGMA_FLOOR = 1e-9
SELECTION_QUANTILE = 0.99  # of the consistency excess X's own uncertainty explains


@dataclass(frozen=True)
class HandEye:
    """The hand-eye result as stored in ``handeye.json``: ``T_tool_cam`` and everything else."""

    T_tool_cam: np.ndarray
    method: str = "refined"
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        T = np.asarray(self.T_tool_cam, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_tool_cam must be 4x4, got shape {T.shape}")
        object.__setattr__(self, "T_tool_cam", T)

    def to_dict(self) -> dict[str, Any]:
        """JSON mapping with ``T_tool_cam``, ``method`` and the extras."""
        out = dict(self.extra)
        out.update(T_tool_cam=self.T_tool_cam.tolist(), method=self.method)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> HandEye:
        """From a mapping with ``T_tool_cam`` (and optionally ``method``)."""
        extra = {k: v for k, v in data.items() if k not in ("T_tool_cam", "method")}
        return cls(np.array(data["T_tool_cam"], dtype=np.float64), data.get("method", "refined"), extra)

    def save(self, path: str | Path) -> None:
        """Write ``handeye.json`` atomically."""
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> HandEye:
        """Read ``handeye.json``."""
        path = Path(path)
        try:
            return cls.from_dict(json.loads(path.read_text()))
        except (KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"{path}: not a hand-eye file: {exc}") from exc


# ----------------------------------------------------------------------------- AX = XB


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


def consistency_mm(X: np.ndarray, T_base_tool: np.ndarray, T_cam_board: np.ndarray, board: Board) -> float:
    """RMS scatter (mm) of the board's points in the base frame over the views, given X.

    Each view puts the board at ``T_base_tool_i X T_cam_board_i``; with the right X and exact
    data all views agree. Independent of truth, it scores every method alike.
    """
    P = board.object_points()
    T = T_base_tool @ X @ T_cam_board
    pts = np.einsum("vij,nj->vni", T[:, :3, :3], P) + T[:, None, :3, 3]
    return float(np.sqrt(np.mean(np.sum((pts - pts.mean(0)) ** 2, axis=-1))))


def mismatch_sigma(theta_A: np.ndarray, theta_B: np.ndarray) -> float:
    """Robust standard deviation (rad) of the pairs' rotation-angle mismatch ``θA − θB``.

    The mismatch is zero for the right data, so its spread is taken about zero: 1.4826 times
    the median of ``|θA − θB|`` (the normal-consistent MAD), which a minority of wrong pairs
    (those of one bad view) cannot inflate much.
    """
    m = np.abs(np.asarray(theta_A, dtype=np.float64) - np.asarray(theta_B, dtype=np.float64))
    return max(1.4826 * float(np.median(m)), MISMATCH_SIGMA_FLOOR)


def _consistency_residuals(X: np.ndarray, T_base_tool: np.ndarray, T_cam_board: np.ndarray,
                           P: np.ndarray) -> np.ndarray:
    T = T_base_tool @ X @ T_cam_board
    pts = np.einsum("vij,nj->vni", T[:, :3, :3], P) + T[:, None, :3, 3]
    return (pts - pts.mean(0)).ravel()


def consistency_margin(
    X: np.ndarray, cov: np.ndarray, T_base_tool: np.ndarray, T_cam_board: np.ndarray, board: Board,
    quantile: float = SELECTION_QUANTILE,
) -> dict[str, float]:
    """How much worse a consistency X's own uncertainty explains (mm², and mm at X's consistency).

    With ``r(δ)`` the consistency residuals of ``X exp(δ)`` (``consistency_mm`` squared is
    ``|r|² / (V N)``) and ``J`` their Jacobian, an error ``δ ~ N(0, cov)`` of X changes the
    squared consistency by ``δᵀ H δ``, ``H = JᵀJ / (V N)``: a weighted sum of χ²₁ whose weights
    are the eigenvalues of ``cov^½ H cov^½``; its ``quantile`` by the Welch–Satterthwaite
    approximation (a scaled χ² of matched mean and variance) is the margin.
    """
    from scipy.special import gammaincinv  # the chi-square quantile, without scipy.stats' import

    P = board.object_points()
    f0 = _consistency_residuals(X, T_base_tool, T_cam_board, P)
    J = np.empty((f0.size, 6))
    for k in range(6):
        h = 1e-7 if k < 3 else 1e-5
        dx = np.zeros(6)
        dx[k] = h
        J[:, k] = (_consistency_residuals(X @ _delta(dx), T_base_tool, T_cam_board, P) - f0) / h
    H = J.T @ J / (len(T_base_tool) * len(P))
    w, U = np.linalg.eigh(0.5 * (cov + cov.T))
    half = U @ np.diag(np.sqrt(np.clip(w, 0.0, None))) @ U.T
    lam = np.clip(np.linalg.eigvalsh(half @ H @ half), 0.0, None)
    mean, var = float(lam.sum()), float(2.0 * np.sum(lam**2))
    if mean <= 0.0:
        return {"expected_mm2": 0.0, "margin_mm2": 0.0}
    a, nu = var / (2.0 * mean), 2.0 * mean**2 / var
    return {"expected_mm2": mean, "margin_mm2": float(a * 2.0 * gammaincinv(nu / 2.0, quantile))}


def check_motion(A: np.ndarray, names: list[str] | None = None) -> dict[str, float]:
    """Raise :class:`CalibrationError` if the arm's rotations cannot determine X.

    X is determined only if at least two motions rotate about clearly different axes.
    Returns the largest angle between rotation axes (deg) and the count of rotating pairs.
    """
    rv = matrix_to_rotvec(A[:, :3, :3])
    th = np.linalg.norm(rv, axis=1)
    big = th > np.radians(MIN_PAIR_ROTATION_DEG)
    if big.sum() < 2:
        raise CalibrationError(
            f"degenerate hand-eye motion: only {int(big.sum())} of {len(A)} motion pairs rotate "
            f"by more than {MIN_PAIR_ROTATION_DEG:g} deg; the arm must turn the camera between views"
        )
    ax = rv[big] / th[big, None]
    cross = np.linalg.norm(np.cross(ax[:, None, :], ax[None, :, :]), axis=-1)
    spread = float(np.degrees(np.arcsin(np.clip(cross.max(), 0.0, 1.0))))
    if spread < MIN_AXIS_SPREAD_DEG:
        raise CalibrationError(
            f"degenerate hand-eye motion: all {int(big.sum())} rotating motion pairs turn about "
            f"nearly the same axis (largest angle between rotation axes {spread:.2f} deg < "
            f"{MIN_AXIS_SPREAD_DEG:g} deg), so X = T_tool_cam is not determined about that axis. "
            f"Re-take the hand-eye views (calibration/handeye) rotating the scanner about at least "
            f"two different axes between views, e.g. tilted towards different sides of the board, "
            f"not only turned about one axis"
        )
    return {"axis_spread_deg": spread, "rotating_pairs": int(big.sum())}


# ----------------------------------------------------------------------------- labelling


def symmetry_transforms(board: Board) -> list[np.ndarray]:
    """Board-frame transforms ``S`` (4, 4), one per labelling the board's symmetry allows.

    If a view's pose is ``T`` under one labelling, it is ``T @ S`` under the other; the first
    is the identity. Matches :func:`crossline.calibrate.detect.board_symmetries`.
    """
    P = board.object_points()
    c = 0.5 * (P.min(0) + P.max(0))
    out = []
    for perm in board_symmetries(board):
        # the rotation in the board plane that carries each point k onto point perm[k]
        d0, d1 = P[1] - P[0], P[perm[1]] - P[perm[0]]
        if board.cols < 2 or np.linalg.norm(d0) == 0:  # pragma: no cover - boards have >= 2 cols
            continue
        a = np.arctan2(d1[1], d1[0]) - np.arctan2(d0[1], d0[0])
        R = rotvec_to_matrix(np.array([0.0, 0.0, a]))
        S = make_transform(R, c - R @ c)
        assert np.allclose(transform_points(S, P), P[perm], atol=1e-9 * board.spacing)
        out.append(S)
    return out


def resolve_labellings(
    T_base_tool: np.ndarray, T_cam_board: np.ndarray, board: Board
) -> tuple[np.ndarray, np.ndarray]:
    """Choose per view the board labelling that makes all views agree on one board frame.

    Returns the relabelled ``T_cam_board`` (V, 4, 4) and per view the index into
    :func:`symmetry_transforms` applied to it (0 = as detected); the first view keeps its
    detected labelling. Boards without symmetry are returned unchanged.
    """
    S = np.array(symmetry_transforms(board))
    V, G = len(T_cam_board), len(S)
    if G == 1 or V < 2:
        return T_cam_board.copy(), np.zeros(V, dtype=int)
    cand = T_cam_board[:, None] @ S[None]  # (V, G, 4, 4)
    inv_cand = invert_transform(cand)
    # rotation angle of every arm motion (i -> j), and of every board motion per labelling
    thA = rotation_angle((invert_transform(T_base_tool)[None, :] @ T_base_tool[:, None])[..., :3, :3])
    # thB[i, g, j, h]: angle of cand[j, h] @ inv(cand[i, g])
    thB = rotation_angle(
        (cand[None, None, :, :] @ inv_cand[:, :, None, None])[..., :3, :3]
    )
    iu, ju = np.triu_indices(V, 1)
    best_choice, best_score = None, np.inf
    for ref in range(V):
        # each view's labelling from its motion relative to the reference view
        choice = np.argmin(np.abs(thA[ref, :, None] - thB[ref, 0]), axis=1)
        choice[ref] = 0
        score = np.median(np.abs(thA[iu, ju] - thB[iu, choice[iu], ju, choice[ju]]))
        if score < best_score - 1e-12:
            best_choice, best_score = choice, score
    choice = best_choice
    # confirm with a first X: each view's board in the base frame must agree with the others'
    P = board.object_points()
    for _ in range(3):
        Tc = cand[np.arange(V), choice]
        A, B = motion_pairs(T_base_tool, Tc, list(zip(iu, ju, strict=True)))
        X = chou_kamel(A, B)
        Tbb = T_base_tool[:, None] @ X @ cand  # (V, G, 4, 4)
        pts = np.einsum("vgij,nj->vgni", Tbb[..., :3, :3], P) + Tbb[..., None, :3, 3]
        consensus = np.median(pts[np.arange(V), choice], axis=0)  # (N, 3)
        err = np.sqrt(np.mean(np.sum((pts - consensus) ** 2, -1), -1))  # (V, G)
        new = err.argmin(1)
        if np.array_equal(new, choice):
            break
        choice = new
    # the same symmetry applied to every view changes nothing physical: keep view 0 as detected
    rel = S[choice] @ invert_transform(S[choice[0]])
    idx = np.array([_sym_index(S, r) for r in rel])
    return T_cam_board @ S[idx], idx


def _sym_index(S: list[np.ndarray], T: np.ndarray) -> int:
    return int(np.argmin([np.abs(s - T).max() for s in S]))


# ----------------------------------------------------------------------------- refinement


def _delta(x: np.ndarray) -> np.ndarray:
    return make_transform(rotvec_to_matrix(x[:3]), x[3:])


@dataclass(frozen=True)
class Refinement:
    """Result of :func:`refine_handeye`."""

    X: np.ndarray
    T_base_board: np.ndarray
    residuals: np.ndarray  # (V, N, 2) px: bias-corrected measurement minus projection
    arm_corrections: np.ndarray  # (V, 6): flange rotation (rad, flange frame), position (mm, base)
    iterations: int
    covariance_X: np.ndarray  # (6, 6) of the perturbation X_true = X exp(rotation, translation)
    # the standard deviations the final solve weighted with: image_px, arm_mm, arm_rad
    sigmas: dict[str, float] = field(default_factory=dict)
    # per group (image, arm_rotation, arm_position): weighted residual square sum over its
    # redundancy at the solution; 1 when the group's sigma fits its residuals
    variance_factors: dict[str, float] = field(default_factory=dict)
    sigma_iterations: int = 0  # variance-component re-weightings done

    @property
    def rms_px(self) -> float:
        """RMS reprojection error over all points of all views (px)."""
        return float(np.sqrt(np.mean(np.sum(self.residuals**2, -1))))


def _corrected_arm(T_base_tool: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Arm poses with corrections ``xi`` (V, 6): rotation in the flange frame, position in base."""
    R = T_base_tool[:, :3, :3] @ rotvec_to_matrix(xi[:, :3])
    return make_transform(R, T_base_tool[:, :3, 3] + xi[:, 3:])


_STEPS = np.r_[[1e-7] * 3, [1e-5] * 3, [1e-7] * 3, [1e-5] * 3, [1e-7] * 3, [1e-5] * 3]
# lower bounds of estimated standard deviations (px, mm, rad): far below any real noise, they
# keep exact (synthetic) data well conditioned
SIGMA_FLOORS = {"image_px": 1e-4, "arm_mm": 1e-5, "arm_rad": 1e-8}
VCE_X_TOL = 0.05  # re-weighting stops when it moves X by less than this many of its sigmas


def _jacobian(fun, x: np.ndarray, *, V: int, N: int, with_arm: bool) -> np.ndarray:
    """Forward-difference Jacobian of the hand-eye residuals (image rows, then arm priors).

    A view's rows depend on X, T_base_board and its own arm correction only, so one component
    of every view's correction is perturbed at once.
    """
    f0 = fun(x)
    J = np.zeros((f0.size, x.size))
    for k in range(12):
        dx = np.zeros_like(x)
        dx[k] = _STEPS[k]
        J[:, k] = (fun(x + dx) - f0) / _STEPS[k]
    if with_arm:
        rows = np.arange(2 * N * V).reshape(V, 2 * N)
        for m in range(6):
            dx = np.zeros_like(x)
            dx[12 + m :: 6] = _STEPS[12 + m]
            df = (fun(x + dx) - f0) / _STEPS[12 + m]
            cols = 12 + 6 * np.arange(V) + m
            J[rows, cols[:, None]] = df[rows]
            prior = 2 * N * V + (3 * np.arange(V) + m if m < 3 else 3 * V + 3 * np.arange(V) + m - 3)
            J[prior, cols] = df[prior]
    return J


def refine_handeye(
    camera: Camera,
    board: Board,
    points: np.ndarray,
    T_base_tool: np.ndarray,
    X0: np.ndarray,
    T_base_board0: np.ndarray,
    *,
    sigma_px: float = 1.0,
    arm_sigma_mm: float = 0.0,
    arm_sigma_rad: float = 0.0,
    bias_correction: bool = True,
    rounds: int = 3,
    estimate_sigmas: bool = False,
    max_sigma_iterations: int = 25,
    sigma_tol: float = 0.005,
) -> Refinement:
    """X and ``T_base_board`` minimising the reprojection error of measured points (V, N, 2).

    Every board point of every view is projected through
    ``T_cam_board_i = inv(X) inv(T_base_tool_i) T_base_board`` with the calibrated camera.
    With ``arm_sigma_mm`` and ``arm_sigma_rad`` > 0 the reported arm poses are not taken as
    exact: each view's flange pose gets a correction (3 rotations in the flange frame, 3
    translations in the base frame) weighted by those standard deviations against the
    image residuals weighted by ``sigma_px`` (maximum likelihood when the arm's error is
    Gaussian). With zero arm sigmas only X and ``T_base_board`` move (12 parameters). The
    circle-centre bias is re-predicted from the current estimate for each of ``rounds``.

    With ``estimate_sigmas`` the three standard deviations given are starting values: they
    are re-estimated from the solution by variance-component estimation (Förstner): each
    group's weighted residual square sum over its redundancy (its share of the degrees of
    freedom, from the hat matrix) rescales its variance, and the problem is re-solved, until
    no sigma changes by more than ``sigma_tol`` (relative) or a re-weighting moves X by less
    than ``VCE_X_TOL`` of its standard deviations. The arm's error and the board poses' image
    error then share the disagreement between arm and images as their precisions say, which
    a per-view comparison of poses cannot do (it charges the board poses' error to the arm).
    The covariance is then not rescaled by the overall chi-square.
    """
    P = board.object_points()
    pts = np.asarray(points, dtype=np.float64)
    V, N = pts.shape[:2]
    with_arm = arm_sigma_mm > 0 and arm_sigma_rad > 0
    X, Tbb = X0.copy(), T_base_board0.copy()
    xi = np.zeros((V, 6))
    offsets = np.zeros_like(pts)
    correct = bias_correction and board.pattern != "chessboard"

    def cam_board(X: np.ndarray, Tbb: np.ndarray, xi: np.ndarray) -> np.ndarray:
        return invert_transform(X) @ invert_transform(_corrected_arm(T_base_tool, xi)) @ Tbb

    R_arm, t_arm = T_base_tool[:, :3, :3], T_base_tool[:, :3, 3]
    sig = {"image_px": float(sigma_px), "arm_mm": float(arm_sigma_mm), "arm_rad": float(arm_sigma_rad)}
    estimate = estimate_sigmas and with_arm
    gain = dict.fromkeys(sig, 1.0)
    last = dict.fromkeys(sig, 0.0)
    sol = None
    factors: dict[str, float] = {}
    iterations = 0  # LM iterations over all rounds
    sigma_iterations = 0
    for _ in range(rounds if correct else 1):
        if correct:
            offsets = np.array([
                centroid_offsets(camera, board, matrix_to_rotvec(T[:3, :3]), T[:3, 3])
                for T in cam_board(X, Tbb, xi)
            ])
        obs = pts - offsets
        X_base, Tbb_base = X.copy(), Tbb.copy()
        x0 = np.zeros(12 + (6 * V if with_arm else 0))
        if with_arm:
            x0[12:] = xi.ravel()
        for it in range(max_sigma_iterations + 1 if estimate else 1):

            def fun(x: np.ndarray, X_base=X_base, Tbb_base=Tbb_base, obs=obs,
                    s=(sig["image_px"], sig["arm_rad"], sig["arm_mm"])) -> np.ndarray:
                xv = x[12:].reshape(V, 6) if with_arm else np.zeros((V, 6))
                # T_cam_board = inv(X) inv(arm) T_base_board, composed on rotations and vectors
                Rx = X_base[:3, :3] @ rotvec_to_matrix(x[:3])
                tx = X_base[:3, :3] @ x[3:6] + X_base[:3, 3]
                Rb = Tbb_base[:3, :3] @ rotvec_to_matrix(x[6:9])
                tb = Tbb_base[:3, :3] @ x[9:12] + Tbb_base[:3, 3]
                RaT = np.swapaxes(R_arm @ rotvec_to_matrix(xv[:, :3]), 1, 2)
                Rc = Rx.T @ RaT @ Rb
                tc = (RaT @ (tb - t_arm - xv[:, 3:])[:, :, None])[:, :, 0] @ Rx - tx @ Rx
                pc = P @ np.swapaxes(Rc, 1, 2) + tc[:, None, :]
                img = ((camera.project(pc) - obs) / s[0]).ravel()
                if not with_arm:
                    return img
                prior = [(xv[:, :3] / s[1]).ravel(), (xv[:, 3:] / s[2]).ravel()]
                return np.concatenate([img, *prior])

            last_J: dict[str, np.ndarray] = {}

            def jac(x: np.ndarray, fun=fun, last_J=last_J) -> np.ndarray:
                last_J["x"], last_J["J"] = x.copy(), _jacobian(fun, x, V=V, N=N, with_arm=with_arm)
                return last_J["J"]

            prev = x0
            sol = levenberg_marquardt(fun, dense_normal(jac), x0)
            iterations += sol.iterations
            x0 = sol.x
            if not estimate:
                break
            # the solver's last Jacobian is the one at its solution; the factors describe the
            # weighting of this solve, whichever test below ends the loop
            J = last_J["J"] if np.array_equal(last_J["x"], sol.x) else jac(sol.x)
            factors = _variance_factors(J, sol.normal, sol.fun, V, N)
            if it > 0:
                # where the data hardly tell a sigma (an arm far more precise than the board
                # poses: the likelihood is flat in it), X no longer moves: stop there
                d = sol.x[:6] - prev[:6]
                if d @ np.linalg.solve(np.linalg.pinv(sol.normal)[:6, :6], d) < VCE_X_TOL**2:
                    break
            # Förstner's update is sigma^2 <- sigma^2 f. It converges slowly for a group whose
            # rows are nearly spent on the parameters (an arm far more precise than the board
            # poses): while a group's steps keep one direction their gain doubles (to 16),
            # when they turn it halves (to 1); a step changes a sigma by 4x at most.
            new = {}
            for g, key in (("image", "image_px"), ("arm_rotation", "arm_rad"), ("arm_position", "arm_mm")):
                raw = 0.5 * np.log(max(factors[g], 1e-30))
                gain[key] = min(2 * gain[key], 16.0) if raw * last[key] > 0 else max(gain[key] / 2, 1.0)
                last[key] = raw
                step = float(np.clip(gain[key] * raw, -np.log(4.0), np.log(4.0)))
                # a group below its floor (exact data) counts as settled
                new[key] = max(sig[key] * float(np.exp(step)), SIGMA_FLOORS[key])
            if it == max_sigma_iterations or all(abs(new[k] / sig[k] - 1.0) <= sigma_tol for k in sig):
                break
            sig = new
            sigma_iterations += 1
        X = X_base @ _delta(sol.x[:6])
        Tbb = Tbb_base @ _delta(sol.x[6:12])
        if with_arm:
            xi = sol.x[12:].reshape(V, 6)
    res = sol.fun[: 2 * N * V].reshape(V, N, 2) * sig["image_px"]
    cov = np.linalg.pinv(sol.normal)
    if not estimate:
        # the weights are relative only: scale by the reduced chi-square
        cov *= 2.0 * sol.cost / max(sol.fun.size - sol.x.size, 1)
    return Refinement(X, Tbb, res, xi, iterations, cov[:6, :6], sig, factors, sigma_iterations)


def _variance_factors(J: np.ndarray, normal: np.ndarray, f: np.ndarray, V: int, N: int) -> dict[str, float]:
    """Per residual group: weighted square sum over redundancy (Förstner's variance components).

    A row's redundancy is ``1 - h`` with ``h`` the diagonal of the hat matrix
    ``J (JᵀJ)⁻¹ Jᵀ`` of the whitened problem: the share of that observation not spent on the
    parameters. Rows: image (2NV), arm rotation priors (3V), arm position priors (3V).
    """
    r = 1.0 - np.einsum("ij,ij->i", J @ np.linalg.pinv(normal), J)
    n_img = 2 * N * V
    groups = {"image": slice(0, n_img), "arm_rotation": slice(n_img, n_img + 3 * V),
              "arm_position": slice(n_img + 3 * V, n_img + 6 * V)}
    return {g: float(np.sum(f[sl] ** 2) / max(np.sum(r[sl]), 1e-9)) for g, sl in groups.items()}


def point_uncertainty(X: np.ndarray, cov: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """1-sigma uncertainty (mm, RMS of the 3-D error) of camera points carried by X to the tool.

    ``cov`` is the covariance of the perturbation ``X_true = X exp(ω, t)`` (rad, mm).
    """
    p = np.asarray(points_cam, dtype=np.float64)
    R = X[:3, :3]
    # d(X p) = R (ω × p + t) = R [-[p]x | I] (ω, t)
    skew = np.zeros((len(p), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = p[:, 2], -p[:, 1], p[:, 0]
    Jp = np.concatenate([-skew, np.broadcast_to(np.eye(3), skew.shape)], axis=2)
    Jp = R @ Jp
    return np.sqrt(np.einsum("nij,jk,nik->n", Jp, cov, Jp))


def arm_noise_estimate(
    X: np.ndarray, T_base_tool: np.ndarray, T_cam_board: np.ndarray
) -> tuple[float, float, np.ndarray]:
    """Per-axis standard deviations of the arm's pose error (mm, rad) implied by a solution X.

    Each view implies the flange pose ``T_base_board inv(T_cam_board_i) inv(X)``, with
    ``T_base_board`` the views' mean; its difference from the reported pose is the arm's error
    (plus a little PnP noise). 12 of the 6V numbers are spent on X and ``T_base_board``.
    Returns (sigma_mm, sigma_rad, T_base_board).
    """
    V = len(T_base_tool)
    Tbb = _mean_transform(T_base_tool @ X @ T_cam_board)
    implied = Tbb @ invert_transform(T_cam_board) @ invert_transform(X)
    rot = matrix_to_rotvec(np.swapaxes(T_base_tool[:, :3, :3], 1, 2) @ implied[:, :3, :3])
    tr = implied[:, :3, 3] - T_base_tool[:, :3, 3]
    dof = max(3 * V - 6, 1)
    return float(np.sqrt(np.sum(tr**2) / dof)), float(np.sqrt(np.sum(rot**2) / dof)), Tbb


def _mean_transform(T: np.ndarray) -> np.ndarray:
    """Rotation mean (chordal, by SVD) and translation mean of transforms (V, 4, 4)."""
    return make_transform(orthonormalize(T[:, :3, :3].sum(0)), T[:, :3, 3].mean(0))


# ----------------------------------------------------------------------------- stage


def solve_handeye(
    camera: Camera,
    board: Board,
    points: np.ndarray,
    T_base_tool: np.ndarray,
    names: list[str],
    *,
    mismatch_k: float = MISMATCH_K,
    bias_correction: bool = True,
) -> HandEye:
    """All methods and the chosen X from measured points (V, N, 2) and arm poses (V, 4, 4).

    Motion pairs whose rotation-angle mismatch exceeds ``mismatch_k`` robust sigmas of all
    pairs' mismatches are rejected (module docstring, step 2).
    """
    V = len(points)
    if V < 3:
        raise CalibrationError(f"hand-eye calibration needs at least 3 views with the board found, got {V}")
    fits = [board_pose(camera, board, p, bias_correction=bias_correction) for p in points]
    T0 = np.array([f.T_cam_board for f in fits])
    Tc, sym = resolve_labellings(T_base_tool, T0, board)
    S = symmetry_transforms(board)
    # the points relabelled alike: the pose T @ S sees point k where the detection had perm[k]
    perms = board_symmetries(board)
    pts = np.array([p[perms[s]] for p, s in zip(points, sym, strict=True)])
    all_pairs = list(itertools.combinations(range(V), 2))
    A, B = motion_pairs(T_base_tool, Tc, all_pairs)
    thA, thB = rotation_angle(A[:, :3, :3]), rotation_angle(B[:, :3, :3])
    sigma_m = mismatch_sigma(thA, thB)
    tol = mismatch_k * sigma_m
    keep = np.abs(thA - thB) <= tol
    rejected = [
        {"pair": [names[i], names[j]], "theta_A_deg": float(np.degrees(thA[k])),
         "theta_B_deg": float(np.degrees(thB[k]))}
        for k, (i, j) in enumerate(all_pairs) if not keep[k]
    ]
    for r in rejected:
        log.warning("hand-eye pair %s rejected: rotation angles %.4f vs %.4f deg differ by more than "
                    "%.4g deg (%g robust sigmas of all pairs' mismatches)",
                    r["pair"], r["theta_A_deg"], r["theta_B_deg"], np.degrees(tol), mismatch_k)
    # a view in more rejected than accepted pairs is the culprit (its arm pose or its image):
    # it is left out of everything that uses absolute poses (OpenCV, the refinement)
    bad_count = np.zeros(V, dtype=int)
    for k, (i, j) in enumerate(all_pairs):
        if not keep[k]:
            bad_count[i] += 1
            bad_count[j] += 1
    use = bad_count <= (V - 1) / 2
    rejected_views = [
        {"image": names[v], "rejected_pairs": int(bad_count[v]), "pairs": V - 1}
        for v in range(V) if not use[v]
    ]
    for r in rejected_views:
        log.warning("%s: left out of the hand-eye solution: %d of its %d motion pairs have "
                    "mismatching rotation angles", r["image"], r["rejected_pairs"], r["pairs"])
    in_use = np.array([use[i] and use[j] for i, j in all_pairs])
    keep &= in_use
    if keep.sum() < 2 or use.sum() < 3:
        raise CalibrationError(
            f"hand-eye calibration: only {int(keep.sum())} of {len(all_pairs)} motion pairs have "
            f"matching rotation angles (|theta_A - theta_B| <= {np.degrees(tol):.4g} deg, "
            f"{mismatch_k:g} robust sigmas of all pairs' mismatches); check that poses.csv matches "
            f"the images"
        )
    motion = check_motion(A[keep])
    Ak, Bk = A[keep], B[keep]
    all_names, all_fits, all_Tc, all_sym = names, fits, Tc, sym
    u = np.nonzero(use)[0]
    T_base_tool, Tc, pts = T_base_tool[u], Tc[u], pts[u]
    names = [names[k] for k in u]
    methods: dict[str, dict[str, Any]] = {}

    def record(name: str, X: np.ndarray) -> None:
        rot, tr = pair_residuals(X, Ak, Bk)
        methods[name] = {
            "T_tool_cam": X,
            "rotation_residual_deg_rms": float(np.degrees(np.sqrt(np.mean(rot**2)))),
            "translation_residual_mm_rms": float(np.sqrt(np.mean(tr**2))),
            "board_consistency_mm": consistency_mm(X, T_base_tool, Tc, board),
        }

    X_ck = chou_kamel(Ak, Bk)
    record("chou_kamel", X_ck)
    for name in OPENCV_METHODS:
        try:
            record(name, opencv_handeye(T_base_tool, Tc, name))
        except cv2.error as exc:  # pragma: no cover - OpenCV failures are reported, not fatal
            methods[name] = {"error": str(exc).strip().splitlines()[-1]}
    # image noise from the single-view fits (6 pose parameters each), arm noise from X_ck
    n_obs = pts.shape[1] * 2
    # (rms_px is the RMS of 2-D residuals: per coordinate it is rms / sqrt 2)
    # the floors lie far below any real noise; they keep exact (synthetic) data well conditioned
    sigma_px = max(float(np.sqrt(np.mean([f.rms_px**2 for f in fits]) / 2 * n_obs / (n_obs - 6))),
                   SIGMA_FLOORS["image_px"])
    # the refinement starts from the algebraic solution the views agree with best
    algebraic = ["chou_kamel", *(m for m in OPENCV_METHODS if "T_tool_cam" in methods[m])]
    start = min(algebraic, key=lambda m: methods[m]["board_consistency_mm"])
    X_start = methods[start]["T_tool_cam"]
    s_mm, s_rad, Tbb0 = arm_noise_estimate(X_start, T_base_tool, Tc)
    s_mm, s_rad = max(s_mm, SIGMA_FLOORS["arm_mm"]), max(s_rad, SIGMA_FLOORS["arm_rad"])
    plain = refine_handeye(camera, board, pts, T_base_tool, X_start, Tbb0, bias_correction=bias_correction)
    record("reprojection", plain.X)
    methods["reprojection"]["reprojection_rms_px"] = plain.rms_px
    # the pose comparison charges the board poses' own error to the arm: the refinement
    # re-estimates all three sigmas from its residuals (variance components)
    ref = refine_handeye(camera, board, pts, T_base_tool, plain.X, plain.T_base_board, sigma_px=sigma_px,
                         arm_sigma_mm=s_mm, arm_sigma_rad=s_rad, bias_correction=bias_correction,
                         estimate_sigmas=True)
    X, Tbb, res = ref.X, ref.T_base_board, ref.residuals
    record("refined", X)
    methods["refined"]["reprojection_rms_px"] = ref.rms_px
    # what the noise allows: X's uncertainty at the boards' distance, on the optical axis
    z = float(np.median(Tc[:, 2, 3]))
    methods["refined"]["uncertainty"] = {
        "covariance_X": ref.covariance_X,
        "rotation_deg_1sigma": float(np.degrees(np.sqrt(np.trace(ref.covariance_X[:3, :3])))),
        "translation_mm_1sigma": float(np.sqrt(np.trace(ref.covariance_X[3:, 3:]))),
        "board_distance_mm": z,
        "point_mm_1sigma_at_board_distance": float(
            point_uncertainty(X, ref.covariance_X, np.array([[0.0, 0.0, z]]))[0]
        ),
    }
    methods["refined"]["noise_model"] = {
        "image_sigma_px": ref.sigmas["image_px"], "arm_sigma_mm": ref.sigmas["arm_mm"],
        "arm_sigma_rad": ref.sigmas["arm_rad"],
        "initial": {"image_sigma_px": sigma_px, "arm_sigma_mm": s_mm, "arm_sigma_rad": s_rad},
        "variance_factors": ref.variance_factors, "reweightings": ref.sigma_iterations,
        "arm_corrections_rms_mm": float(np.sqrt(np.mean(ref.arm_corrections[:, 3:] ** 2))),
        "arm_corrections_rms_rad": float(np.sqrt(np.mean(ref.arm_corrections[:, :3] ** 2))),
    }
    selection = select_estimate(methods, ref.covariance_X, T_base_tool, Tc, board)
    selection["refinement_start"] = start
    chosen = selection["method"]
    if chosen != "refined":
        log.warning("hand-eye: %s chosen over the refined X: its board consistency %.4f mm beats the "
                    "refined %.4f mm by more than X's uncertainty explains (%.4f mm^2 margin)",
                    chosen, methods[chosen]["board_consistency_mm"],
                    methods["refined"]["board_consistency_mm"], selection["margin_mm2"])
        X = methods[chosen]["T_tool_cam"]
    view_rms = np.sqrt(np.mean(np.sum(res**2, -1), -1))
    extra = {
        "methods": methods,
        "T_base_board": Tbb,
        "pairs": {
            "total": len(all_pairs),
            "used": int(keep.sum()),
            "rejected": int((~keep).sum()),
            "angle_tolerance_deg": float(np.degrees(tol)),
            "mismatch_k": mismatch_k,
            "mismatch_sigma_deg": float(np.degrees(sigma_m)),
            "mismatch_rms_deg": float(np.degrees(np.sqrt(np.mean((thA - thB) ** 2)))),
            "rejected_pairs": rejected,
            "rejected_views": rejected_views,
            **motion,
        },
        "board_poses": [
            {"image": n, "used": bool(use[k]), "T_cam_board": T,
             "labelling_turn_deg": float(np.degrees(np.arctan2(S[s][1, 0], S[s][0, 0]))),
             "pnp_rms_px": f.rms_px,
             "refined_rms_px": float(view_rms[int(np.searchsorted(u, k))]) if use[k] else None}
            for k, (n, T, s, f) in enumerate(zip(all_names, all_Tc, all_sym, all_fits, strict=True))
        ],
        "residuals": {n: r for n, r in zip(names, res, strict=True)},
        "reprojection_rms_px": methods["refined"]["reprojection_rms_px"],
        "selection": selection,
    }
    return HandEye(X, chosen, extra)


def select_estimate(
    methods: dict[str, dict[str, Any]], cov_X: np.ndarray, T_base_tool: np.ndarray,
    T_cam_board: np.ndarray, board: Board,
) -> dict[str, Any]:
    """The final method by board consistency on the views (module docstring, step 5).

    The refined X stays unless a method's squared consistency is lower than the refined's by
    more than :func:`consistency_margin` of the refined X's covariance; then the method with
    the best consistency wins. Returns the winner, the scores and the comparison with the best
    OpenCV method.
    """
    scores = {m: v["board_consistency_mm"] for m, v in methods.items() if "board_consistency_mm" in v}
    ref = scores["refined"]
    best = min(scores, key=scores.get)
    margin = consistency_margin(methods["refined"]["T_tool_cam"], cov_X, T_base_tool, T_cam_board, board)
    chosen = best if ref**2 - scores[best] ** 2 > margin["margin_mm2"] else "refined"
    opencv = [m for m in OPENCV_METHODS if m in scores]
    out: dict[str, Any] = {
        "method": chosen,
        "rule": "refined unless a method's squared board consistency is lower by more than the "
                f"{100 * SELECTION_QUANTILE:g} % quantile of what the refined X's covariance explains",
        "board_consistency_mm": {m: scores[m] for m in sorted(scores)},
        "best_consistency_method": best,
        "expected_excess_mm2": margin["expected_mm2"],
        "margin_mm2": margin["margin_mm2"],
        # the consistency the refined X may exceed the least-scatter one by, at its own level
        "margin_mm": float(np.sqrt(scores[best] ** 2 + margin["margin_mm2"]) - scores[best]),
    }
    if opencv:
        b = min(opencv, key=scores.get)
        c = scores[chosen]
        out.update(best_opencv=b, best_opencv_consistency_mm=scores[b],
                   vs_best_opencv_mm=c - scores[b], vs_best_opencv_percent=100.0 * (c / scores[b] - 1.0))
    return out


def run_calibrate_handeye(
    capture: str | Path,
    camera_json: str | Path,
    out: str | Path,
    *,
    mismatch_k: float = MISMATCH_K,
    threads: int = 1,
) -> HandEye:
    """Stage: solve X = T_tool_cam from ``calibration/handeye`` and write ``handeye.json``."""
    from crossline.calibrate.camera import detect_views
    from crossline.io.capture import open_capture

    cv2.setNumThreads(1)  # parallelism comes from our pool of `threads` workers (determinism)
    cap = open_capture(capture)
    camera = Camera.load(camera_json)
    board = cap.rig.board
    shape = (cap.rig.sensor.height, cap.rig.sensor.width)
    names = [str(p.relative_to(cap.root)) for p in cap.handeye_images]
    dets = detect_views(cap.handeye_images, board, shape, threads)
    skipped = []
    for n, d in zip(names, dets, strict=True):
        if not d.found:
            log.warning("%s: skipped: %s", n, d.reason)
            skipped.append({"image": n, "reason": d.reason})
    use = [k for k, d in enumerate(dets) if d.found]
    if len(use) < 3:
        lines = "\n".join(f"  - {s['image']}: {s['reason']}" for s in skipped)
        raise CalibrationError(
            f"capture {cap.root}: calibration/handeye: hand-eye calibration needs at least 3 views "
            f"with the board found, got {len(use)} of {len(names)}" + (f":\n{lines}" if lines else "")
        )
    try:
        he = solve_handeye(
            camera, board, np.array([dets[k].points for k in use]), cap.handeye_T_base_tool[use],
            [names[k] for k in use], mismatch_k=mismatch_k,
        )
    except CalibrationError as exc:
        # what the solver finds wrong is in the arm poses (degenerate motion) or in how they
        # match the views (rotation angles): the file that holds them is named
        raise CalibrationError(f"capture {cap.root}: calibration/handeye/poses.csv (the arm poses of "
                               f"{len(use)} views with the board found): {exc}") from None
    he.extra["skipped_views"] = skipped
    he.save(out)
    sel, pairs = he.extra["selection"], he.extra["pairs"]
    log.info("hand-eye: %d views, %d/%d pairs used (mismatch sigma %.4f deg, cut %.4f deg); "
             "reprojection RMS %.4f px; %s chosen, board consistency %.4f mm (best OpenCV: %s "
             "%.4f mm)", len(use), pairs["used"], pairs["total"], pairs["mismatch_sigma_deg"],
             pairs["angle_tolerance_deg"], he.extra["reprojection_rms_px"], he.method,
             sel["board_consistency_mm"][he.method], sel.get("best_opencv", "-"),
             sel.get("best_opencv_consistency_mm", float("nan")))
    return he

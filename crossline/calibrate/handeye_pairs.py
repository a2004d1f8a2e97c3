"""Which views and motion pairs a hand-eye solution can use (steps 1 and 2 of
:mod:`crossline.calibrate.handeye`'s docstring).

``symmetry_transforms`` and ``resolve_labellings`` choose each view's board labelling so that
all views agree on one board frame (boards that look the same turned in their plane);
``mismatch_sigma`` is the robust spread of the pairs' rotation-angle mismatch ``θA − θB`` that
the pairs are cut on (``MISMATCH_K`` sigmas by default); ``check_motion`` rejects motion whose
rotation axes cannot determine X. Split from ``crossline.calibrate.handeye`` (issue 21.3),
which re-exports these names.
"""

from __future__ import annotations

import numpy as np

from crossline.board import Board
from crossline.calibrate.detect import board_symmetries
from crossline.calibrate.handeye_solvers import chou_kamel, motion_pairs
from crossline.errors import CalibrationError
from crossline.geometry import (
    invert_transform,
    make_transform,
    matrix_to_rotvec,
    rotation_angle,
    rotvec_to_matrix,
    transform_points,
)
from crossline.robust import robust_sigma

__all__ = [
    "MISMATCH_K",
    "check_motion",
    "mismatch_sigma",
    "resolve_labellings",
    "symmetry_transforms",
]

MIN_PAIR_ROTATION_DEG = 1.0  # pairs rotating less say nothing about the rotation axis
MIN_AXIS_SPREAD_DEG = 5.0  # rotation axes must span at least this angle
MISMATCH_K = 4.0  # default cut on |theta_A - theta_B|, in robust sigmas of all pairs' mismatches
# floor of that sigma (rad): far below any real rotation noise, it keeps exact (synthetic)
# data, whose mismatches are rounding, from rejecting pairs on rounding
MISMATCH_SIGMA_FLOOR = 1e-9


def mismatch_sigma(theta_A: np.ndarray, theta_B: np.ndarray) -> float:
    """Robust standard deviation (rad) of the pairs' rotation-angle mismatch ``θA − θB``.

    The mismatch is zero for the right data, so its spread is taken about zero: 1.4826 times
    the median of ``|θA − θB|`` (the normal-consistent MAD), which a minority of wrong pairs
    (those of one bad view) cannot inflate much.
    """
    m = np.abs(np.asarray(theta_A, dtype=np.float64) - np.asarray(theta_B, dtype=np.float64))
    return max(robust_sigma(m, about=0.0), MISMATCH_SIGMA_FLOOR)


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

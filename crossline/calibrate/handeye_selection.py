"""Choosing the final hand-eye X on the views: board consistency and its margin.

Step 5 of :mod:`crossline.calibrate.handeye`'s docstring: every method is scored by
``consistency_mm`` (the scatter of the board's points in the base frame over the views);
``select_estimate`` keeps the refined X unless another method's consistency is better by more
than ``consistency_margin`` (what X's own covariance explains, at ``SELECTION_QUANTILE``).
Split from ``crossline.calibrate.handeye`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crossline.board import Board
from crossline.calibrate.handeye_refine import _delta
from crossline.calibrate.handeye_solvers import OPENCV_METHODS

__all__ = ["SELECTION_QUANTILE", "consistency_margin", "consistency_mm", "select_estimate"]

SELECTION_QUANTILE = 0.99  # of the consistency excess X's own uncertainty explains


def consistency_mm(X: np.ndarray, T_base_tool: np.ndarray, T_cam_board: np.ndarray, board: Board) -> float:
    """RMS scatter (mm) of the board's points in the base frame over the views, given X.

    Each view puts the board at ``T_base_tool_i X T_cam_board_i``; with the right X and exact
    data all views agree. Independent of truth, it scores every method alike.
    """
    P = board.object_points()
    T = T_base_tool @ X @ T_cam_board
    pts = np.einsum("vij,nj->vni", T[:, :3, :3], P) + T[:, None, :3, 3]
    return float(np.sqrt(np.mean(np.sum((pts - pts.mean(0)) ** 2, axis=-1))))


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

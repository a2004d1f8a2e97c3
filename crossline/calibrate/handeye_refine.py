"""Hand-eye refinement: X and ``T_base_board`` by reprojection, with the arm's noise modelled.

Step 4 of :mod:`crossline.calibrate.handeye`'s docstring: ``refine_handeye`` minimises the
reprojection error of every board point in every view, with the arm poses exact or, by
maximum likelihood, corrected against their standard deviations, which variance-component
estimation (Förstner) re-estimates from the residuals; ``arm_noise_estimate`` gives the arm's
starting sigmas from an algebraic X and ``point_uncertainty`` carries X's covariance to camera
points. Split from ``crossline.calibrate.handeye`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets
from crossline.calibrate.lm import dense_normal, levenberg_marquardt
from crossline.camera import Camera
from crossline.geometry import (
    invert_transform,
    make_transform,
    matrix_to_rotvec,
    orthonormalize,
    rotvec_to_matrix,
)

__all__ = ["SIGMA_FLOORS", "Refinement", "arm_noise_estimate", "point_uncertainty", "refine_handeye"]

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

"""The camera fit: Zhang's start, the float64 bundle adjustment, the bias iterations.

``calibrate_camera`` (the steps of :mod:`crossline.calibrate.camera`'s docstring, on one set
of views): ``_zhang`` initialises through ``cv2.calibrateCamera``, ``bundle_adjust`` refines
intrinsics, distortion and every view's pose by sparse Levenberg–Marquardt with the named
distortion coefficients held at 0, and the circle centres' perspective bias is taken out
iteratively; the result, a :class:`CameraFit`, also gives the intrinsics' covariance. Split
from ``crossline.calibrate.camera`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets
from crossline.calibrate.lm import levenberg_marquardt
from crossline.camera import CAMERA_PARAMETERS, Camera
from crossline.errors import CalibrationError
from crossline.geometry import make_transform, matrix_to_rotvec, rotvec_to_matrix

__all__ = ["DISTORTION", "PARAMETERS", "CameraFit", "bundle_adjust", "calibrate_camera"]

PARAMETERS = CAMERA_PARAMETERS
DISTORTION = PARAMETERS[4:]


@dataclass(frozen=True)
class CameraFit:
    """A calibrated camera and, per view, its board pose, bias offsets and residuals."""

    camera: Camera
    T_cam_board: np.ndarray  # (V, 4, 4)
    offsets: np.ndarray  # (V, N, 2) predicted perspective bias removed from the measurements
    residuals: np.ndarray  # (V, N, 2) corrected measurements minus projections
    bias_history: list[dict[str, float]] = field(default_factory=list)
    normal: np.ndarray | None = None  # JᵀJ of the last bundle adjustment (free intrinsics, 6 V)
    fixed: tuple[str, ...] = ()  # distortion coefficients held at 0 (names from PARAMETERS)
    reference: CameraFit | None = None  # the fit with every coefficient free, when some are fixed
    selection: list[dict[str, Any]] | None = None  # the candidate models (select_distortion)

    @property
    def free(self) -> np.ndarray:
        """Indices into PARAMETERS of the intrinsics the fit estimated."""
        return _free_indices(self.fixed)

    @property
    def sigma_px(self) -> float:
        """Residual standard deviation per image coordinate (px), degrees of freedom counted."""
        V, N = self.residuals.shape[:2]
        dof = 2 * V * N - (len(self.free) + 6 * V)
        return float(np.sqrt(np.sum(self.residuals**2) / max(dof, 1)))

    @property
    def covariance(self) -> np.ndarray:
        """Covariance (9, 9) of fx, fy, cx, cy, k1, k2, p1, p2, k3: sigma² (JᵀJ)⁻¹, poses
        marginalised; rows and columns of fixed coefficients are zero."""
        if self.normal is None:
            raise ValueError("no normal matrix: the fit did not come from bundle_adjust")
        fi = self.free
        C = np.zeros((9, 9))
        # inverted with Jacobi scaling: the parameters' units differ by many orders of magnitude
        A = self.normal
        d = 1.0 / np.sqrt(np.maximum(np.diag(A), 1e-300))
        inv = d[:, None] * np.linalg.pinv(d[:, None] * A * d[None, :], hermitian=True) * d[None, :]
        C[np.ix_(fi, fi)] = self.sigma_px**2 * inv[: fi.size, : fi.size]
        return C

    @property
    def view_rms(self) -> np.ndarray:
        """RMS residual (px) of every view."""
        return np.sqrt(np.mean(np.sum(self.residuals**2, axis=-1), axis=-1))

    @property
    def rms_px(self) -> float:
        """RMS residual (px) over all points of all views."""
        return float(np.sqrt(np.mean(np.sum(self.residuals**2, axis=-1))))


def _project_views(params: np.ndarray, P: np.ndarray, V: int, image_size) -> np.ndarray:
    fx, fy, cx, cy = params[:4]
    cam = Camera(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), params[4:9], image_size)
    ext = params[9:].reshape(V, 6)
    R = rotvec_to_matrix(ext[:, :3])
    pc = np.einsum("vij,nj->vni", R, P) + ext[:, None, 3:]
    return cam.project(pc)


def _free_indices(fixed: tuple[str, ...] | list[str]) -> np.ndarray:
    bad = set(fixed) - set(DISTORTION)
    if bad:
        raise ValueError(f"only distortion coefficients {DISTORTION} can be fixed, got {sorted(bad)}")
    return np.array([k for k, n in enumerate(PARAMETERS) if n not in fixed])


def bundle_adjust(
    board: Board,
    points: np.ndarray,
    camera: Camera,
    T_cam_board: np.ndarray,
    fixed: tuple[str, ...] = (),
) -> tuple[Camera, np.ndarray, np.ndarray, np.ndarray]:
    """Refine intrinsics, distortion and every view's pose (float64 LM) on points (V, N, 2).

    The distortion coefficients named in ``fixed`` are held at 0. Returns the camera, the
    poses (V, 4, 4), the residuals (V, N, 2) and JᵀJ at the solution (parameters: the free
    ones of fx, fy, cx, cy, k1, k2, p1, p2, k3 in that order, then 6 per view).
    """
    P = board.object_points()
    V, N = points.shape[:2]
    fi = _free_indices(fixed)
    nf = fi.size
    base = np.r_[camera.fx, camera.fy, camera.cx, camera.cy, camera.dist].astype(np.float64)
    base[[k for k in range(9) if k not in fi]] = 0.0
    x0 = np.concatenate(
        [
            base[fi],
            np.concatenate([np.r_[matrix_to_rotvec(T[:3, :3]), T[:3, 3]] for T in T_cam_board]),
        ]
    )
    obs = np.asarray(points, dtype=np.float64)

    def full(x: np.ndarray) -> np.ndarray:
        p = np.empty(9 + 6 * V)
        p[:9] = base
        p[fi] = x[:nf]
        p[9:] = x[nf:]
        return p

    def fun(x: np.ndarray) -> np.ndarray:
        return (_project_views(full(x), P, V, camera.image_size) - obs).ravel()

    steps = np.r_[np.r_[[1e-4] * 4, [1e-8] * 5][fi], [1e-8] * 3, [1e-6] * 3]

    def normal(x: np.ndarray, f0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # forward differences; a view's residuals depend on the shared intrinsics and its
        # own 6 only, so one pose parameter of every view is perturbed at once, and JᵀJ is
        # assembled from the blocks (the dense Jacobian would be mostly zeros)
        Ji = np.empty((V, 2 * N, nf))
        for k in range(nf):
            dx = np.zeros_like(x)
            dx[k] = steps[k]
            Ji[:, :, k] = ((fun(x + dx) - f0) / steps[k]).reshape(V, 2 * N)
        Jv = np.empty((V, 2 * N, 6))
        for m in range(6):
            dx = np.zeros_like(x)
            dx[nf + m :: 6] = steps[nf + m]
            Jv[:, :, m] = ((fun(x + dx) - f0) / steps[nf + m]).reshape(V, 2 * N)
        fv = f0.reshape(V, 2 * N)
        A = np.zeros((x.size, x.size))
        g = np.empty(x.size)
        A[:nf, :nf] = np.einsum("vri,vrj->ij", Ji, Ji)
        g[:nf] = np.einsum("vri,vr->i", Ji, fv)
        cross = np.einsum("vri,vrj->vij", Ji, Jv)  # (V, nf, 6)
        own = np.einsum("vri,vrj->vij", Jv, Jv)  # (V, 6, 6)
        gv = np.einsum("vri,vr->vi", Jv, fv)
        for v in range(V):
            sl = slice(nf + 6 * v, nf + 6 + 6 * v)
            A[:nf, sl] = cross[v]
            A[sl, :nf] = cross[v].T
            A[sl, sl] = own[v]
            g[sl] = gv[v]
        return A, g

    res = levenberg_marquardt(fun, normal, x0)
    x = full(res.x)
    cam = Camera(np.array([[x[0], 0, x[2]], [0, x[1], x[3]], [0, 0, 1.0]]), x[4:9], camera.image_size)
    ext = x[9:].reshape(V, 6)
    T = make_transform(rotvec_to_matrix(ext[:, :3]), ext[:, 3:])
    return cam, T, res.fun.reshape(V, N, 2), res.normal


def _zhang(
    board: Board, points: np.ndarray, image_size, fixed: tuple[str, ...] = ()
) -> tuple[Camera, np.ndarray]:
    """Zhang's method through ``cv2.calibrateCamera`` (5 coefficients, zero skew)."""
    obj = [board.object_points().astype(np.float32)] * len(points)
    img = [p.astype(np.float32) for p in points]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    flags = 0
    for name, flag in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2), ("k3", cv2.CALIB_FIX_K3)):
        if name in fixed:
            flags |= flag
    if "p1" in fixed and "p2" in fixed:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    _, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(image_size), None, None, flags=flags,
                                                   criteria=crit)
    T = make_transform(rotvec_to_matrix(np.array(rvecs).reshape(-1, 3)), np.array(tvecs).reshape(-1, 3))
    return Camera(K, dist.ravel()[:5], image_size), T


def calibrate_camera(
    points: np.ndarray,
    board: Board,
    image_size: tuple[int, int],
    *,
    bias_correction: bool = True,
    fixed: tuple[str, ...] = (),
    start: CameraFit | None = None,
    max_iterations: int = 10,
    bias_tol_px: float = 1e-6,
) -> CameraFit:
    """Calibrate from measured points (V, N, 2) in board order; see the module docstring.

    ``fixed`` names distortion coefficients held at 0. ``start``, a fit of the same points,
    replaces Zhang's initialisation: its camera (fixed coefficients zeroed), poses and bias
    offsets are where the bundle adjustment and the bias iterations start.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 3:
        raise CalibrationError(f"camera calibration needs at least 3 views, got {len(pts)}")
    fixed = tuple(n for n in DISTORTION if n in fixed)
    if start is None:
        cam, T = _zhang(board, pts, image_size, fixed)
        offsets = np.zeros_like(pts)
        history: list[dict[str, float]] = []
    else:
        cam, T, offsets = start.camera, start.T_cam_board, start.offsets
        history = [dict(h) for h in start.bias_history]
    cam, T, res, A = bundle_adjust(board, pts - offsets, cam, T, fixed)

    def record(it: int, change: float) -> None:
        history.append({"iteration": it, "rms_px": float(np.sqrt(np.mean(np.sum(res**2, -1)))),
                        "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "change_px": change,
                        "fixed": ",".join(fixed)})

    it0 = int(history[-1]["iteration"]) + 1 if history else 0
    record(it0, 0.0)
    if bias_correction and board.pattern != "chessboard":
        for it in range(it0 + 1, it0 + max_iterations + 1):
            new = np.array([
                centroid_offsets(cam, board, matrix_to_rotvec(Tv[:3, :3]), Tv[:3, 3]) for Tv in T
            ])
            change = float(np.abs(new - offsets).max())
            offsets = new
            cam, T, res, A = bundle_adjust(board, pts - offsets, cam, T, fixed)
            record(it, change)
            if change < bias_tol_px:
                break
    return CameraFit(cam, T, offsets, res, history, A, fixed)

"""Camera calibration: intrinsics and 5-coefficient distortion from board views (Zhang).

Steps: detect the board in every view (:mod:`crossline.calibrate.detect`), initialise with
``cv2.calibrateCamera`` (Zhang's method, OpenCV's 5-coefficient model, zero skew), then polish
all parameters in float64 by a sparse Levenberg–Marquardt bundle adjustment (OpenCV works on
float32 points, which leaves ~1e-4 px of rounding). With bias correction the circle centres
are corrected iteratively: calibrate, predict for each circle the offset of its imaged area
centroid from the projection of its centre (:mod:`crossline.calibrate.bias`), subtract it
from the measured centroids, calibrate again, until the offsets change by < ``bias_tol_px``.

Views where the board is not found, or whose RMS residual exceeds ``outlier_factor`` times
the median (and an absolute floor of ``OUTLIER_FLOOR_PX``), are skipped and listed with
their reason; fewer than ``min_views`` usable views is a :class:`CalibrationError` that
names every view and why it was or was not used.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets
from crossline.calibrate.detect import Detection, detect_board
from crossline.calibrate.lm import levenberg_marquardt
from crossline.camera import Camera
from crossline.errors import CalibrationError
from crossline.geometry import make_transform, matrix_to_rotvec, rotvec_to_matrix

__all__ = [
    "OUTLIER_FLOOR_PX",
    "PARAMETERS",
    "VIEW_SETS",
    "CameraFit",
    "bundle_adjust",
    "calibrate_camera",
    "detect_views",
    "grid_pixels",
    "projection_uncertainty",
    "run_calibrate_camera",
    "uncertainty_summary",
]

log = logging.getLogger(__name__)

# a view is never an outlier below this RMS (px): exact or very clean data has tiny medians
OUTLIER_FLOOR_PX = 0.02
VIEW_SETS = ("camera", "all")


@dataclass(frozen=True)
class CameraFit:
    """A calibrated camera and, per view, its board pose, bias offsets and residuals."""

    camera: Camera
    T_cam_board: np.ndarray  # (V, 4, 4)
    offsets: np.ndarray  # (V, N, 2) predicted perspective bias removed from the measurements
    residuals: np.ndarray  # (V, N, 2) corrected measurements minus projections
    bias_history: list[dict[str, float]] = field(default_factory=list)
    normal: np.ndarray | None = None  # JᵀJ of the last bundle adjustment (9 + 6 V parameters)

    @property
    def sigma_px(self) -> float:
        """Residual standard deviation per image coordinate (px), degrees of freedom counted."""
        V, N = self.residuals.shape[:2]
        dof = 2 * V * N - (9 + 6 * V)
        return float(np.sqrt(np.sum(self.residuals**2) / max(dof, 1)))

    @property
    def covariance(self) -> np.ndarray:
        """Covariance (9, 9) of fx, fy, cx, cy, k1, k2, p1, p2, k3: sigma² (JᵀJ)⁻¹, poses marginalised."""
        if self.normal is None:
            raise ValueError("no normal matrix: the fit did not come from bundle_adjust")
        return self.sigma_px**2 * np.linalg.inv(self.normal)[:9, :9]

    @property
    def view_rms(self) -> np.ndarray:
        """RMS residual (px) of every view."""
        return np.sqrt(np.mean(np.sum(self.residuals**2, axis=-1), axis=-1))

    @property
    def rms_px(self) -> float:
        """RMS residual (px) over all points of all views."""
        return float(np.sqrt(np.mean(np.sum(self.residuals**2, axis=-1))))


# ----------------------------------------------------------------------------- solver


def _project_views(params: np.ndarray, P: np.ndarray, V: int, image_size) -> np.ndarray:
    fx, fy, cx, cy = params[:4]
    cam = Camera(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), params[4:9], image_size)
    ext = params[9:].reshape(V, 6)
    R = rotvec_to_matrix(ext[:, :3])
    pc = np.einsum("vij,nj->vni", R, P) + ext[:, None, 3:]
    return cam.project(pc)


def bundle_adjust(
    board: Board,
    points: np.ndarray,
    camera: Camera,
    T_cam_board: np.ndarray,
) -> tuple[Camera, np.ndarray, np.ndarray, np.ndarray]:
    """Refine intrinsics, distortion and every view's pose (float64 LM) on points (V, N, 2).

    Returns the camera, the poses (V, 4, 4), the residuals (V, N, 2) and JᵀJ at the solution
    (parameters fx, fy, cx, cy, the 5 distortion coefficients, then 6 per view).
    """
    P = board.object_points()
    V, N = points.shape[:2]
    x0 = np.concatenate(
        [
            [camera.fx, camera.fy, camera.cx, camera.cy],
            camera.dist,
            np.concatenate([np.r_[matrix_to_rotvec(T[:3, :3]), T[:3, 3]] for T in T_cam_board]),
        ]
    )
    obs = np.asarray(points, dtype=np.float64)

    def fun(x: np.ndarray) -> np.ndarray:
        return (_project_views(x, P, V, camera.image_size) - obs).ravel()

    steps = np.r_[[1e-4] * 4, [1e-8] * 5, [1e-8] * 3, [1e-6] * 3]

    def normal(x: np.ndarray, f0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # forward differences; a view's residuals depend on the 9 shared parameters and its
        # own 6 only, so one pose parameter of every view is perturbed at once, and JᵀJ is
        # assembled from the blocks (the dense Jacobian would be mostly zeros)
        Ji = np.empty((V, 2 * N, 9))
        for k in range(9):
            dx = np.zeros_like(x)
            dx[k] = steps[k]
            Ji[:, :, k] = ((fun(x + dx) - f0) / steps[k]).reshape(V, 2 * N)
        Jv = np.empty((V, 2 * N, 6))
        for m in range(6):
            dx = np.zeros_like(x)
            dx[9 + m :: 6] = steps[9 + m]
            Jv[:, :, m] = ((fun(x + dx) - f0) / steps[9 + m]).reshape(V, 2 * N)
        fv = f0.reshape(V, 2 * N)
        A = np.zeros((x.size, x.size))
        g = np.empty(x.size)
        A[:9, :9] = np.einsum("vri,vrj->ij", Ji, Ji)
        g[:9] = np.einsum("vri,vr->i", Ji, fv)
        cross = np.einsum("vri,vrj->vij", Ji, Jv)  # (V, 9, 6)
        own = np.einsum("vri,vrj->vij", Jv, Jv)  # (V, 6, 6)
        gv = np.einsum("vri,vr->vi", Jv, fv)
        for v in range(V):
            sl = slice(9 + 6 * v, 15 + 6 * v)
            A[:9, sl] = cross[v]
            A[sl, :9] = cross[v].T
            A[sl, sl] = own[v]
            g[sl] = gv[v]
        return A, g

    res = levenberg_marquardt(fun, normal, x0)
    x = res.x
    cam = Camera(np.array([[x[0], 0, x[2]], [0, x[1], x[3]], [0, 0, 1.0]]), x[4:9], camera.image_size)
    ext = x[9:].reshape(V, 6)
    T = make_transform(rotvec_to_matrix(ext[:, :3]), ext[:, 3:])
    return cam, T, res.fun.reshape(V, N, 2), res.normal


def _zhang(board: Board, points: np.ndarray, image_size) -> tuple[Camera, np.ndarray]:
    """Zhang's method through ``cv2.calibrateCamera`` (5 coefficients, zero skew)."""
    obj = [board.object_points().astype(np.float32)] * len(points)
    img = [p.astype(np.float32) for p in points]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    _, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(image_size), None, None, criteria=crit)
    T = make_transform(rotvec_to_matrix(np.array(rvecs).reshape(-1, 3)), np.array(tvecs).reshape(-1, 3))
    return Camera(K, dist.ravel()[:5], image_size), T


def calibrate_camera(
    points: np.ndarray,
    board: Board,
    image_size: tuple[int, int],
    *,
    bias_correction: bool = True,
    max_iterations: int = 10,
    bias_tol_px: float = 1e-6,
) -> CameraFit:
    """Calibrate from measured points (V, N, 2) in board order; see the module docstring."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 3:
        raise CalibrationError(f"camera calibration needs at least 3 views, got {len(pts)}")
    cam, T = _zhang(board, pts, image_size)
    cam, T, res, A = bundle_adjust(board, pts, cam, T)
    offsets = np.zeros_like(pts)
    history = [{"iteration": 0, "rms_px": float(np.sqrt(np.mean(np.sum(res**2, -1)))),
                "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "change_px": 0.0}]
    if bias_correction and board.pattern != "chessboard":
        for it in range(1, max_iterations + 1):
            new = np.array([
                centroid_offsets(cam, board, matrix_to_rotvec(Tv[:3, :3]), Tv[:3, 3]) for Tv in T
            ])
            change = float(np.abs(new - offsets).max())
            offsets = new
            cam, T, res, A = bundle_adjust(board, pts - offsets, cam, T)
            history.append({"iteration": it, "rms_px": float(np.sqrt(np.mean(np.sum(res**2, -1)))),
                            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                            "change_px": change})
            if change < bias_tol_px:
                break
    return CameraFit(cam, T, offsets, res, history, A)


PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def grid_pixels(window: tuple[int, int, int, int], n: int = 21) -> np.ndarray:
    """An n x n grid of pixels (M, 2) spanning a window (x, y, width, height), edges included."""
    x, y, w, h = window
    u, v = np.meshgrid(np.linspace(x, x + w - 1, n), np.linspace(y, y + h - 1, n))
    return np.column_stack([u.ravel(), v.ravel()])


def projection_uncertainty(camera: Camera, covariance: np.ndarray, pixels: np.ndarray) -> float:
    """Predicted RMS (px, 1 sigma) of the projection error at ``pixels`` from the covariance
    (9, 9) of the intrinsics and distortion: how far points seen there are projected (and
    their rays cast) from where the true camera would put them."""
    xy = camera.undistort(np.asarray(pixels, dtype=np.float64))
    Q = np.column_stack([xy, np.ones(len(xy))])
    x0 = np.r_[camera.fx, camera.fy, camera.cx, camera.cy, camera.dist]
    J = np.empty((len(Q), 2, 9))
    for k in range(9):
        h = 1e-5 * max(1.0, abs(x0[k]))
        proj = []
        for sgn in (1.0, -1.0):
            p = x0.copy()
            p[k] += sgn * h
            K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
            proj.append(Camera(K, p[4:9], camera.image_size).project(Q))
        J[:, :, k] = (proj[0] - proj[1]) / (2 * h)
    var = np.einsum("nik,kl,nil->n", J, covariance, J)
    return float(np.sqrt(np.mean(var)))


def uncertainty_summary(fit: CameraFit, windows: dict[str, tuple[int, int, int, int]]) -> dict[str, Any]:
    """The fit's standard deviations and its predicted projection error over each window."""
    C = fit.covariance
    return {
        "sigma_px": fit.sigma_px,
        "std": dict(zip(PARAMETERS, np.sqrt(np.diag(C)).tolist(), strict=True)),
        "covariance": C,
        "projection_rms_px": {name: projection_uncertainty(fit.camera, C, grid_pixels(win))
                              for name, win in windows.items()},
        "note": "1 sigma, from the residuals and the Jacobian of the final bundle adjustment; "
                "projection error RMS over a 21 x 21 grid of each window",
    }


# ----------------------------------------------------------------------------- stage


def detect_views(
    paths: list[Path], board: Board, shape: tuple[int, int], threads: int = 1
) -> list[Detection]:
    """Board detections for image files, in order (read and detected in ``threads`` threads)."""
    from crossline.io.images import read_image

    def one(p: Path) -> Detection:
        return detect_board(read_image(p, shape), board)

    if threads <= 1:
        return [one(p) for p in paths]
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(pool.map(one, paths))


def _view_table(names: list[str], reasons: dict[str, str], rms: dict[str, float]) -> list[dict[str, Any]]:
    return [
        {"image": n, "used": n not in reasons, "reason": reasons.get(n, ""), "rms_px": rms.get(n)}
        for n in names
    ]


def _too_few(views: list[dict[str, Any]], min_views: int) -> CalibrationError:
    used = sum(v["used"] for v in views)
    lines = "\n".join(
        f"  - {v['image']}: " + ("used" + (f" (RMS {v['rms_px']:.3f} px)" if v["rms_px"] is not None else "")
                                  if v["used"] else v["reason"])
        for v in views
    )
    return CalibrationError(
        f"camera calibration needs at least {min_views} usable views, got {used} of {len(views)}:\n{lines}"
    )


def solve_views(
    names: list[str],
    detections: list[Detection],
    board: Board,
    image_size: tuple[int, int],
    *,
    bias_correction: bool = True,
    outlier_factor: float = 3.0,
    min_views: int = 6,
) -> tuple[CameraFit, list[str], list[dict[str, Any]]]:
    """Calibrate from detections, skipping views not found and RMS outliers.

    Returns the fit, the names of the views it used (in order) and the table of all views.
    """
    reasons: dict[str, str] = {}
    rms: dict[str, float] = {}
    for n, d in zip(names, detections, strict=True):
        if not d.found:
            reasons[n] = d.reason
            log.warning("%s: skipped: %s", n, d.reason)
    for _ in range(len(names)):
        use = [i for i, n in enumerate(names) if n not in reasons]
        if len(use) < max(min_views, 3):
            raise _too_few(_view_table(names, reasons, rms), min_views)
        fit = calibrate_camera(
            np.array([detections[i].points for i in use]), board, image_size,
            bias_correction=bias_correction,
        )
        vr = fit.view_rms
        rms.update({names[i]: float(r) for i, r in zip(use, vr, strict=True)})
        limit = max(outlier_factor * float(np.median(vr)), OUTLIER_FLOOR_PX)
        worst = int(np.argmax(vr))
        if vr[worst] <= limit:
            return fit, [names[i] for i in use], _view_table(names, reasons, rms)
        # drop the worst view only: one bad view inflates the others' residuals too
        n = names[use[worst]]
        reasons[n] = (f"RMS residual {vr[worst]:.3f} px is an outlier (> {outlier_factor:g} x median "
                      f"{np.median(vr):.3f} px)")
        log.warning("%s: skipped: %s", n, reasons[n])
    raise _too_few(_view_table(names, reasons, rms), min_views)  # pragma: no cover


def run_calibrate_camera(
    capture: str | Path,
    out: str | Path,
    *,
    bias_correction: bool = True,
    outlier_factor: float = 3.0,
    min_views: int = 6,
    threads: int = 1,
    views: str = "all",
) -> Camera:
    """Stage: calibrate the camera from the board views and write ``camera.json``.

    ``views="camera"`` uses ``calibration/camera/*.png`` only; ``"all"`` (default) adds every
    other lasers-off board view of the capture (``laser_*/<pose>_board.png`` and
    ``handeye/*.png``): same camera, same board, and the intrinsics' precision grows with the
    number of views (the principal point above all).
    """
    from crossline.io.capture import open_capture

    if views not in VIEW_SETS:
        raise ValueError(f"views must be one of {VIEW_SETS}, got {views!r}")
    cv2.setNumThreads(1)  # parallelism comes from our pool of `threads` workers (determinism)
    cap = open_capture(capture)
    board = cap.rig.board
    size = (cap.rig.sensor.width, cap.rig.sensor.height)
    paths = list(cap.camera_images)
    if views == "all":
        paths += [v.board_image for laser in sorted(cap.laser_views) for v in cap.laser_views[laser]]
        paths += list(cap.handeye_images)
    names = [str(p.relative_to(cap.root)) for p in paths]
    detections = detect_views(paths, board, (size[1], size[0]), threads)
    fit, used, table = solve_views(
        names, detections, board, size, bias_correction=bias_correction,
        outlier_factor=outlier_factor, min_views=min_views,
    )
    cam = fit.camera
    last = fit.bias_history[-1]
    extra: dict[str, Any] = {
        "model": "pinhole + OpenCV 5-coefficient distortion (k1, k2, p1, p2, k3)",
        "rms_px": fit.rms_px,
        "n_views_used": len(used),
        "views": table,
        "residuals": {n: fit.residuals[k] for k, n in enumerate(used)},
        "T_cam_board": {n: fit.T_cam_board[k] for k, n in enumerate(used)},
        "bias_correction": {
            "enabled": bool(bias_correction and board.pattern != "chessboard"),
            "iterations": int(last["iteration"]),
            "mean_shift_px": float(np.mean(np.linalg.norm(fit.offsets, axis=-1))),
            "max_shift_px": float(np.max(np.linalg.norm(fit.offsets, axis=-1))),
            "history": fit.bias_history,
        },
        "board": board.to_dict(),
        "view_set": views,
        "uncertainty": uncertainty_summary(fit, {"sensor": (0, 0, *size), "scan_window": (
            cap.rig.scan_window.x, cap.rig.scan_window.y, cap.rig.scan_window.width,
            cap.rig.scan_window.height)}),
    }
    cam = Camera(cam.K, cam.dist, cam.image_size, extra)
    cam.save(out)
    log.info("camera: %d of %d views used, RMS %.4f px, fx %.3f fy %.3f cx %.3f cy %.3f",
             len(used), len(names), fit.rms_px, cam.fx, cam.fy, cam.cx, cam.cy)
    u = extra["uncertainty"]
    log.info("camera: predicted projection error (1 sigma RMS) %.4f px over the sensor, %.4f px over "
             "the scan window; std cx %.4f px, cy %.4f px", u["projection_rms_px"]["sensor"],
             u["projection_rms_px"]["scan_window"], u["std"]["cx"], u["std"]["cy"])
    return cam

"""Camera calibration: intrinsics and 5-coefficient distortion from board views (Zhang).

Steps: detect the board in every view (:mod:`crossline.calibrate.detect`), initialise with
``cv2.calibrateCamera`` (Zhang's method, OpenCV's 5-coefficient model, zero skew), then polish
all parameters in float64 by a sparse Levenberg–Marquardt bundle adjustment (OpenCV works on
float32 points, which leaves ~1e-4 px of rounding). With bias correction the circle centres
are corrected iteratively: calibrate, predict for each circle the offset of its imaged area
centroid from the projection of its centre (:mod:`crossline.calibrate.bias`), subtract it
from the measured centroids, calibrate again, until the offsets change by < ``bias_tol_px``.

Distortion model. With few views, or views that leave the sensor's edges bare, a coefficient
(k3 first, the term of highest order) may not be determined by the data: free, it makes the
predicted projection error meaningless (tens of pixels at the corners). Such coefficients are
fixed at 0 by model selection (:func:`select_distortion`): the radial models with k3, then k2
and k3 held at 0 are fitted too, and the one with the lowest predicted projection error over
the scan window wins, counting both its noise and the model error that fixing leaves
(:func:`model_error`). camera.json says which coefficients were fixed and why, and its
predicted error includes that model error.

Views where the board is not found, or whose RMS residual exceeds ``outlier_factor`` times
the median (and an absolute floor of ``OUTLIER_FLOOR_PX``), are skipped and listed with
their reason; fewer than ``min_views`` usable views is a :class:`CalibrationError` that
names every view and why it was or was not used.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.bias import centroid_offsets
from crossline.calibrate.detect import Detection, detect_board
from crossline.calibrate.lm import levenberg_marquardt
from crossline.camera import CAMERA_PARAMETERS, Camera
from crossline.errors import CalibrationError
from crossline.geometry import make_transform, matrix_to_rotvec, rotvec_to_matrix

__all__ = [
    "DISTORTION",
    "DISTORTION_CHOICES",
    "DISTORTION_MODELS",
    "OUTLIER_FLOOR_PX",
    "PARAMETERS",
    "VIEW_SETS",
    "CameraFit",
    "bundle_adjust",
    "calibrate_camera",
    "detect_views",
    "grid_pixels",
    "model_error",
    "projection_uncertainty",
    "projection_variance",
    "run_calibrate_camera",
    "select_distortion",
    "solve_views",
    "uncertainty_summary",
]

log = logging.getLogger(__name__)

# a view is never an outlier below this RMS (px): exact or very clean data has tiny medians
OUTLIER_FLOOR_PX = 0.02
MAX_RMS_PX = 2.0  # reprojection RMS above which the views fit no camera: a wrong board, not a lens
VIEW_SETS = ("camera", "all")
PARAMETERS = CAMERA_PARAMETERS
DISTORTION = PARAMETERS[4:]
# candidate distortion models, as the coefficients each holds at 0 (the first: all free): the
# radial terms of highest order go first, as they need the widest field to be seen; the
# tangential pair stays free (fixing it moves the principal point, never a small change)
DISTORTION_MODELS: tuple[tuple[str, ...], ...] = ((), ("k3",), ("k2", "k3"))
DISTORTION_CHOICES = ("select", "full")


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


# ----------------------------------------------------------------------------- solver


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


def grid_pixels(window: tuple[int, int, int, int], n: int = 21) -> np.ndarray:
    """An n x n grid of pixels (M, 2) spanning a window (x, y, width, height), edges included."""
    x, y, w, h = window
    u, v = np.meshgrid(np.linspace(x, x + w - 1, n), np.linspace(y, y + h - 1, n))
    return np.column_stack([u.ravel(), v.ravel()])


def _directions(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    xy = camera.undistort(np.asarray(pixels, dtype=np.float64))
    return np.column_stack([xy, np.ones(len(xy))])


def projection_variance(camera: Camera, covariance: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Predicted variance (M,) px² (sum over u and v) of the projection error at each pixel
    from the covariance (9, 9) of the intrinsics and distortion."""
    Q = _directions(camera, pixels)
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
    return np.einsum("nik,kl,nil->n", J, covariance, J)


def projection_uncertainty(camera: Camera, covariance: np.ndarray, pixels: np.ndarray) -> float:
    """Predicted RMS (px, 1 sigma) of the projection error at ``pixels`` from the covariance
    (9, 9) of the intrinsics and distortion: how far points seen there are projected (and
    their rays cast) from where the true camera would put them."""
    return float(np.sqrt(np.mean(projection_variance(camera, covariance, pixels))))


def model_error(fit: CameraFit, reference: CameraFit, pixels: np.ndarray) -> dict[str, float]:
    """Predicted projection error (px RMS over ``pixels``) of a fit with coefficients fixed,
    as noise and model error, against ``reference``, the fit of the same points with all
    coefficients free (taken as unbiased).

    The noise part comes from the fit's own covariance. The model part is the bias that
    fixing coefficients at 0 leaves: the squared difference between the two fits'
    projections, less what the noise alone puts into that difference (for nested least
    squares, var(reference - fit) = var(reference) - var(fit)), clipped at 0. Their sum is
    an estimate of the fit's mean squared error (Mallows' Cp, in the units that matter), and
    for ``reference`` itself it is its variance.
    """
    var = float(np.mean(projection_variance(fit.camera, fit.covariance, pixels)))
    var_ref = float(np.mean(projection_variance(reference.camera, reference.covariance, pixels)))
    Q = _directions(reference.camera, pixels)
    d2 = float(np.mean(np.sum((fit.camera.project(Q) - reference.camera.project(Q)) ** 2, axis=1)))
    bias2 = max(d2 - max(var_ref - var, 0.0), 0.0) if fit.fixed else 0.0
    return {"noise_px": float(np.sqrt(var)), "model_px": float(np.sqrt(bias2)),
            "difference_px": float(np.sqrt(d2)), "reference_noise_px": float(np.sqrt(var_ref)),
            "total_px": float(np.sqrt(var + bias2))}


def select_distortion(
    points: np.ndarray,
    board: Board,
    image_size: tuple[int, int],
    full: CameraFit,
    window: tuple[int, int, int, int],
    *,
    bias_correction: bool = True,
    models: tuple[tuple[str, ...], ...] | None = None,
) -> tuple[CameraFit, list[dict[str, Any]]]:
    """The distortion model (which coefficients to fix at 0) with the lowest predicted
    projection error over ``window``, and the table of every candidate.

    ``full`` is the fit of ``points`` with all five coefficients free. A coefficient the views
    do not determine (k3 when no board reaches the sensor's edges, say) inflates the free
    fit's variance far more than fixing it costs in model error (:func:`model_error`): then
    fixing it wins. Where the views determine every coefficient, the model error of any
    fixed set exceeds its saving in noise and the free fit stays. Candidates are fitted from
    ``full`` with its bias offsets; the winner's bias iterations are then run to the end.
    """
    pix = grid_pixels(window)
    rows: list[dict[str, Any]] = []
    fits: list[CameraFit] = []
    for fixed in models or DISTORTION_MODELS:
        fit = full if not fixed else calibrate_camera(
            points, board, image_size, bias_correction=bias_correction, fixed=fixed, start=full,
            max_iterations=0)
        fits.append(fit)
        rows.append({"fixed": list(fit.fixed), "free": [n for n in DISTORTION if n not in fit.fixed],
                     "rms_px": fit.rms_px, **model_error(fit, full, pix)})
    best = min(range(len(rows)), key=lambda k: (rows[k]["total_px"], -len(rows[k]["fixed"])))
    for k, r in enumerate(rows):
        r["chosen"] = k == best
    chosen = fits[best]
    if chosen.fixed and bias_correction and board.pattern != "chessboard":
        chosen = calibrate_camera(points, board, image_size, bias_correction=True, fixed=chosen.fixed,
                                  start=chosen)
    return replace(chosen, reference=full, selection=rows), rows


def uncertainty_summary(fit: CameraFit, windows: dict[str, tuple[int, int, int, int]]) -> dict[str, Any]:
    """The fit's standard deviations and its predicted projection error over each window
    (noise and, where coefficients were fixed, model error: :func:`model_error`)."""
    C = fit.covariance
    ref = fit.reference or fit
    parts = {name: model_error(fit, ref, grid_pixels(win)) for name, win in windows.items()}
    return {
        "sigma_px": fit.sigma_px,
        "std": dict(zip(PARAMETERS, np.sqrt(np.diag(C)).tolist(), strict=True)),
        "covariance": C,
        "projection_rms_px": {name: e["total_px"] for name, e in parts.items()},
        "projection_noise_px": {name: e["noise_px"] for name, e in parts.items()},
        "projection_model_px": {name: e["model_px"] for name, e in parts.items()},
        "note": "1 sigma, from the residuals and the Jacobian of the final bundle adjustment, plus "
                "(where distortion coefficients were fixed at 0) the model error that fixing them "
                "leaves, estimated against the fit with all of them free; projection error RMS over "
                "a 21 x 21 grid of each window",
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
    distortion: str = "select",
    window: tuple[int, int, int, int] | None = None,
) -> tuple[CameraFit, list[str], list[dict[str, Any]]]:
    """Calibrate from detections, skipping views not found and RMS outliers.

    ``distortion="select"`` then fixes at 0 the coefficients the views do not determine
    (:func:`select_distortion`, judged over ``window``, by default the whole sensor);
    ``"full"`` keeps all five free. Returns the fit, the names of the views it used (in
    order) and the table of all views.
    """
    if distortion not in DISTORTION_CHOICES:
        raise ValueError(f"distortion must be one of {DISTORTION_CHOICES}, got {distortion!r}")
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
            if not fit.rms_px <= MAX_RMS_PX:  # every view equally bad: the board, not a view
                raise CalibrationError(
                    f"the board's points fit no camera: RMS {fit.rms_px:.2f} px over {len(use)} "
                    f"views (a sound calibration leaves well under 1 px; refused above "
                    f"{MAX_RMS_PX:g} px). Check that rig.yaml's board ({board.pattern} "
                    f"{board.cols} x {board.rows}, spacing {board.spacing:g} mm) is the board in "
                    f"the images")
            if distortion == "select":
                pts = np.array([detections[i].points for i in use])
                fit, _ = select_distortion(pts, board, image_size, fit, window or (0, 0, *image_size),
                                           bias_correction=bias_correction)
                rms.update({names[i]: float(r) for i, r in zip(use, fit.view_rms, strict=True)})
            return fit, [names[i] for i in use], _view_table(names, reasons, rms)
        # drop the worst view only: one bad view inflates the others' residuals too
        n = names[use[worst]]
        reasons[n] = (f"RMS residual {vr[worst]:.3f} px is an outlier (> {outlier_factor:g} x median "
                      f"{np.median(vr):.3f} px)")
        log.warning("%s: skipped: %s", n, reasons[n])
    raise _too_few(_view_table(names, reasons, rms), min_views)  # pragma: no cover


def _model_record(fit: CameraFit, distortion: str) -> dict[str, Any]:
    """camera.json's account of which distortion coefficients were estimated, and why."""
    rec: dict[str, Any] = {
        "selection": distortion,
        "free": [n for n in DISTORTION if n not in fit.fixed],
        "fixed": {n: 0.0 for n in fit.fixed},
    }
    if distortion == "full":
        rec["reason"] = "all five coefficients estimated (distortion: full, no model selection)"
        return rec
    rows = fit.selection or []
    full = next((r for r in rows if not r["fixed"]), None)
    mine = next((r for r in rows if r["chosen"]), None)
    if fit.fixed and full is not None and mine is not None:
        rec["reason"] = (
            f"{', '.join(fit.fixed)} fixed at 0: the views do not determine "
            f"{'it' if len(fit.fixed) == 1 else 'them'}; over the scan window the fit with all "
            f"coefficients free predicts {full['total_px']:.4f} px RMS projection error (noise), "
            f"this model {mine['total_px']:.4f} px (noise {mine['noise_px']:.4f} px, model error "
            f"{mine['model_px']:.4f} px), the lowest of {len(rows)} candidate models")
    else:
        rec["reason"] = ("all five coefficients estimated: fixing any of them at 0 costs more model "
                         "error over the scan window than it saves in noise")
    rec["criterion"] = ("predicted projection error over the scan window (px RMS, 1 sigma): noise "
                        "from the fit's covariance plus the model error of fixing coefficients, "
                        "estimated against the fit with all of them free")
    rec["candidates"] = rows
    return rec


def run_calibrate_camera(
    capture: str | Path,
    out: str | Path,
    *,
    bias_correction: bool = True,
    outlier_factor: float = 3.0,
    min_views: int = 6,
    threads: int = 1,
    views: str = "all",
    distortion: str = "select",
) -> Camera:
    """Stage: calibrate the camera from the board views and write ``camera.json``.

    ``views="camera"`` uses ``calibration/camera/*.png`` only; ``"all"`` (default) adds every
    other lasers-off board view of the capture (``laser_*/<pose>_board.png`` where it exists, and
    ``handeye/*.png``): same camera, same board, and the intrinsics' precision grows with the
    number of views (the principal point above all). ``distortion``: see :func:`solve_views`
    (the model is judged over the scan window, where the scanner measures).
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
        # a laser pose taken with the laser always on has no lasers-off board view to add
        paths += [v.board_image for laser in sorted(cap.laser_views) for v in cap.laser_views[laser]
                  if v.board_image is not None]
        paths += list(cap.handeye_images)
    names = [str(p.relative_to(cap.root)) for p in paths]
    detections = detect_views(paths, board, (size[1], size[0]), threads)
    sw = cap.rig.scan_window
    window = (sw.x, sw.y, sw.width, sw.height)
    fit, used, table = solve_views(
        names, detections, board, size, bias_correction=bias_correction,
        outlier_factor=outlier_factor, min_views=min_views, distortion=distortion, window=window,
    )
    cam = fit.camera
    last = fit.bias_history[-1]
    extra: dict[str, Any] = {
        "model": "pinhole + OpenCV 5-coefficient distortion (k1, k2, p1, p2, k3)",
        "distortion_model": _model_record(fit, distortion),
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
        "uncertainty": uncertainty_summary(fit, {"sensor": (0, 0, *size), "scan_window": window}),
    }
    cam = Camera(cam.K, cam.dist, cam.image_size, extra)
    cam.save(out)
    if fit.fixed:
        log.info("camera: %s", extra["distortion_model"]["reason"])
    log.info("camera: %d of %d views used, RMS %.4f px, fx %.3f fy %.3f cx %.3f cy %.3f",
             len(used), len(names), fit.rms_px, cam.fx, cam.fy, cam.cx, cam.cy)
    u = extra["uncertainty"]
    log.info("camera: predicted projection error (1 sigma RMS) %.4f px over the sensor, %.4f px over "
             "the scan window; std cx %.4f px, cy %.4f px", u["projection_rms_px"]["sensor"],
             u["projection_rms_px"]["scan_window"], u["std"]["cx"], u["std"]["cy"])
    return cam

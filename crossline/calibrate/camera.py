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

The code is split by idea (issue 21.3): ``camera_fit`` (Zhang's start, the bundle adjustment,
the bias iterations: ``calibrate_camera``, ``CameraFit``), ``camera_uncertainty`` (the
predicted projection error, noise and model error), ``camera_model_selection`` (the choice of
distortion model and camera.json's record of it). This module keeps the stage (the views'
detection, ``solve_views`` with its outlier loop, ``run_calibrate_camera``) and re-exports the
names its importers use.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.camera_fit import (
    DISTORTION,
    PARAMETERS,
    CameraFit,
    bundle_adjust,
    calibrate_camera,
)
from crossline.calibrate.camera_fit import _project_views as _project_views
from crossline.calibrate.camera_model_selection import DISTORTION_MODELS, _model_record, select_distortion
from crossline.calibrate.camera_uncertainty import (
    grid_pixels,
    model_error,
    projection_uncertainty,
    projection_variance,
    uncertainty_summary,
)
from crossline.calibrate.detect import Detection, detect_board
from crossline.camera import Camera
from crossline.errors import CalibrationError

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

# a view is never an outlier below this RMS (px): its points are located to a tenth of a
# pixel. On clean data the median is a few thousandths, and a view merely worse than the
# others (steeper, nearer the sensor's corners, where the model's residual is larger) holds
# what the others lack: dropped, the camera is extrapolated there
OUTLIER_FLOOR_PX = 0.1
MAX_RMS_PX = 2.0  # reprojection RMS above which the views fit no camera: a wrong board, not a lens
VIEW_SETS = ("camera", "all")
DISTORTION_CHOICES = ("select", "full")


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

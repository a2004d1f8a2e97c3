"""Which distortion coefficients the views determine: the model's choice and its record.

``select_distortion`` fits the candidate models of ``DISTORTION_MODELS`` (k3, then k2 and k3
held at 0) and keeps the one with the lowest predicted projection error over the scan window
(:func:`crossline.calibrate.camera_uncertainty.model_error`); ``_model_record`` is
camera.json's account of which coefficients were estimated, and why. Split from
``crossline.calibrate.camera`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from crossline.board import Board
from crossline.calibrate.camera_fit import DISTORTION, CameraFit, calibrate_camera
from crossline.calibrate.camera_uncertainty import grid_pixels, model_error

__all__ = ["DISTORTION_MODELS", "select_distortion"]

# candidate distortion models, as the coefficients each holds at 0 (the first: all free): the
# radial terms of highest order go first, as they need the widest field to be seen; the
# tangential pair stays free (fixing it moves the principal point, never a small change)
DISTORTION_MODELS: tuple[tuple[str, ...], ...] = ((), ("k3",), ("k2", "k3"))


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

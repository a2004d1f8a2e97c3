"""A calibrated camera's predicted projection error: its noise, and the model error of fixing.

``projection_variance`` and ``projection_uncertainty`` carry the covariance of the
intrinsics to the projection of points seen at given pixels (``grid_pixels`` spans a
window); ``model_error`` adds, for a fit with distortion coefficients fixed at 0, the bias
that fixing them leaves, against the fit with all of them free; ``uncertainty_summary`` is
camera.json's account of both. Split from ``crossline.calibrate.camera`` (issue 21.3), which
re-exports these names.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crossline.calibrate.camera_fit import PARAMETERS, CameraFit
from crossline.camera import Camera

__all__ = [
    "grid_pixels",
    "model_error",
    "projection_uncertainty",
    "projection_variance",
    "uncertainty_summary",
]


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

"""The camera model: pinhole plus OpenCV's 5-coefficient distortion, project and undistort.

Pixels follow OpenCV: ``(u, v) = (column, row)``, the centre of the top-left pixel is
``(0, 0)``, always in full-sensor coordinates. Distortion is ``(k1, k2, p1, p2, k3)``; the
paper's ``(k1, k2, k5)`` radial and ``(k3, k4)`` tangential terms are OpenCV's ``k1, k2, k3``
and ``p1, p2``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from crossline.errors import CrosslineError
from crossline.io.atomic import write_json
from crossline.io.contract import _short
from crossline.io.values import finite_array
from crossline.jit import jit

__all__ = ["CAMERA_PARAMETERS", "Camera", "distort_normalized", "undistort_normalized"]


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV's 5-coefficient distortion to normalised image points (N, 2)."""
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=np.float64)
    x = xy[..., 0]
    y = xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort_normalized(
    xy_d: np.ndarray, dist: np.ndarray, tol: float = 1e-14, max_iter: int = 50
) -> np.ndarray:
    """Invert the distortion for normalised points (N, 2) by Newton's method.

    Converges to ``tol`` in normalised units (1e-14 is about 1e-10 px for a 5000 px focal
    length), far below the 1e-3 px that ``cv2.undistortPoints``' fixed-point iteration can
    leave at the corners of a strongly distorted lens. The 2x2 Newton step is solved in
    closed form, point by point (compiled), each until its own step is below ``tol``.
    """
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=np.float64)
    xy_d = np.asarray(xy_d, dtype=np.float64)
    flat = np.ascontiguousarray(xy_d.reshape(-1, 2))
    out = np.empty_like(flat)
    _newton_undistort(flat, k1, k2, p1, p2, k3, float(tol), int(max_iter), out)
    return out.reshape(xy_d.shape)


@jit
def _newton_undistort(xy_d, k1, k2, p1, p2, k3, tol, max_iter, out):  # pragma: no cover - compiled
    """Per point, Newton steps until the step is at most ``tol`` (or ``max_iter`` steps)."""
    for i in range(xy_d.shape[0]):
        xd = xy_d[i, 0]
        yd = xy_d[i, 1]
        X = xd
        Y = yd
        for _ in range(max_iter):
            r2 = X * X + Y * Y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d(radial)/d(r2)
            fx = X * radial + 2.0 * p1 * X * Y + p2 * (r2 + 2.0 * X * X) - xd
            fy = Y * radial + p1 * (r2 + 2.0 * Y * Y) + 2.0 * p2 * X * Y - yd
            # Jacobian [[a, b], [b, c]] of the distortion (it is symmetric)
            a = radial + 2.0 * X * X * dradial + 2.0 * p1 * Y + 6.0 * p2 * X
            b = 2.0 * X * Y * dradial + 2.0 * p1 * X + 2.0 * p2 * Y
            c = radial + 2.0 * Y * Y * dradial + 6.0 * p1 * Y + 2.0 * p2 * X
            det = a * c - b * b
            sx = (c * fx - b * fy) / det
            sy = (a * fy - b * fx) / det
            X = X - sx
            Y = Y - sy
            # on as long as the step is above tol (a NaN step ends it, as it ends nothing else)
            if not (abs(sx) > tol or abs(sy) > tol) or sx != sx or sy != sy:
                break
        out[i, 0] = X
        out[i, 1] = Y


# the camera model's parameters, in the order of its covariance (camera.json uncertainty)
CAMERA_PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


class CameraFileError(CrosslineError, ValueError):
    """camera.json cannot be read or holds no usable camera model (names the file)."""


@dataclass(frozen=True)
class Camera:
    """Intrinsics ``K`` (3×3), distortion ``(k1, k2, p1, p2, k3)`` and sensor size (width, height)."""

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3):
            raise ValueError(f"camera matrix K must be 3x3, got shape {K.shape}")
        if dist.shape != (5,):
            raise ValueError(f"distortion must have 5 coefficients (k1, k2, p1, p2, k3), got {dist}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))

    @property
    def fx(self) -> float:
        """Focal length along u in pixels."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Focal length along v in pixels."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point u in pixels."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point v in pixels."""
        return float(self.K[1, 2])

    def perturbed(self, delta: np.ndarray) -> Camera:
        """The camera with ``delta`` (9,) added to its parameters, in CAMERA_PARAMETERS order."""
        x = np.asarray(delta, dtype=np.float64).reshape(9)
        K = self.K.copy()
        K[0, 0] += x[0]
        K[1, 1] += x[1]
        K[0, 2] += x[2]
        K[1, 2] += x[3]
        return Camera(K, self.dist + x[4:], self.image_size)

    def normalized_to_pixels(self, xy_d: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) from distorted normalised coordinates (N, 2)."""
        K = self.K
        u = K[0, 0] * xy_d[..., 0] + K[0, 1] * xy_d[..., 1] + K[0, 2]
        v = K[1, 1] * xy_d[..., 1] + K[1, 2]
        return np.stack([u, v], axis=-1)

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Distorted normalised coordinates (N, 2) from pixels (N, 2)."""
        uv = np.asarray(uv, dtype=np.float64)
        K = self.K
        y = (uv[..., 1] - K[1, 2]) / K[1, 1]
        x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.stack([x, y], axis=-1)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of points (N, 3) given in the camera frame (mm); z must be > 0."""
        p = np.asarray(points_cam, dtype=np.float64)
        xy = p[..., :2] / p[..., 2:3]
        return self.normalized_to_pixels(distort_normalized(xy, self.dist))

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Ideal (undistorted) normalised coordinates (N, 2) of pixels (N, 2)."""
        return undistort_normalized(self.pixels_to_normalized(uv), self.dist)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit ray directions (N, 3) in the camera frame through pixels (N, 2)."""
        xy = self.undistort(uv)
        d = np.concatenate([xy, np.ones((*xy.shape[:-1], 1))], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict with the contract keys ``K``, ``dist``, ``image_size`` and extras."""
        out = dict(self.extra)
        out.update(
            K=self.K.tolist(), dist=self.dist.tolist(), image_size=list(self.image_size)
        )
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Camera:
        """Camera from a dict with keys ``K``, ``dist``, ``image_size`` (others kept as extras).

        KeyError for a missing key; ValueError naming the key and what was expected where a
        value is no usable camera model (non-finite or not numbers, K not of the form
        [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, image_size not two positive
        whole numbers).
        """
        if not isinstance(data, dict):
            raise ValueError(f"expected a JSON object with keys K, dist, image_size, "
                             f"got {type(data).__name__}")
        missing = [k for k in ("K", "dist", "image_size") if k not in data]
        if missing:
            raise KeyError(f"camera model lacks key(s) {missing}")
        form = "the 3x3 camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in px, fx and fy > 0"
        K = finite_array(data, "K", (3, 3), form)
        if not (K[0, 0] > 0 and K[1, 1] > 0) or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
            raise ValueError(f"'K' = {K.tolist()}: expected {form}")
        dist = finite_array(data, "dist", (5,), "5 distortion coefficients [k1, k2, p1, p2, k3]")
        size = data["image_size"]
        if not (isinstance(size, list | tuple) and len(size) == 2 and all(
                isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)):
            raise ValueError(f"'image_size' = {_short(size)}: expected [width, height], two positive "
                             f"whole numbers of pixels")
        extra = {k: v for k, v in data.items() if k not in ("K", "dist", "image_size")}
        return cls(K, dist, tuple(size), extra)

    def save(self, path: str | Path) -> None:
        """Write ``camera.json`` atomically."""
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> Camera:
        """Read ``camera.json``."""
        path = Path(path)
        try:
            return cls.from_dict(json.loads(path.read_text()))
        except (KeyError, ValueError, TypeError) as exc:
            raise CameraFileError(f"{path}: not a camera model: {exc}") from exc

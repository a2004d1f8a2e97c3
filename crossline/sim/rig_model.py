"""The virtual rig's model for the renderer: its camera, lasers and sensor, and the ambient light.

``RigModel`` holds the rig's camera (``crossline.camera.Camera``), its laser sheets, its
sensor chain with the fixed pattern noise (PRNU) drawn from the seed, and per-process caches
of exact rays (every pixel of a window, the coarse ambient grid, a window's undistorted
bounds); ``Light`` is the ambient light and ``vignetting`` its cos^4 fall-off; ``_rays`` turns
undistorted coordinates into camera rays for every tracer, and ``COARSE_STEP``, ``NODE_STEP``,
``CHUNK`` and ``ORIGIN`` are the sampling steps and the ray origin the renderers share. Split
from ``crossline.sim.render`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crossline.camera import Camera
from crossline.sim.optics import RayTable, SensorModel, exact_xy, standard_normal_f32
from crossline.sim.scene import dot3, empty3
from crossline.sim.sheet import LaserSheet

__all__ = ["CHUNK", "COARSE_STEP", "NODE_STEP", "ORIGIN", "Light", "RigModel", "vignetting"]

COARSE_STEP = 8  # px between rays of the faint scan-exposure ambient light
NODE_STEP = 4  # px between the first rays of a board view (edges are then traced per pixel)
CHUNK = 1 << 15  # rays traced at once: the temporaries of a chunk stay in the CPU cache
ORIGIN = np.zeros(3)


@dataclass(frozen=True)
class Light:
    """Ambient light: electrons on a white surface facing ``up``, a gentle gradient."""

    e_white: float
    up: np.ndarray  # unit vector towards the light (camera frame)
    grad: np.ndarray  # relative change per mm (camera frame)
    ref: np.ndarray  # point where the gradient is zero (camera frame)

    def electrons(self, P: np.ndarray, N: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        """Electrons (before vignetting) from points with normals and albedos."""
        k = 0.6 + 0.4 * np.maximum(0.0, dot3(N, self.up))
        return self.e_white * albedo * k * (1.0 + dot3(P - self.ref, self.grad))


def vignetting(xy: np.ndarray) -> np.ndarray:
    """Natural cos^4 fall-off of the field angle for undistorted normalised coordinates."""
    r2 = xy[..., 0] ** 2 + xy[..., 1] ** 2
    return 1.0 / (1.0 + r2) ** 2


class RigModel:
    """The rig's camera, lasers and sensor, with per-process caches of rays."""

    def __init__(self, preset, bit_depth: int | None = None, seed: int = 0,
                 data_bits: int | None = None):
        self.preset = preset
        s = preset.sensor
        self.camera = Camera(np.array(s.K), np.array(s.dist), (s.width, s.height))
        self.bits = int(bit_depth or s.bit_depth)
        # the ADC's bits inside the container: the rig's (or the container's), at most the container's
        self.data_bits = min(int(data_bits or s.data_bits or self.bits), self.bits)
        self.lasers = {k: LaserSheet(k, v) for k, v in preset.lasers.items()}
        self.sensor_window = (0, 0, s.width, s.height)
        self.scan_window = tuple(int(v) for v in s.scan_window)
        rng = np.random.default_rng([int(seed), 1001])
        prnu = standard_normal_f32(rng, s.height * s.width).reshape(s.height, s.width)
        self.prnu = (1.0 + np.float32(s.prnu) * prnu).astype(np.float32)
        self.sensor = SensorModel(s, self.bits, self.prnu, self.data_bits)
        self._tables: dict = {}
        self._coarse: dict = {}
        self._bounds: dict = {}

    def table(self, window) -> RayTable:
        """Exact rays of every pixel of a window (cached).

        The table reaches NODE_STEP px beyond the window's right and bottom edges, so that the
        grid of every NODE_STEP-th pixel centre (board views) covers the whole window.
        """
        window = tuple(window)
        if window not in self._tables:
            x0, y0, w, h = window
            self._tables[window] = RayTable(self.camera, (x0, y0, w + NODE_STEP, h + NODE_STEP))
        return self._tables[window]

    def coarse(self, window):
        """Exact rays on the coarse ambient grid of a window: (xy (ch, cw, 2))."""
        window = tuple(window)
        if window not in self._coarse:
            x0, y0, w, h = window
            cw, ch = -(-w // COARSE_STEP), -(-h // COARSE_STEP)
            u = x0 + COARSE_STEP * np.arange(cw) + (COARSE_STEP - 1) / 2
            v = y0 + COARSE_STEP * np.arange(ch) + (COARSE_STEP - 1) / 2
            U, V = np.meshgrid(u, v)
            xy = exact_xy(self.camera, np.stack([U.ravel(), V.ravel()], -1)).reshape(ch, cw, 2)
            self._coarse[window] = xy
        return self._coarse[window]

    def bounds(self, window, margin: float):
        """Undistorted normalised bounds (xmin, xmax, ymin, ymax) of a window plus margin px."""
        key = (tuple(window), margin)
        if key not in self._bounds:
            x0, y0, w, h = window
            a = np.linspace(0, 1, 101)
            u0, u1 = x0 - 0.5 - margin, x0 + w - 0.5 + margin
            v0, v1 = y0 - 0.5 - margin, y0 + h - 0.5 + margin
            pts = np.concatenate([
                np.stack([u0 + a * (u1 - u0), np.full_like(a, v0)], -1),
                np.stack([u0 + a * (u1 - u0), np.full_like(a, v1)], -1),
                np.stack([np.full_like(a, u0), v0 + a * (v1 - v0)], -1),
                np.stack([np.full_like(a, u1), v0 + a * (v1 - v0)], -1),
            ])
            xy = exact_xy(self.camera, pts)
            pad = 0.02 * (np.ptp(xy[:, 0]) + np.ptp(xy[:, 1]))
            self._bounds[key] = (xy[:, 0].min() - pad, xy[:, 0].max() + pad,
                                 xy[:, 1].min() - pad, xy[:, 1].max() + pad)
        return self._bounds[key]

    def project(self, P: np.ndarray) -> np.ndarray:
        """Pixels of camera-frame points (z > 0)."""
        return self.camera.project(P)


# ----------------------------------------------------------------------------- tracing


def _rays(xy: np.ndarray) -> np.ndarray:
    """Camera rays (x, y, 1) of undistorted coordinates (N, 2), column-major (N, 3)."""
    d = empty3(len(xy))
    d[:, 0] = xy[:, 0]
    d[:, 1] = xy[:, 1]
    d[:, 2] = 1.0
    return d

"""The laser sheet: a fan of light from an emitter, of Gaussian thickness, in the camera frame.

For a surface point P with outward normal N the irradiance, in electrons the pixel that sees
a white (albedo 1) Lambertian surface there would collect, is::

    E = E_ref * exp(-2 f^2 / w(s)^2) * (w0 / w(s)) * (s0 / s) * fan(phi) * max(0, -N . b)

* ``f = n . P + d``: distance of P from the sheet's centre plane (the calibrated plane);
* ``s = |P - e|``, ``b = (P - e) / s``: propagation distance and direction from the emitter e;
* ``w(s) = w0 sqrt(1 + ((s - s0) / zR)^2)``: 1/e^2 half-thickness of a Gaussian beam focused
  at s0 with Rayleigh range ``zR = pi w0^2 / (M^2 lambda)``; the factor ``w0 / w`` keeps the
  power through the thickness constant;
* ``s0 / s``: a fan spreads its power over a line that grows linearly with s;
* ``fan(phi) = 1 - rolloff (phi / phi_max)^2`` inside the fan's half angle, 0 outside
  (a Powell lens line: nearly flat, slightly dimmer at the ends);
* ``max(0, -N . b)``: Lambert's cosine of the incidence angle (light on a tilted surface
  spreads over a larger area).

Whether the segment from P to the emitter is free (shadows) is decided by the renderer.
"""

from __future__ import annotations

import numpy as np

from crossline.sim.presets import LaserSpec
from crossline.sim.scene import dot3, norm3, rowdot

__all__ = ["BAND_SIGMAS", "LaserSheet"]

# light beyond 2.3 w from the centre plane is dropped: < 2.6e-5 of the peak, < 0.3 e- for the
# brightest stripes, a twentieth of the read noise
BAND_SIGMAS = 2.3


class LaserSheet:
    """One laser of the rig, in the camera frame."""

    def __init__(self, name: str, spec: LaserSpec):
        self.name = name
        self.spec = spec
        self.n = np.asarray(spec.normal, dtype=np.float64)
        self.d = float(spec.d)
        self.e = np.asarray(spec.emitter, dtype=np.float64)
        self.c = np.asarray(spec.fan_centre, dtype=np.float64)
        self.c = self.c - (self.c @ self.n) * self.n
        self.c /= np.linalg.norm(self.c)
        self.side = np.cross(self.n, self.c)
        self.w0 = spec.waist_mm
        self.s0 = spec.focus_mm
        self.zr = spec.rayleigh_mm
        self.phi_max = np.radians(spec.fan_half_angle_deg)

    def width(self, s: np.ndarray) -> np.ndarray:
        """1/e^2 half-thickness w(s) (mm)."""
        return self.w0 * np.sqrt(1.0 + ((s - self.s0) / self.zr) ** 2)

    def distance(self, P: np.ndarray) -> np.ndarray:
        """Signed distance of points from the centre plane (mm)."""
        return dot3(P, self.n) + self.d

    def in_fan(self, P: np.ndarray) -> np.ndarray:
        """Fan profile (0 outside the fan) of points."""
        v = P - self.e
        phi = np.arctan2(dot3(v, self.side), dot3(v, self.c))
        x = phi / self.phi_max
        return np.where(np.abs(x) <= 1.0, 1.0 - self.spec.fan_rolloff * x * x, 0.0)

    def irradiance(self, P: np.ndarray, N: np.ndarray, f: np.ndarray | None = None) -> np.ndarray:
        """Electrons on a white surface at points P with normals N, before shadowing."""
        if f is None:
            f = self.distance(P)
        v = P - self.e
        s = norm3(v)
        w = self.width(s)
        cos_inc = np.maximum(0.0, -rowdot(N, v) / s)
        g = np.exp(-2.0 * (f / w) ** 2)
        return self.spec.peak_electrons * g * (self.w0 / w) * (self.s0 / s) * self.in_fan(P) * cos_inc

    def to_dict(self) -> dict:
        """Everything about this laser that a validation may need."""
        s = self.spec
        return {
            "normal": self.n.tolist(),
            "d": self.d,
            "emitter_cam": self.e.tolist(),
            "fan_centre_cam": self.c.tolist(),
            "fan_half_angle_deg": s.fan_half_angle_deg,
            "fan_rolloff": s.fan_rolloff,
            "wavelength_nm": s.wavelength_nm,
            "waist_mm": s.waist_mm,
            "m2": s.m2,
            "focus_mm": s.focus_mm,
            "rayleigh_mm": self.zr,
            "thickness_model": "w(s) = waist_mm * sqrt(1 + ((s - focus_mm) / rayleigh_mm)^2), "
                               "1/e^2 half-thickness; profile exp(-2 f^2 / w^2)",
            "peak_electrons": s.peak_electrons,
            "speckle_contrast": s.speckle_contrast,
            "speckle_grain_px": s.speckle_grain_px,
        }

"""The measuring arm: where it puts the scanner, and the error of the pose it reports.

Poses. The scanner's camera pose ``T_base_cam`` is chosen (looking at a target from a
distance, tilted, rolled); the arm's flange is then ``T_base_tool = T_base_cam @ inv(X)``
with the rig's true hand-eye matrix ``X = T_tool_cam``.

Scans sweep the scanner along a straight line over the artefact (level, or rising along an
inclined artefact such as a tilted ball bar, which keeps it in the measuring range) at a
speed that varies by +-15 % (a hand-guided arm), with a slow wobble of the orientation
(about 1.5 deg) around the camera's own axes, so that the poses are not a pure translation.
The sweep runs along the image's u axis, or at ``-roll_deg`` to it when the scan rolls the
camera about its axis.

Reported-pose error. The paper's arm has a stated precision of 0.02 mm. We read it as two
standard deviations of the 3-D error of the flange position, so each axis has
``sigma = 0.02 / (2 sqrt 3) = 0.0058 mm``. An articulated arm's error depends on its joint
configuration, which changes smoothly along a sweep, plus a little encoder jitter; so the
error is split into

* a smooth part: per axis a stationary Gauss-Markov (Ornstein-Uhlenbeck) process of
  standard deviation ``0.9 sigma`` (0.0052 mm) and correlation time 0.3 s, sampled at the
  frame times (AR(1) with ``phi = exp(-dt / tau)``);
* a white part: independent per frame, ``sqrt(1 - 0.9^2) sigma`` (0.0025 mm) per axis;
* an orientation error of the same structure, 2e-5 rad per axis in total (1.8e-5 smooth,
  0.87e-5 white), applied in the flange frame: ``R_reported = R_true @ exp([dtheta]x)``.

The position error is added in the base frame. Calibration poses (hand-eye views) are far
apart in configuration, so each gets an independent draw of the total error.
"""

from __future__ import annotations

import numpy as np

from crossline.geometry import invert_transform, make_transform, rotvec_to_matrix
from crossline.sim.presets import ArmNoiseSpec, RigPreset, ScanSpec

__all__ = ["noise_calibration", "noise_scan", "noise_to_dict", "scan_trajectory"]


def _gauss_markov(rng: np.random.Generator, n: int, dt: float, tau: float, sigma: float) -> np.ndarray:
    """(n, 3) stationary AR(1) samples of a Gauss-Markov process."""
    phi = np.exp(-dt / tau)
    q = np.sqrt(1.0 - phi * phi)
    x = np.empty((n, 3))
    xi = rng.standard_normal((n, 3))
    x[0] = sigma * xi[0]
    for i in range(1, n):
        x[i] = phi * x[i - 1] + q * sigma * xi[i]
    return x


def _apply(T: np.ndarray, dp: np.ndarray, dth: np.ndarray) -> np.ndarray:
    R = T[:, :3, :3] @ rotvec_to_matrix(dth)
    return make_transform(R, T[:, :3, 3] + dp)


def noise_scan(T_true: np.ndarray, spec: ArmNoiseSpec, dt: float, rng: np.random.Generator):
    """Reported poses of a sweep (N, 4, 4) and the errors (position mm, rotation rad)."""
    n = len(T_true)
    dp = _gauss_markov(rng, n, dt, spec.corr_time_s, spec.sigma_smooth_mm)
    dp += spec.sigma_white_mm * rng.standard_normal((n, 3))
    dth = _gauss_markov(rng, n, dt, spec.corr_time_s, spec.rot_sigma_smooth)
    dth += spec.rot_sigma_white * rng.standard_normal((n, 3))
    return _apply(T_true, dp, dth), dp, dth


def noise_calibration(T_true: np.ndarray, spec: ArmNoiseSpec, rng: np.random.Generator):
    """Reported poses (N, 4, 4) of independent calibration poses, and the errors."""
    n = len(T_true)
    dp = spec.sigma_axis_mm * rng.standard_normal((n, 3))
    dth = spec.rot_sigma_rad * rng.standard_normal((n, 3))
    return _apply(T_true, dp, dth), dp, dth


def noise_to_dict(spec: ArmNoiseSpec) -> dict:
    """The arm-noise model and its numbers, for truth.json."""
    return {
        "model": "reported T_base_tool = true with position error dp (base frame) added and "
                 "rotation R_true @ exp([dtheta]x) (flange frame); each per axis = smooth "
                 "Gauss-Markov (AR(1) at the frame times) + white; calibration poses: "
                 "independent draws of the total",
        "precision_mm": spec.precision_mm,
        "precision_reading": "2 sigma of the 3-D flange position error",
        "sigma_axis_mm": spec.sigma_axis_mm,
        "sigma_smooth_mm": spec.sigma_smooth_mm,
        "sigma_white_mm": spec.sigma_white_mm,
        "corr_time_s": spec.corr_time_s,
        "rot_sigma_axis_rad": spec.rot_sigma_rad,
        "rot_sigma_smooth_rad": spec.rot_sigma_smooth,
        "rot_sigma_white_rad": spec.rot_sigma_white,
    }


def view_rotation(view_dir: np.ndarray, x_hint: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """R_base_cam whose z axis is ``view_dir`` and whose x axis is ``x_hint`` rolled by ``roll``."""
    z = view_dir / np.linalg.norm(view_dir)
    x = x_hint - (x_hint @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    return R @ rotvec_to_matrix(np.array([0.0, 0.0, roll]))


def tilted_down(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit viewing direction: straight down, tilted by ``tilt`` towards ``azimuth``."""
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    return np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)])


def scan_trajectory(preset: RigPreset, spec: ScanSpec, aim: np.ndarray, n_frames: int):
    """Frame times (s) and true T_base_cam (N, 4, 4) of a sweep centred on the aim point.

    The speed is the preset's (its sweep over its frame count); fewer frames cover the middle
    of the same sweep, more frames a longer one.
    """
    fps = preset.sensor.frame_rate
    T_full = (spec.frames - 1) / fps
    speed = spec.sweep_mm / T_full
    times = np.arange(n_frames) / fps
    tc = times - times[-1] / 2  # time from the middle of the sweep
    amp = 0.15 * speed * T_full / (2 * np.pi)
    s = speed * tc + amp * np.sin(2 * np.pi * tc / T_full)
    h = np.radians(spec.heading_deg)
    sdir = np.array([np.cos(h), np.sin(h), 0.0])
    across = np.array([-np.sin(h), np.cos(h), 0.0])
    rise = np.radians(spec.sweep_incline_deg)
    path = np.array([np.cos(h) * np.cos(rise), np.sin(h) * np.cos(rise), np.sin(rise)])
    target0 = aim + path * spec.sweep_offset_mm[0] + across * spec.sweep_offset_mm[1]
    roll = np.radians(spec.roll_deg)
    R0 = view_rotation(tilted_down(spec.tilt_deg, spec.tilt_azimuth_deg), sdir, roll)
    wob = np.radians(spec.wobble_deg) * np.stack(
        [np.sin(2 * np.pi * 0.35 * tc + 0.3), np.sin(2 * np.pi * 0.27 * tc + 1.1),
         0.5 * np.sin(2 * np.pi * 0.41 * tc + 2.0)], axis=1)
    R = R0 @ rotvec_to_matrix(wob)
    target = target0 + s[:, None] * path
    eye = target - spec.distance_mm * R[:, :, 2]
    return times, make_transform(R, eye)


def tool_from_cam(T_base_cam: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Flange poses T_base_tool = T_base_cam @ inv(X)."""
    return T_base_cam @ invert_transform(X)

"""Calibration views: where the board is for camera, laser-plane and hand-eye calibration.

* Camera views (board moved in front of the fixed camera): tilts from 0 to ``max_tilt``
  about axes spread around the board plane, rolls within +-25 deg, distances over the
  working range, and board centres pushed towards the corners and edges of the frame (as far
  as the whole board stays in view) so that the distortion is seen everywhere. The first
  views are fronto-parallel.
* Laser views: the board at several depths and tilts with its centre on the laser's plane,
  at the point of the plane nearest the optical axis at that depth (moved along the stripe if
  the board would leave the frame), so the stripe always crosses the board's middle.
* Hand-eye views: the board lies on the table at T_base_board; the scanner looks at it from
  the working distance, tilted 15-35 deg from the board's normal towards azimuths spread over
  the full circle and rolled by up to +-30 deg, so that the relative motions rotate about
  different axes. The board's x axis always appears within +-40 deg of the image's u axis,
  which keeps the 180-deg symmetry of a symmetric grid resolvable by its orientation.
"""

from __future__ import annotations

import numpy as np

from crossline.camera import Camera
from crossline.errors import CrosslineError
from crossline.geometry import make_transform, rotvec_to_matrix
from crossline.sim.arm import view_rotation
from crossline.sim.presets import BoardSpec, CalibrationSpec, LaserSpec, RigPreset

__all__ = ["board_outline_points", "camera_views", "handeye_views", "laser_views"]

GOLDEN = np.radians(137.50776)


def board_outline_points(spec: BoardSpec) -> np.ndarray:
    """Board points (board frame) that must be seen for detection: every circle's rim."""
    pts = spec.board.object_points()
    if spec.board.pattern == "chessboard":
        s = spec.board.spacing
        ring = np.array([[-s, -s], [s, -s], [-s, s], [s, s]], dtype=np.float64)
    else:
        r = spec.board.diameter / 2 * 1.6  # the rim plus a little light around it
        a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        ring = np.stack([r * np.cos(a), r * np.sin(a)], -1)
    out = (pts[:, None, :2] + ring[None]).reshape(-1, 2)
    return np.column_stack([out, np.zeros(len(out))])


def _visible(cam: Camera, T_cam_board: np.ndarray, pts: np.ndarray, margin: float = 12.0) -> bool:
    P = pts @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    if np.any(P[:, 2] < 10.0):
        return False
    uv = cam.project(P)
    w, h = cam.image_size
    return bool(np.all((uv[:, 0] > margin) & (uv[:, 0] < w - 1 - margin)
                       & (uv[:, 1] > margin) & (uv[:, 1] < h - 1 - margin)))


def _does_not_fit(what: str, spec: BoardSpec, depth: float) -> CrosslineError:
    b = spec.board
    x0, y0, x1, y1 = spec.plate_rect()
    kind = "chessboard" if b.pattern == "chessboard" else f"{b.pattern} circle grid"
    return CrosslineError(
        f"{what}: the {b.cols}x{b.rows} {kind} ({x1 - x0:.0f} x {y1 - y0:.0f} mm with its "
        f"margin) does not fit the camera's frame at {depth:.0f} mm; use a smaller board"
    )


def _tilt(axis_angle: float, tilt: float) -> np.ndarray:
    return rotvec_to_matrix(np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0]) * tilt)


def _board_centre(spec: BoardSpec) -> np.ndarray:
    ex, ey = spec.board.extent()
    return np.array([ex / 2, ey / 2, 0.0])


def _fit_camera_view(cam, R, bc, pts, depth, tx, ty, depth_max):
    """Board pose with its centre as far towards (tx, ty) as the frame allows; deeper if needed."""
    w, h = cam.image_size
    while depth <= depth_max:
        frac = 1.0
        for _ in range(40):
            uv = np.array([cam.cx + tx * frac * (w / 2), cam.cy + ty * frac * (h / 2)])
            ray = np.append(cam.undistort(uv[None])[0], 1.0)
            T = make_transform(R, depth * ray - R @ bc)
            if _visible(cam, T, pts):
                return T
            frac *= 0.9
        depth += 4.0
    return None


def camera_views(cam: Camera, spec: BoardSpec, cal: CalibrationSpec, n: int) -> list[np.ndarray]:
    """T_cam_board of ``n`` camera-calibration views."""
    pts = board_outline_points(spec)
    bc = _board_centre(spec)
    # targets in units of the half frame: centre, corners, edges
    targets = [(0, 0), (0.0, 0.0), (-1, -1), (1, 1), (1, -1), (-1, 1), (0, -1), (0, 1), (-1, 0),
               (1, 0), (-1, -1), (1, 1), (1, -1), (-1, 1), (0.5, -1), (-0.5, 1), (-1, 0.5),
               (1, -0.5), (0, 0), (1, 1)]
    tilts = [0, 0, 25, 30, 35, 40, 20, 30, 40, 25, 15, 40, 30, 35, 20, 38, 28, 33, 40, 18]
    z0, z1 = cal.depth_range_mm
    views = []
    for i in range(n):
        tilt = np.radians(min(tilts[i % len(tilts)], cal.max_tilt_deg))
        roll = np.radians(25.0 * np.sin(2.3 * i + 0.5)) if i >= 2 else 0.0
        R = rotvec_to_matrix(np.array([0.0, 0.0, roll])) @ _tilt(GOLDEN * i, tilt)
        depth = z0 + (z1 - z0) * ((0.5 + 0.618034 * i) % 1.0)
        if i == 1:
            depth = z0 + 0.25 * (z1 - z0)
        tx, ty = targets[i % len(targets)]
        T = _fit_camera_view(cam, R, bc, pts, depth, tx, ty, z1 + 40.0)
        if T is None:
            raise _does_not_fit(f"camera view {i}", spec, depth)
        views.append(T)
    return views


def laser_views(cam: Camera, spec: BoardSpec, laser: LaserSpec, depths: tuple[float, ...],
                n: int, phase: float = 0.0) -> list[np.ndarray]:
    """T_cam_board of ``n`` laser-calibration poses of one laser (board centre on its plane)."""
    pts = board_outline_points(spec)
    bc = _board_centre(spec)
    nrm = np.asarray(laser.normal)
    d = laser.d
    tilts = [18, -22, 26, -14, 24, -20]
    axes = [30, 120, 75, 160, 10, 100]
    along = np.array([-nrm[1], nrm[0], 0.0])
    along /= np.linalg.norm(along)
    views = []
    for i in range(n):
        depth = depths[i % len(depths)] + (i // len(depths)) * 3.0
        R = rotvec_to_matrix(np.array([0.0, 0.0, np.radians(10.0 * np.sin(1.7 * i + phase))])) @ \
            _tilt(np.radians(axes[i % len(axes)] + phase), np.radians(tilts[i % len(tilts)]))
        # a chessboard turned so the stripe crosses its squares, by the least turn that lets
        # it fit the frame; the board as it comes if no such turn does
        turns = [_across_squares(R, nrm, k) for k in (0, -1, 1, -2, 2)] \
            if spec.board.pattern == "chessboard" else []
        T = None
        for Rt in [*turns, R]:
            for dz in np.arange(0.0, 24.0, 3.0):
                z = depth + dz
                q = -(nrm[2] * z + d) * nrm[:2] / (nrm[:2] @ nrm[:2])
                P0 = np.array([q[0], q[1], z])
                # slide along the stripe (stays on the plane) until the whole board is in view
                for s in np.concatenate([[0.0], np.repeat(np.arange(2.0, 60.0, 2.0), 2)
                                         * np.tile([1, -1], 29)]):
                    Tc = make_transform(Rt, P0 + s * along - Rt @ bc)
                    if _visible(cam, Tc, pts, margin=20.0):
                        T = Tc
                        break
                if T is not None:
                    break
            if T is not None:
                break
        if T is None:
            raise _does_not_fit(f"laser view {i}", spec, depth)
        views.append(T)
    return views


def _across_squares(R: np.ndarray, laser_normal: np.ndarray, k: int = 0) -> np.ndarray:
    """The board turned in its plane so that the stripe crosses a chessboard's squares at 22.5 deg
    to their rows and diagonals, as a user would hold it: a stripe along a row runs on the
    squares' edges, one along a diagonal on one colour and through the corners. ``k`` adds
    ``k`` x 45 deg to the least such turn."""
    t = R.T @ np.cross(laser_normal, R[:, 2])  # the stripe's direction in the board frame
    psi = np.degrees(np.arctan2(t[1], t[0]))
    delta = psi % 45.0 - 22.5 + 45.0 * k  # the least turn to 22.5 deg modulo 45, and k more
    return R @ rotvec_to_matrix(np.array([0.0, 0.0, np.radians(delta)]))


def handeye_views(cam: Camera, preset: RigPreset, n: int, distance: float) -> list[np.ndarray]:
    """True T_base_cam of ``n`` hand-eye views of the board lying on the table."""
    spec = preset.board
    pts = board_outline_points(spec)
    Tbb = preset.T_base_board
    centre = Tbb[:3, :3] @ _board_centre(spec) + Tbb[:3, 3]
    x_board = Tbb[:3, 0]
    tilts = [15, 25, 35, 20, 30, 18, 33, 27, 22, 32, 16, 28]
    rolls = [-20, 15, -10, 22, -22, 5, 18, -15, 12, -5, 20, -18]
    views = []
    for i in range(n):
        az = 360.0 * i / n + 17.0 * (i % 3)
        t, a = np.radians(tilts[i % len(tilts)]), np.radians(az)
        # from the board's normal (base +z, towards the camera) tilted towards azimuth a
        towards_cam = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
        R = view_rotation(-towards_cam, x_board, np.radians(rolls[i % len(rolls)]))
        found = None
        for dist in distance + np.arange(0.0, 30.0, 3.0):
            offset = np.array([3.0 * np.cos(1.3 * i), 3.0 * np.sin(0.7 * i), 0.0])
            for _ in range(12):
                eye = centre + offset + towards_cam * dist
                T_base_cam = make_transform(R, eye)
                T_cam_board = np.linalg.inv(T_base_cam) @ Tbb
                if _visible(cam, T_cam_board, pts, margin=20.0):
                    found = T_base_cam
                    break
                offset *= 0.7
            if found is not None:
                break
        if found is None:
            raise _does_not_fit(f"hand-eye view {i}", spec, distance)
        T_base_cam = found
        views.append(T_base_cam)
    return views

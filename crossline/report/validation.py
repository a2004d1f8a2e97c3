"""Estimates against the simulator's truth: the helpers of the report's validation part.

``label_errors`` (wrong A/B labels of stripe points against the true centre lines),
``volume_points`` and ``plane_depth_range`` (the measured volume and the scanner's measuring
range), ``frame_rotation`` and ``camera_error`` (estimated camera against the true one),
``laser_plane_error`` and ``transform_error`` (laser planes, hand-eye). Split from
``crossline.report.metrics`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.optimize import least_squares

from crossline.geometry import angle_between, rotation_angle, rotvec_to_matrix
from crossline.robust import robust_sigma
from crossline.scan.labels import nearest_in_column

__all__ = [
    "camera_error",
    "frame_rotation",
    "label_errors",
    "laser_plane_error",
    "plane_depth_range",
    "transform_error",
    "true_line_at",
    "volume_points",
]


# ----------------------------------------------------------------------------- against truth


def true_line_at(key_u: np.ndarray, key_v: np.ndarray, span: int, frame: np.ndarray,
                 u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The true line's row at each point's (fractional) column and its slope (rows per column).

    ``key_u`` (frame * span + column) and ``key_v`` are one laser's true points sorted by
    (key, row). The row is interpolated between the line's rows at the columns either side of
    the point (each the row nearest the point, for a line that crosses a column twice). The
    slope is the mean of the steps to the columns either side where they agree within 2x;
    where they do not, a column's nearest row lies on another surface (a step, an occlusion)
    and the gentler step is the line's. Where only one column has the line, its row is taken,
    with the slope of the next pair of columns if there is one.
    """
    c0 = np.floor(u).astype(np.int64)
    rows = []
    for dc in (-1, 0, 1, 2):
        q = (frame * span + c0 + dc).astype(np.float64)
        j, _ = nearest_in_column(key_u, key_v, q, v)
        rows.append(np.where(j >= 0, key_v[np.maximum(j, 0)], np.nan))
    rm, r0, r1, r2 = rows
    ahead, behind = r1 - r0, r0 - rm
    with np.errstate(invalid="ignore"):
        agree = np.abs(ahead - behind) <= 0.5 * np.fmax(np.abs(ahead), np.abs(behind))
        gentler = np.where(np.abs(ahead) <= np.abs(behind), ahead, behind)
    slope = np.where(agree, 0.5 * (ahead + behind),
                     np.where(np.isfinite(ahead) & np.isfinite(behind), gentler,
                              np.fmax(ahead, behind)))
    slope = np.where(np.isfinite(slope), slope, r2 - r1)
    t = u - c0
    row = np.where(np.isfinite(r0) & np.isfinite(r1), r0 + t * (r1 - r0),
                   np.where(np.isfinite(r0) & (t <= 0.5), r0 + t * slope,
                            np.where(np.isfinite(r1), r1 - (1.0 - t) * slope, np.nan)))
    # a point half a column or more from the one column its line has: its nearest true row
    row = np.where(np.isnan(row) & np.isfinite(r0), r0, row)
    return row, np.nan_to_num(slope, nan=0.0)


def label_errors(
    frame: np.ndarray, laser: np.ndarray, u: np.ndarray, v: np.ndarray,
    true_frame: np.ndarray, true_laser: np.ndarray, true_u: np.ndarray, true_v: np.ndarray,
    *, near_px: float = 3.0, crossing_px: float = 15.0,
) -> dict[str, Any]:
    """Wrong A/B labels of stripe points (px) against the true centre lines of their frames.

    Distances are measured across a true line, in the image: the point's row against the
    line's row at the point's column (interpolated between the line's columns), times the
    line's cosine to the rows. A steep stripe's centres sit at fractional columns, and its row
    changes by many pixels per column: along the column the same centre error reads that many
    times larger. A point is checked where one true line of its frame passes within
    ``near_px`` of it and the other does not; its true laser is that line's. Points within
    ``crossing_px`` of both lines are the crossing band, counted apart. ``centre_error``: per
    laser, the right-labelled centres' signed distance from their true line (px; n, mean, RMS
    and robust sigma), away from the crossing band: across the stripe, where the speckle bound
    (:mod:`crossline.report.speckle`) applies.
    """
    frame = np.asarray(frame, dtype=np.int64)
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    laser = np.asarray(laser).astype(str)
    tf = np.asarray(true_frame, dtype=np.int64)
    tu = np.asarray(true_u, dtype=np.int64)
    tv = np.asarray(true_v, dtype=np.float64)
    tl = np.asarray(true_laser).astype(str)
    span = int(max(np.ceil(u.max(initial=0.0)), tu.max(initial=0))) + 4
    dist = {}
    for name in ("A", "B"):
        m = tl == name
        if not m.any():
            dist[name] = np.full(u.size, np.nan)
            continue
        key = (tf[m] * span + tu[m]).astype(np.float64)
        order = np.lexsort((tv[m], key))
        row, slope = true_line_at(key[order], tv[m][order], span, frame, u, v)
        dist[name] = (v - row) / np.hypot(1.0, slope)
    da, db = np.abs(dist["A"]), np.abs(dist["B"])
    with np.errstate(invalid="ignore"):
        # where both true lines pass within near_px the point could be either: not checked
        checked = (np.fmin(da, db) <= near_px) & ~(np.maximum(da, db) <= near_px)
        truth = np.where(np.nan_to_num(da, nan=np.inf) <= np.nan_to_num(db, nan=np.inf), "A", "B")
        crossing = np.maximum(da, db) < crossing_px
    wrong = checked & (laser != truth)
    n_checked = int(checked.sum())
    # how far the right-labelled centres lie from their true line, across it, away from the
    # crossing (where the two stripes' light overlaps)
    centre = {}
    for name in ("A", "B"):
        m = checked & ~crossing & (laser == truth) & (truth == name)
        r = dist[name][m]
        if r.size >= 10:
            centre[name] = {"n": int(r.size), "mean_px": float(r.mean()),
                            "rms_px": float(np.sqrt(np.mean(r**2))),
                            "sigma_px": robust_sigma(r)}
    return {"points": int(frame.size), "checked": n_checked, "wrong": int(wrong.sum()),
            "wrong_away_from_crossing": int((wrong & ~crossing).sum()),
            "wrong_in_crossing_band": int((wrong & crossing).sum()),
            "wrong_rate": float(wrong.sum() / n_checked) if n_checked else None,
            "near_px": near_px, "crossing_px": crossing_px, "centre_error": centre}


def volume_points(
    camera: Any,
    *,
    z_range: tuple[float, float] = (115.0, 185.0),
    region: tuple[int, int, int, int] | None = None,
    grid: tuple[int, int] = (17, 9),
    depths: int = 8,
) -> np.ndarray:
    """Points (M, 3) in the camera frame filling the measured volume: a pixel grid over
    ``region`` (x, y, width, height; default the full sensor) seen through ``camera``, at
    ``depths`` distances evenly spread over ``z_range`` (mm along the optical axis)."""
    w, h = camera.image_size
    x0, y0, rw, rh = region if region is not None else (0, 0, w, h)
    u, v = np.meshgrid(np.linspace(x0, x0 + rw - 1, grid[0]), np.linspace(y0, y0 + rh - 1, grid[1]))
    xy = camera.undistort(np.column_stack([u.ravel(), v.ravel()]))
    z = np.linspace(z_range[0], z_range[1], depths)
    pts = np.concatenate([np.column_stack([xy * zi, np.full(len(xy), zi)]) for zi in z])
    return pts


def plane_depth_range(
    camera: Any,
    planes: list[tuple[np.ndarray, float]],
    *,
    region: tuple[int, int, int, int] | None = None,
    grid: tuple[int, int] = (64, 48),
    quantiles: tuple[float, float] = (0.01, 0.99),
) -> tuple[float, float] | None:
    """Depth range (mm along the optical axis) over which laser planes (n, d) cross the rays of
    ``region`` (x, y, width, height; default the full sensor): the scanner's measuring range.

    The extreme 1 % at each end are left out, where a ray runs nearly along a plane. None when
    no ray meets a plane in front of the camera.
    """
    w, h = camera.image_size
    x0, y0, rw, rh = region if region is not None else (0, 0, w, h)
    u, v = np.meshgrid(np.linspace(x0, x0 + rw - 1, grid[0]), np.linspace(y0, y0 + rh - 1, grid[1]))
    rays = camera.rays(np.column_stack([u.ravel(), v.ravel()]))
    z = []
    for n, d in planes:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -float(d) / (rays @ np.asarray(n, dtype=np.float64))
        zi = (rays * t[:, None])[:, 2]
        z.append(zi[np.isfinite(zi) & (t > 0) & (zi > 0)])
    z = np.concatenate(z) if z else np.empty(0)
    if len(z) == 0:
        return None
    lo, hi = np.quantile(z, quantiles)
    return float(lo), float(hi)


def frame_rotation(est: Any, true: Any, volume_cam: np.ndarray) -> np.ndarray:
    """Rotation R (3, 3) of the estimated camera's frame against the true one that best explains
    the projection difference over the volume: ``est.project(R @ X)`` nearest ``true.project(X)``.

    A camera model is determined by its views only up to such a rotation where they leave the
    principal point loose: a principal-point error with the rotation that undoes it bends no
    ray, and the laser planes and hand-eye, found through the same camera, carry the same
    rotation, so measured points in the arm's frame do not feel it.
    """
    X = np.asarray(volume_cam, dtype=np.float64)
    target = true.project(X)

    def resid(rv: np.ndarray) -> np.ndarray:
        return (est.project(X @ rotvec_to_matrix(rv).T) - target).ravel()

    return rotvec_to_matrix(least_squares(resid, np.zeros(3), x_scale=1e-3).x)


def camera_error(est: Any, true: Any, volume_cam: np.ndarray) -> dict[str, Any]:
    """Projection difference (px) of the estimated camera against the true one over the volume,
    the same after the best rotation of its frame (``frame_free``: what bends rays), and the
    parameter differences (estimated minus true)."""
    duv = est.project(volume_cam) - true.project(volume_cam)
    dn = np.linalg.norm(duv, axis=1)
    R = frame_rotation(est, true, volume_cam)
    dn_free = np.linalg.norm(est.project(volume_cam @ R.T) - true.project(volume_cam), axis=1)
    names = ("fx", "fy", "cx", "cy")
    out: dict[str, Any] = {
        "rms_px": float(np.sqrt(np.mean(dn**2))),
        "max_px": float(dn.max()),
        "n_points": len(volume_cam),
        "frame_free": {"rms_px": float(np.sqrt(np.mean(dn_free**2))),
                       "max_px": float(dn_free.max()),
                       "rotation_deg": float(np.degrees(rotation_angle(R))),
                       "R_cam_est_cam": R.tolist()},
    }
    for n_, e, t in zip(names, (est.fx, est.fy, est.cx, est.cy),
                        (true.fx, true.fy, true.cx, true.cy), strict=True):
        out[f"d{n_}_px"] = e - t
    for n_, e, t in zip(("k1", "k2", "p1", "p2", "k3"), est.dist, true.dist, strict=True):
        out[f"d{n_}"] = float(e - t)
    return out


def laser_plane_error(
    est: tuple[np.ndarray, float],
    true: tuple[np.ndarray, float],
    true_camera: Any,
    *,
    z_range: tuple[float, float] = (115.0, 185.0),
    region: tuple[int, int, int, int] | None = None,
) -> dict[str, Any]:
    """Estimated laser plane (camera frame) against the true one, over the measured volume.

    Points of the true plane seen by the camera within ``z_range`` are compared with the
    estimated plane: their perpendicular distance to it (``rms_mm``, ``max_mm``) and how far
    a triangulated point moves along its ray (``ray_rms_mm``, what a scan would feel).
    """
    n_e, d_e = np.asarray(est[0], dtype=np.float64), float(est[1])
    n_t, d_t = np.asarray(true[0], dtype=np.float64), float(true[1])
    if float(n_e @ n_t) < 0:
        n_e, d_e = -n_e, -d_e
    w, h = true_camera.image_size
    x0, y0, rw, rh = region if region is not None else (0, 0, w, h)
    u, v = np.meshgrid(np.linspace(x0, x0 + rw - 1, 64), np.linspace(y0, y0 + rh - 1, 48))
    rays = true_camera.rays(np.column_stack([u.ravel(), v.ravel()]))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_true = -d_t / (rays @ n_t)
        t_est = -d_e / (rays @ n_e)
    p = rays * t_true[:, None]
    ok = np.isfinite(t_true) & (p[:, 2] >= z_range[0]) & (p[:, 2] <= z_range[1])
    out: dict[str, Any] = {
        "angle_deg": float(np.degrees(angle_between(n_e, n_t))),
        "d_diff_mm": d_e - d_t,
        "n_points": int(ok.sum()),
    }
    if ok.any():
        dist = p[ok] @ n_e + d_e
        move = np.abs(t_est[ok] - t_true[ok])
        out.update(rms_mm=float(np.sqrt(np.mean(dist**2))), max_mm=float(np.abs(dist).max()),
                   ray_rms_mm=float(np.sqrt(np.mean(move**2))), ray_max_mm=float(move.max()))
    return out


def transform_error(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> dict[str, Any]:
    """Rigid transform against the true one: rotation angle, translation, and the RMS / max
    displacement of ``points`` (M, 3) mapped by each (e.g. the measured volume in ``cam``)."""
    from crossline.geometry import invert_transform, transform_points

    T_est = np.asarray(T_est, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    D = invert_transform(T_true) @ T_est
    disp = np.linalg.norm(transform_points(T_est, points) - transform_points(T_true, points), axis=1)
    return {
        "rotation_deg": float(np.degrees(rotation_angle(D[:3, :3]))),
        "translation_mm": float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])),
        "rms_mm": float(np.sqrt(np.mean(disp**2))),
        "max_mm": float(disp.max()),
    }

"""The calibrations in the report: which files it can read, their figures, their errors.

``calibration_problem`` says why a camera.json, lasers.json or handeye.json lacks what the
report and the certificate read; ``_calibration`` gives the figures the calibration stages
stored; ``_validation`` (with ``_validation_depths`` and ``_point_depths``, the measured
volume's depth range) scores the calibrations against the simulator's truth over the
measured volume. The calibration certificate shares these. Split from
``crossline.report.accuracy`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from crossline.errors import CrosslineError
from crossline.geometry import make_transform

__all__ = ["calibration_problem"]


def calibration_problem(kind: str, data: dict) -> str | None:
    """Why ``data`` (camera.json, lasers.json or handeye.json as read) is not a ``kind``
    calibration that the report and the certificate can read, or None when it is one: the
    readers' own checks (``Camera.from_dict``, ``LaserPlanes.from_dict``, ``HandEye.from_dict``:
    the key and what was expected)."""
    from crossline.calibrate.handeye import HandEye
    from crossline.camera import Camera
    from crossline.laser import LaserPlanes

    reader = {"camera": Camera, "lasers": LaserPlanes, "handeye": HandEye}[kind]
    try:
        reader.from_dict(data)
    except (KeyError, ValueError, TypeError) as exc:
        return str(exc).strip('"')
    return None


def _calibration(inputs: dict[str, dict | None]) -> dict[str, Any]:
    """Calibration figures as stored by the calibration stages (whatever keys they have)."""
    from crossline.geometry import angle_between, matrix_to_rotvec, rotation_angle

    cal: dict[str, Any] = {}
    cam = inputs.get("camera")
    if cam and "K" in cam:
        K = np.asarray(cam["K"], dtype=np.float64)
        c = {"fx_px": K[0, 0], "fy_px": K[1, 1], "cx_px": K[0, 2], "cy_px": K[1, 2],
             "skew": K[0, 1], "dist": list(np.asarray(cam.get("dist", [np.nan] * 5), float)),
             "image_size": cam.get("image_size"), "rms_px": cam.get("rms_px")}
        views = cam.get("views")
        if isinstance(views, list):
            c["views"] = [{"image": str(v.get("image", i)), "used": bool(v.get("used", True)),
                           "reason": v.get("reason"), "rms_px": v.get("rms_px")}
                          for i, v in enumerate(views) if isinstance(v, dict)]
            c["views_used"] = sum(v["used"] for v in c["views"])
        for k in ("bias_correction", "n_points"):
            if k in cam and not isinstance(cam[k], list | dict):
                c[k] = cam[k]
            elif isinstance(cam.get(k), dict):  # keep its figures, not its history
                c[k] = {kk: v for kk, v in cam[k].items() if isinstance(v, bool | int | float | str)}
        if isinstance(cam.get("board"), dict):
            c["board"] = dict(cam["board"])
        dm = cam.get("distortion_model")
        if isinstance(dm, dict):  # which coefficients were estimated, and why (not the candidates)
            c["distortion_model"] = {k: dm[k] for k in ("selection", "free", "fixed", "reason")
                                     if k in dm}
        unc = cam.get("uncertainty")
        if isinstance(unc, dict):  # its figures, not the covariance matrix
            c["uncertainty"] = {k: unc[k] for k in ("sigma_px", "std", "projection_rms_px") if k in unc}
        cal["camera"] = c
    las = inputs.get("lasers")
    present = [L for L in ("A", "B") if isinstance((las or {}).get(L), dict)]
    if las and "A" in present:  # a one-line rig has plane A alone
        out: dict[str, Any] = {}
        for L in present:
            pl = las[L]
            n = np.asarray(pl["normal"], dtype=np.float64)
            e = {"normal": (n / np.linalg.norm(n)).tolist(), "d_mm": float(pl["d"]) / np.linalg.norm(n)}
            for k, v in pl.items():
                if k not in ("normal", "d") and isinstance(v, int | float) and not isinstance(v, bool):
                    e[k] = v
            out[L] = e
        if "B" in out:
            out["angle_AB_deg"] = float(las.get("angle_AB_deg", np.degrees(angle_between(
                np.asarray(out["A"]["normal"]), np.asarray(out["B"]["normal"])))))
        cal["lasers"] = out
    he = inputs.get("handeye")
    if he and "T_tool_cam" in he:
        X = np.asarray(he["T_tool_cam"], dtype=np.float64)
        h: dict[str, Any] = {"method": he.get("method"), "T_tool_cam": X.tolist()}
        for k, v in he.items():
            if isinstance(v, int | float) and not isinstance(v, bool):
                h[k] = v
        methods = {}
        for name, m in sorted((he.get("methods") or {}).items()):
            if not isinstance(m, dict):
                continue
            Xm = m.get("T_tool_cam", m.get("X"))
            e = {k: v for k, v in m.items() if isinstance(v, int | float) and not isinstance(v, bool)}
            if isinstance(m.get("error"), str):
                e["error"] = m["error"]
            if Xm is not None:
                Xm = np.asarray(Xm, dtype=np.float64)
                if Xm.shape == (4, 4):
                    e["T_tool_cam"] = Xm.tolist()
                    e["rotvec_deg"] = np.degrees(matrix_to_rotvec(Xm[:3, :3])).tolist()
                    D = np.linalg.inv(X) @ Xm
                    e["vs_chosen_rotation_deg"] = float(np.degrees(rotation_angle(D[:3, :3])))
                    e["vs_chosen_translation_mm"] = float(np.linalg.norm(Xm[:3, 3] - X[:3, 3]))
            methods[name] = e
        h["methods"] = methods
        pairs = he.get("pairs")
        if isinstance(pairs, dict):
            h["pairs"] = {k: v for k, v in pairs.items()
                          if isinstance(v, int | float) and not isinstance(v, bool)}
        h["rotvec_deg"] = np.degrees(matrix_to_rotvec(X[:3, :3])).tolist()
        sel = he.get("selection")
        if isinstance(sel, dict):  # why this X: the rule and its figures
            h["selection"] = {k: v for k, v in sel.items() if isinstance(v, int | float | str)
                              and not isinstance(v, bool)}
        chosen = (he.get("methods") or {}).get(he.get("method")) or {}
        for key in ("uncertainty", "noise_model"):  # their figures, not the covariance matrix
            if isinstance(chosen.get(key), dict):
                h[key] = {k: v for k, v in chosen[key].items()
                          if isinstance(v, int | float) and not isinstance(v, bool)}
        cal["handeye"] = h
    return cal


def _validation_depths(given: Any, truth: dict, true_cam: Any,
                       region: tuple[int, int, int, int] | None,
                       point_depths: np.ndarray | None = None) -> tuple[tuple[float, float], str]:
    """The validation volume's depth range and where it came from: the configuration; else
    the depths the scans measured at (1-99 %); else where the true laser planes cross the scan
    window (the rig's whole measuring range); else the drawn rig's window depths."""
    from crossline.report import metrics as mt

    if given is not None:
        return (float(given[0]), float(given[1])), "configuration (report.metrology.volume_z_mm)"
    if point_depths is not None:
        z = point_depths[np.isfinite(point_depths) & (point_depths > 0)]
        if len(z) >= 100:
            lo, hi = np.quantile(z, (0.01, 0.99))
            return (float(lo), float(hi)), "the depths the scans measured at, 1–99 %"
    planes = [(np.asarray(p["normal"], dtype=np.float64), float(p["d"]))
              for p in (truth.get("lasers") or {}).values() if isinstance(p, dict) and "normal" in p]
    if true_cam is not None and planes:
        z = mt.plane_depth_range(true_cam, planes, region=region)
        if z is not None:
            return z, "where the true laser planes cross the scan window"
    depths = (truth.get("rig_draw") or {}).get("window_depths_mm")
    if isinstance(depths, list) and len(depths) >= 2:
        return (float(min(depths)), float(max(depths))), "the drawn rig's window depths"
    raise CrosslineError("truth.json has neither laser planes nor rig_draw.window_depths_mm: "
                         "set report.metrology.volume_z_mm to validate against it")


def _point_depths(points: Path, most: int = 200_000) -> np.ndarray:
    """Depths (z in the camera frame, mm) of a scan's points, an even subsample of ``most``."""
    from crossline.io.columns import read_columns

    try:
        z = read_columns(points, ["z_cam"])["z_cam"]
    except (KeyError, ValueError, OSError):  # an older points file without camera coordinates
        return np.empty(0)
    step = max(1, len(z) // most)
    return np.asarray(z[::step], dtype=np.float64)


def _validation(inputs: dict, truth: dict, rig: Any, met: dict,
                point_depths: np.ndarray | None = None) -> dict[str, Any]:
    """Calibration errors against the simulator's truth, over the measured volume."""
    from crossline.camera import Camera
    from crossline.report import metrics as mt

    v: dict[str, Any] = {}
    true_cam = None
    region = None
    if rig is not None and getattr(rig, "scan_window", None) is not None:
        w = rig.scan_window
        region = (w.x, w.y, w.width, w.height)
        v["volume_region_px"] = list(region)
    tc = truth.get("camera") or {}
    if "K" in tc:
        size = tc.get("image_size")
        if size is None and rig is not None:
            size = (rig.sensor.width, rig.sensor.height)
        true_cam = Camera(np.asarray(tc["K"]), np.asarray(tc.get("dist", [0] * 5)), tuple(size))
    z, v["volume_from"] = _validation_depths(met.get("volume_z_mm"), truth, true_cam, region,
                                             point_depths)
    v["volume_z_mm"] = list(z)
    vol = mt.volume_points(true_cam, z_range=z, region=region) if true_cam is not None else None
    cam = inputs.get("camera")
    if cam and true_cam is not None and "K" in cam:
        est = Camera(np.asarray(cam["K"]), np.asarray(cam["dist"]), tuple(cam["image_size"]))
        v["camera"] = mt.camera_error(est, true_cam, vol)
    # the estimated camera frame's rotation against the true one (see mt.frame_rotation): the
    # planes and hand-eye are compared also in the frame turned back by it, so that a figure
    # shows what bends the measured points, apart from what the arm's frame does not feel
    R = np.asarray(v["camera"]["frame_free"]["R_cam_est_cam"]) if "camera" in v else None
    las = inputs.get("lasers")
    tl = truth.get("lasers") or {}
    if las and true_cam is not None:
        v["lasers"] = {}
        for L in ("A", "B"):
            if L in las and L in tl:
                v["lasers"][L] = mt.laser_plane_error(
                    (las[L]["normal"], las[L]["d"]), (tl[L]["normal"], tl[L]["d"]), true_cam,
                    z_range=z, region=region)
                if R is not None:
                    v["lasers"][L]["frame_free"] = mt.laser_plane_error(
                        (R.T @ np.asarray(las[L]["normal"], dtype=np.float64), las[L]["d"]),
                        (tl[L]["normal"], tl[L]["d"]), true_cam, z_range=z, region=region)
        if "A" in tl and "B" in tl and "A" in las and "B" in las:
            ang_t = float(np.degrees(mt.angle_between(np.asarray(tl["A"]["normal"], float),
                                                      np.asarray(tl["B"]["normal"], float))))
            ang_e = float(np.degrees(mt.angle_between(np.asarray(las["A"]["normal"], float),
                                                      np.asarray(las["B"]["normal"], float))))
            v["lasers"]["angle_AB_error_deg"] = ang_e - ang_t
    he = inputs.get("handeye")
    if he and "T_tool_cam" in truth and vol is not None:
        Tt = np.asarray(truth["T_tool_cam"], dtype=np.float64)
        h = {"chosen": mt.transform_error(np.asarray(he["T_tool_cam"]), Tt, vol),
             "method": he.get("method")}
        if R is not None:
            h["chosen"]["frame_free"] = mt.transform_error(
                np.asarray(he["T_tool_cam"]) @ make_transform(R, np.zeros(3)), Tt, vol)
        for name, m in sorted((he.get("methods") or {}).items()):
            Xm = m.get("T_tool_cam", m.get("X")) if isinstance(m, dict) else None
            if Xm is not None and np.asarray(Xm).shape == (4, 4):
                h[name] = mt.transform_error(np.asarray(Xm, dtype=np.float64), Tt, vol)
        v["handeye"] = h
    return v

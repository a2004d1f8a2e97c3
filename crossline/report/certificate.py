"""The calibration certificate of a capture: the calibrations alone, checked against limits.

Built for every capture whose camera calibrates, with or without laser, hand-eye or scan
data: ``run_certificate`` reads whichever of camera.json, lasers.json and handeye.json the
capture allowed (the check summary says which and why not the others) and writes

- ``calibration.json``: every parameter with its 1σ, the per-view residuals, the sensor's
  coverage by board points and the mean residual vector over it, the plane residuals per
  board pose, the hand-eye consistency, each check against its limit and PASS/FAIL;
- ``calibration.pdf``: the same as pages (the accuracy report's calibration pages, plus the
  certificate's summary and the coverage).

Both deterministic: same inputs, same bytes (no dates in the PDF).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from crossline import __version__
from crossline.errors import CrosslineError
from crossline.io.atomic import atomic_path, to_jsonable, write_json
from crossline.io.settings import read_settings
from crossline.report.accuracy import (
    ReportData,
    _calibration,
    _check,
    _git_commit,
    _sha256,
    _validation,
    calibration_problem,
)

__all__ = ["DEFAULT_LIMITS", "build_certificate", "coverage", "load_limits", "run_certificate"]

log = logging.getLogger(__name__)

FORMAT = "crossline-certificate/1"

DEFAULT_LIMITS: dict[str, Any] = {
    "camera_rms_px": 0.2,  # reprojection RMS over the views used
    "camera_view_rms_px": 0.4,  # worst reprojection RMS of one used view
    "projection_rms_px": 0.1,  # predicted projection error over the scan window (1σ RMS)
    "coverage_share": 0.5,  # share of the sensor's cells holding a board point
    "coverage_grid": [12, 8],  # cells across and down the sensor
    "laser_rms_mm": 0.01,  # RMS distance of the stripe points to their plane
    "laser_pose_rms_mm": 0.02,  # worst RMS of one board pose against its plane
    "handeye_consistency_mm": 0.05,  # spread of the board's base-frame position over the views
}
CAMERA_PARAMETERS = (("fx", "px"), ("fy", "px"), ("cx", "px"), ("cy", "px"), ("k1", ""),
                     ("k2", ""), ("p1", ""), ("p2", ""), ("k3", ""))


def load_limits(config: str | Path | dict | None) -> tuple[dict, dict]:
    """The configuration (dict, JSON file or text, or None) and the certificate's limits."""
    full = read_settings(config, "certificate configuration")
    limits = dict(DEFAULT_LIMITS)
    given = full.get("certificate", {})
    if not isinstance(given, dict):
        raise CrosslineError("certificate: must be a mapping of limits")
    unknown = sorted(set(given) - set(DEFAULT_LIMITS))
    if unknown:
        raise CrosslineError(f"certificate: unknown limit(s) {unknown}; known: {sorted(DEFAULT_LIMITS)}")
    limits.update(given)
    for k, v in limits.items():
        if k == "coverage_grid":
            if not (isinstance(v, list | tuple) and len(v) == 2
                    and all(isinstance(x, int) and not isinstance(x, bool) and x >= 1 for x in v)):
                raise CrosslineError(f"certificate.coverage_grid must be two integers >= 1, got {v!r}")
        elif not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
            raise CrosslineError(f"certificate.{k} must be a number >= 0, got {v!r}")
    return full, limits


def coverage(uv: np.ndarray, size: tuple[int, int], grid: tuple[int, int]) -> dict[str, Any]:
    """Board points (N, 2) px over the sensor: points per cell of a ``grid`` (cols, rows), share covered."""
    w, h = size
    nc, nr = grid
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
    c = np.clip(((uv[inside, 0] + 0.5) * nc / w).astype(np.int64), 0, nc - 1)
    r = np.clip(((uv[inside, 1] + 0.5) * nr / h).astype(np.int64), 0, nr - 1)
    counts = np.bincount(r * nc + c, minlength=nr * nc).reshape(nr, nc)
    return {"grid": [nc, nr], "points": int(inside.sum()), "cells_covered": int((counts > 0).sum()),
            "cells": nr * nc, "share": float((counts > 0).mean()), "counts": counts}


def _residual_field(uv: np.ndarray, du: np.ndarray, size: tuple[int, int],
                    grid: tuple[int, int]) -> dict[str, Any]:
    """Mean residual vector (px) per cell of the grid (NaN where no point falls)."""
    w, h = size
    nc, nr = grid
    c = np.clip(((uv[:, 0] + 0.5) * nc / w).astype(np.int64), 0, nc - 1)
    r = np.clip(((uv[:, 1] + 0.5) * nr / h).astype(np.int64), 0, nr - 1)
    k = r * nc + c
    n = np.bincount(k, minlength=nr * nc)
    with np.errstate(invalid="ignore", divide="ignore"):
        mu = np.bincount(k, du[:, 0], nr * nc) / n
        mv = np.bincount(k, du[:, 1], nr * nc) / n
    return {"grid": [nc, nr], "mean_du_px": mu.reshape(nr, nc), "mean_dv_px": mv.reshape(nr, nc)}


def _camera_section(raw: dict, cal: dict, limits: dict, rows: list, plots: dict) -> dict[str, Any]:
    from crossline.report.pages import _residuals_by_view

    c = cal["camera"]
    std = (c.get("uncertainty") or {}).get("std") or {}
    values = {"fx": c["fx_px"], "fy": c["fy_px"], "cx": c["cx_px"], "cy": c["cy_px"],
              **dict(zip(("k1", "k2", "p1", "p2", "k3"), c["dist"], strict=True))}
    dm = raw.get("distortion_model") if isinstance(raw.get("distortion_model"), dict) else {}
    free = dm.get("free")
    fixed = {n for n, _ in CAMERA_PARAMETERS[4:]} - set(free) if isinstance(free, list) else set()
    params = [{"name": n, "value": float(values[n]), "sigma": std.get(n), "unit": u,
               "fixed": n in fixed} for n, u in CAMERA_PARAMETERS]
    out: dict[str, Any] = {"parameters": params, "rms_px": c.get("rms_px"),
                           "image_size": c.get("image_size"), "board": c.get("board"),
                           "projection_rms_px": (c.get("uncertainty") or {}).get("projection_rms_px")}
    if dm:  # what was fixed and why, not every candidate model
        out["distortion_model"] = {k: dm[k] for k in ("selection", "free", "fixed", "reason")
                                   if k in dm}
    res = raw.get("residuals") if isinstance(raw.get("residuals"), dict) else {}
    views = []
    for v in c.get("views") or []:
        e = dict(v)
        r = res.get(v["image"])
        if r is not None:
            r = np.asarray(r, dtype=np.float64).reshape(-1, 2)
            e["points"] = len(r)
            e["max_px"] = float(np.sqrt((r ** 2).sum(1)).max()) if len(r) else None
        views.append(e)
    out["views"] = views
    out["views_used"] = sum(bool(v["used"]) for v in views)
    size = tuple(c.get("image_size") or (0, 0))
    grid = tuple(limits["coverage_grid"])
    found = _residuals_by_view(raw) if size[0] else None
    if found is not None:
        uv, du = found
        cov = coverage(uv, size, grid)
        plots["coverage"] = {"uv": uv, "counts": cov["counts"], "size": size}
        out["coverage"] = cov
        out["residual_field"] = _residual_field(uv, du, size, grid)
    used_rms = [v["rms_px"] for v in views if v["used"] and isinstance(v.get("rms_px"), int | float)]
    _check(rows, "camera_rms_px", "camera: reprojection RMS", None, c.get("rms_px"), "px",
           limits["camera_rms_px"])
    _check(rows, "camera_view_rms_px", "camera: worst view's RMS", None,
           max(used_rms) if used_rms else None, "px", limits["camera_view_rms_px"])
    proj = out["projection_rms_px"] or {}
    _check(rows, "projection_rms_px", "camera: predicted error, scan window (1σ)", None,
           proj.get("scan_window"), "px", limits["projection_rms_px"])
    _check(rows, "coverage_share", f"camera: sensor covered ({grid[0]}×{grid[1]} cells)", None,
           out["coverage"]["share"] if "coverage" in out else None, "%", limits["coverage_share"],
           comparison=">=")
    _check(rows, "camera_views_used", "camera: views used", None, out["views_used"], "", None,
           note=f"of {len(views)}")
    return out


def _lasers_section(raw: dict, cal: dict, limits: dict, rows: list) -> dict[str, Any]:
    la = cal["lasers"]
    out: dict[str, Any] = {}
    for L in sorted(k for k in la if isinstance(la[k], dict) and "normal" in la[k]):
        e = dict(la[L])
        src = raw.get(L) or {}
        for k, v in src.items():  # any uncertainty the calibration stored (σ of n and d)
            if ("std" in k or "sigma" in k or k == "uncertainty") and k not in e:
                e[k] = v
        poses = []
        for q in src.get("poses") or []:
            if isinstance(q, dict):
                poses.append({k: q.get(k) for k in ("pose", "rms_mm", "n_used", "n_points",
                                                     "board_rms_px", "reason") if k in q})
        e["poses"] = poses
        out[L] = e
        _check(rows, f"laser_{L}_rms_mm", f"laser {L}: plane fit RMS", None, e.get("rms_mm"), "mm",
               limits["laser_rms_mm"])
        worst = [q["rms_mm"] for q in poses if isinstance(q.get("rms_mm"), int | float)]
        _check(rows, f"laser_{L}_pose_rms_mm", f"laser {L}: worst pose's RMS", None,
               max(worst) if worst else None, "mm", limits["laser_pose_rms_mm"],
               note=f"{len(worst)} poses")
    if "angle_AB_deg" in la:
        out["angle_AB_deg"] = la["angle_AB_deg"]
        _check(rows, "angle_AB_deg", "laser planes: angle between A and B", None,
               la["angle_AB_deg"], "°", None)
    return out


def _handeye_section(raw: dict, cal: dict, limits: dict, rows: list) -> dict[str, Any]:
    he = dict(cal["handeye"])
    chosen = (raw.get("methods") or {}).get(raw.get("method")) or {}
    cons = chosen.get("board_consistency_mm", raw.get("board_consistency_mm"))
    he["board_consistency_mm"] = cons
    _check(rows, "handeye_consistency_mm", "hand-eye: board consistency", None, cons, "mm",
           limits["handeye_consistency_mm"], note=str(he.get("method") or ""))
    u = he.get("uncertainty") or {}
    _check(rows, "handeye_point_mm", "hand-eye: predicted point error (1σ)", None,
           u.get("point_mm_1sigma_at_board_distance"), "mm", None)
    return he


def build_certificate(
    capture: Path, summary: dict | None, calibrations: dict[str, Path | None], config: Any = None,
) -> ReportData:
    """Everything the certificate shows: metrics (JSON-ready) and the plots' arrays."""
    from crossline.io.capture import read_rig

    capture = Path(capture)
    full, limits = load_limits(config)
    rig = read_rig(capture / "rig.yaml")
    files: list[tuple[str, str, Path]] = [("capture", "rig.yaml", capture / "rig.yaml")]
    inputs: dict[str, dict | None] = {}
    for k in ("camera", "lasers", "handeye"):
        p = calibrations.get(k)
        inputs[k] = None
        if p is None:
            continue
        p = Path(p)
        try:
            inputs[k] = json.loads(p.read_text())
        except OSError as exc:
            raise CrosslineError(f"{p}: cannot read the {k} calibration ({exc.strerror})") from exc
        except ValueError as exc:
            raise CrosslineError(f"{p}: not a {k} calibration file (invalid JSON: {exc})") from exc
        if not isinstance(inputs[k], dict):
            raise CrosslineError(f"{p}: not a {k} calibration file (expected a JSON object)")
        if k == "camera":
            from crossline.camera import Camera

            Camera.load(p)  # a usable model (finite K, dist) or a named error
        why = calibration_problem(k, inputs[k])
        if why is not None:
            raise CrosslineError(f"{p}: not a {k} calibration file ({why})")
        files.append(("interim", f"calibration/{k}.json", p))
    truth = None
    if (capture / "truth.json").is_file():
        files.append(("capture", "truth.json", capture / "truth.json"))
        try:
            truth = json.loads((capture / "truth.json").read_text())
        except ValueError:
            log.warning("%s: unreadable; no validation", capture / "truth.json")
    try:
        cal = _calibration(inputs)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise CrosslineError(f"{capture.name}: a calibration file lacks what the certificate "
                             f"needs ({type(exc).__name__}: {exc})") from exc
    stages = (summary or {}).get("stages") or {}
    date = rig.extra.get("capture_date")
    m: dict[str, Any] = {
        "format": FORMAT,
        "title": "crossline calibration certificate",
        "capture": {"name": capture.name, "date": str(date) if date is not None else None,
                    "simulated": truth is not None, "scans": sorted(rig.scans),
                    "lasers": list(getattr(rig, "lasers", ("A", "B")))},
        "software": {"crossline_version": __version__, "git_commit": _git_commit()},
        "stages": stages,
        "calibration": cal,
    }
    plots: dict[str, Any] = {"camera_raw": inputs["camera"], "lasers_raw": inputs["lasers"],
                             "handeye_raw": inputs["handeye"], "rig": rig}
    rows: list[dict[str, Any]] = []
    for key, name, section in (("camera", "camera", _camera_section),
                               ("lasers", "lasers", _lasers_section),
                               ("handeye", "handeye", _handeye_section)):
        if cal.get(key):
            args = (inputs[key], cal, limits, rows) + ((plots,) if key == "camera" else ())
            m[name] = section(*args)
        else:
            why = (stages.get(f"calibrate_{key}") or {}).get("why")
            m[name] = None
            m[f"{name}_missing"] = why or f"no {key}.json given"
    m["checks"] = rows
    statuses = [r["status"] for r in rows]
    m["result"] = ("FAIL" if "FAIL" in statuses else
                   "INCOMPLETE" if "N/A" in statuses or "PASS" not in statuses else "PASS")
    # the same validation volume as the accuracy report's
    given_z = ((full.get("report") or {}).get("metrology") or {}).get("volume_z_mm")
    m["validation"] = _validation(inputs, truth, rig, {"volume_z_mm": given_z}) if truth else None
    m["provenance"] = {
        "crossline_version": __version__, "git_commit": m["software"]["git_commit"],
        "capture_date": m["capture"]["date"], "tolerances": limits, "metrology": {},
        "parameters": full,
        "inputs": [{"root": r, "file": f, "sha256": _sha256(p), "bytes": p.stat().st_size}
                   for r, f, p in sorted(set(files), key=lambda x: (x[0], x[1]))],
    }
    return ReportData(to_jsonable(m), plots)


def run_certificate(
    capture: Path, pdf: Path, out_json: Path, *, summary: Path | None = None,
    camera: Path | None = None, lasers: Path | None = None, handeye: Path | None = None,
    config: Any = None,
) -> dict[str, Any]:
    """The certificate stage: write ``calibration.json`` and ``calibration.pdf``."""
    from crossline.report.certificate_pages import render_certificate

    capture = Path(capture)
    if not (capture / "rig.yaml").is_file():
        raise CrosslineError(f"{capture}: not a capture folder (no rig.yaml)")
    if camera is None:
        raise CrosslineError(f"{capture.name}: a calibration certificate needs the camera "
                             "calibration (--camera camera.json)")
    summ = None
    if summary is not None:
        try:
            summ = json.loads(Path(summary).read_text())
        except (OSError, ValueError) as exc:
            raise CrosslineError(f"{summary}: cannot read the check summary ({exc})") from exc
    data = build_certificate(capture, summ, {"camera": camera, "lasers": lasers,
                                             "handeye": handeye}, config)
    with atomic_path(pdf) as tmp:
        render_certificate(data, tmp)
    write_json(out_json, data.metrics)
    log.info("calibration certificate %s: %s", capture.name, data.metrics["result"])
    return data.metrics

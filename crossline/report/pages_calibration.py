"""The calibration pages of the accuracy report: camera intrinsics with the per-view errors and
residual vectors (read from camera.json whatever its layout), the laser planes with their
residuals and where they cut the image, and hand-eye X by each method. Split from
:mod:`crossline.report.pages` (issue 21.3); the calibration certificate draws them too.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib.patches
import matplotlib.ticker
import numpy as np
from matplotlib.figure import Figure

from crossline.report.pages_common import (
    A4,
    COLOURS,
    LASER_COLOURS,
    LEFT,
    MONO,
    RIGHT,
    Page,
    fmt,
    pretty,
)

__all__ = ["page_camera", "page_handeye", "page_lasers"]


def _residuals_by_view(raw: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """camera.json's layout: ``residuals`` {image: (N, 2)} with ``T_cam_board`` {image: 4×4}
    and ``board``; the points are where the board's circles project."""
    from crossline.board import Board
    from crossline.camera import Camera
    from crossline.geometry import transform_points

    res, poses, board = raw.get("residuals"), raw.get("T_cam_board"), raw.get("board")
    if not (isinstance(res, dict) and isinstance(poses, dict) and isinstance(board, dict)):
        return None
    try:
        b = Board(**{k: board[k] for k in ("pattern", "cols", "rows", "spacing", "diameter",
                                           "circles") if k in board})
        cam = Camera(np.asarray(raw["K"]), np.asarray(raw["dist"]), tuple(raw["image_size"]))
        obj = b.object_points()
        uv, du = [], []
        for name in sorted(res):
            r = np.asarray(res[name], dtype=np.float64).reshape(-1, 2)
            if name not in poses or len(r) != len(obj):
                continue
            uv.append(cam.project(transform_points(np.asarray(poses[name], dtype=np.float64), obj)))
            du.append(r)
    except (KeyError, TypeError, ValueError):
        return None
    return (np.concatenate(uv), np.concatenate(du)) if uv else None


def _find_residuals(raw: dict | None) -> tuple[np.ndarray, np.ndarray] | None:
    """Image points (N, 2) and residual vectors (N, 2) from camera.json, whatever its layout."""
    if not raw:
        return None
    by_view = _residuals_by_view(raw)
    if by_view is not None:
        return by_view
    cands: list[Any] = []
    r = raw.get("residuals")
    if isinstance(r, dict):
        cands.append(r)
    elif isinstance(r, list):
        cands.extend(x for x in r if isinstance(x, dict))
    for v in raw.get("views", []) or []:
        if isinstance(v, dict):
            cands.append(v)
            if isinstance(v.get("residuals"), dict):
                cands.append(v["residuals"])
    uv, du = [], []
    for c in cands:
        a = next((c[k] for k in ("uv", "points", "image_points", "detected", "observed")
                  if k in c), None)
        b = next((c[k] for k in ("duv", "residuals", "vectors", "residual", "error")
                  if k in c and not isinstance(c[k], dict)), None)
        if a is None or b is None:
            continue
        try:
            a = np.asarray(a, dtype=np.float64).reshape(-1, 2)
            b = np.asarray(b, dtype=np.float64).reshape(-1, 2)
        except (ValueError, TypeError):
            continue
        if len(a) == len(b) and len(a):
            uv.append(a)
            du.append(b)
    if not uv:
        return None
    return np.concatenate(uv), np.concatenate(du)


def page_camera(m: dict[str, Any], plots: dict[str, Any]) -> Figure:
    """Intrinsics, per-view reprojection errors and the residual vectors."""
    p = Page(m, "Calibration: camera intrinsics")
    c = m["calibration"].get("camera")
    if not c:
        p.text("No camera.json: the camera calibration is missing.", color=COLOURS["N/A"])
        return p.fig
    d = c["dist"]
    unc = c.get("uncertainty") or {}
    std = unc.get("std") or {}

    def sd(name: str, unit: str, digits: int) -> str:
        return fmt(std[name], unit, digits) if name in std else "–"

    rows = [[n, fmt(c[f"{n}_px"], "px", 3), sd(n, "px", 4)] for n in ("fx", "fy", "cx", "cy")]
    rows2 = [[n, fmt(d[i], "", dg), sd(n, "", dg)]
             for i, (n, dg) in enumerate((("k1", 6), ("k2", 6), ("p1", 7), ("p2", 7), ("k3", 6)))]
    y0 = p.y
    p.table(["Intrinsic", "Value", "1σ"], rows, [LEFT, LEFT + 0.08, LEFT + 0.22, LEFT + 0.32],
            aligns=["left", "right", "right"])
    y1 = p.y
    p.y = y0
    p.table(["Distortion", "Value", "1σ"], rows2, [LEFT + 0.38, LEFT + 0.46, LEFT + 0.62, LEFT + 0.76],
            aligns=["left", "right", "right"])
    p.y = min(p.y, y1)
    proj = unc.get("projection_rms_px") or {}
    if proj:
        p.text("Predicted from these views (1σ, from the residuals and the fit's Jacobian): a point "
               f"is projected {fmt(proj.get('sensor'), 'px', 4)} RMS from where the true camera "
               f"would put it over the sensor, {fmt(proj.get('scan_window'), 'px', 4)} over the "
               f"scan window; residual σ {fmt(unc.get('sigma_px'), 'px', 4)} per coordinate. "
               "More views, or steeper tilts, lower it.", size=8.2)
    dm = c.get("distortion_model") or {}
    if dm.get("reason"):
        p.text(f"Distortion model ({dm.get('selection', '–')}): {dm['reason']}.", size=8.2)
    size = c.get("image_size")
    bc = c.get("bias_correction")
    if (c.get("board") or {}).get("pattern") == "chessboard":
        bias = "; chessboard corners fitted as X-junctions (no perspective bias to correct)"
    elif isinstance(bc, dict):
        on = bc.get("enabled")
        bias = "; circle-centre bias correction " + ("on" if on else "off" if on is not None else "–")
        if on and "mean_shift_px" in bc:
            bias += (f" (mean shift {fmt(bc['mean_shift_px'], 'px')}, max "
                     f"{fmt(bc.get('max_shift_px'), 'px')})")
    elif bc is not None:
        bias = f"; circle-centre bias correction {'on' if bc else 'off'}"
    else:
        bias = ""
    p.text((f"Image size {size[0]} × {size[1]} px; " if size else "")
           + f"reprojection RMS {fmt(c.get('rms_px'), 'px')}" + bias)
    views = c.get("views") or []
    if views:
        ax = p.axes(2.6, left=LEFT + 0.06)
        x = np.arange(len(views))
        vals = np.array([v["rms_px"] if v["rms_px"] is not None else np.nan for v in views], float)
        used = np.array([v["used"] for v in views])
        ax.bar(x[used], np.nan_to_num(vals[used]), color="#4c72b0", label="used")
        if (~used).any():
            ax.bar(x[~used], np.nan_to_num(vals[~used]), color="#dddddd", edgecolor="#cf222e",
                   hatch="//", label="rejected")
        ax.set_xticks(x)
        ax.set_xticklabels([Path(v["image"]).stem for v in views], rotation=60, ha="right",
                           fontsize=6.5)
        ax.set_ylabel("reprojection RMS (px)")
        ax.set_title(f"Per-view reprojection error ({int(used.sum())} of {len(views)} views used)",
                     loc="left")
        if c.get("rms_px") is not None:
            ax.axhline(c["rms_px"], color="black", lw=0.8, ls="--", label="overall RMS")
        ax.legend(loc="upper right")
        p.gap(0.35)
        rej = [v for v in views if not v["used"]]
        for v in rej[:6]:
            p.text(f"rejected {v['image']}: {v.get('reason') or 'no reason given'}", size=7.5,
                   color=COLOURS["FAIL"])
    res = _find_residuals(plots.get("camera_raw"))
    if res is None:
        p.gap(0.2)
        p.text("camera.json holds no residual vectors: no residual plot.", color=COLOURS["N/A"])
        return p.fig
    uv, du = res
    n = np.linalg.norm(du, axis=1)
    p.gap(0.05)
    h = 3.0 / A4[1]
    y = p.y - 0.2 / A4[1] - h
    ax1 = p.fig.add_axes((LEFT + 0.06, y, 0.46, h))
    scale = float(np.percentile(n, 95)) if n.size else 1.0
    w, hh = (size if size else (uv[:, 0].max(), uv[:, 1].max()))
    ax1.quiver(uv[:, 0], uv[:, 1], du[:, 0], du[:, 1], n, angles="xy", scale_units="width",
               scale=20 * max(scale, 1e-9), width=0.002, cmap="viridis")
    ax1.set_xlim(0, w)
    ax1.set_ylim(hh, 0)
    ax1.set_aspect("equal")
    ax1.set_xlabel("u (px)")
    ax1.set_ylabel("v (px)")
    ax1.set_title(f"Residual vectors of {len(uv):,d} points (an arrow 1/20 of the width "
                  f"= {fmt(scale, 'px', 3)})", loc="left", fontsize=8)
    ax2 = p.fig.add_axes((LEFT + 0.62, y, 0.25, h))
    ax2.scatter(du[:, 0], du[:, 1], s=1.5, color="#4c72b0", alpha=0.5, rasterized=True)
    lim = float(np.percentile(np.abs(du), 99.5)) * 1.1 or 1.0
    ax2.set_xlim(-lim, lim)
    ax2.set_ylim(-lim, lim)
    ax2.set_aspect("equal")
    ax2.axhline(0, color="#999999", lw=0.5)
    ax2.axvline(0, color="#999999", lw=0.5)
    ax2.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(4, symmetric=True))
    ax2.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(4, symmetric=True))
    ax2.set_xlabel("Δu (px)")
    ax2.set_ylabel("Δv (px)")
    ax2.set_title(f"RMS {fmt(float(np.sqrt(np.mean(n ** 2))), 'px')}", loc="left", fontsize=8)
    p.y = y - 0.5 / A4[1]
    return p.fig


def _numeric_lists(d: dict) -> dict[str, np.ndarray]:
    out = {}
    for k, v in d.items():
        if isinstance(v, list) and v and all(isinstance(x, int | float) for x in v) and \
                "resid" in k.lower():
            out[k] = np.asarray(v, dtype=np.float64)
    return out


def _pose_rms(d: dict) -> list[tuple[str, float, int | None]]:
    """Per-pose (name, RMS, points) from a laser entry, if it lists poses."""
    poses = d.get("poses") or d.get("views") or d.get("points_per_pose")
    out = []
    if isinstance(poses, list):
        for i, q in enumerate(poses):
            if isinstance(q, dict):
                rms = q.get("rms_mm", q.get("rms"))
                n = q.get("n", q.get("points", q.get("n_points")))
                if isinstance(rms, int | float):
                    out.append((str(q.get("pose", q.get("name", i))), float(rms),
                                n if isinstance(n, int) else None))
    elif isinstance(poses, dict):
        for k, q in poses.items():
            if isinstance(q, dict) and isinstance(q.get("rms_mm", q.get("rms")), int | float):
                n = q.get("n", q.get("points", q.get("n_points")))
                out.append((str(k), float(q.get("rms_mm", q.get("rms"))),
                            n if isinstance(n, int) else None))
    return out


def page_lasers(m: dict[str, Any], plots: dict[str, Any]) -> Figure:
    """The two laser planes: equations, residuals, their angle and where they cut the image."""
    from crossline.camera import Camera

    p = Page(m, "Calibration: laser planes")
    la = m["calibration"].get("lasers")
    if not la:
        p.text("No lasers.json: the laser-plane calibration is missing.", color=COLOURS["N/A"])
        return p.fig
    rows = []
    order = ["rms_mm", "n_used", "n_points", "n_rejected"]
    lasers = [L for L in ("A", "B") if L in la]  # a one-line rig has A alone
    found = {k for L in lasers for k in la[L] if k not in ("normal", "d_mm")}
    extra_keys = [k for k in order if k in found]  # the calibration's own figures only
    for L in lasers:
        n = la[L]["normal"]
        rows.append([L, f"[{n[0]:+.6f}, {n[1]:+.6f}, {n[2]:+.6f}]", fmt(la[L]["d_mm"], "mm", 4)]
                    + [fmt(la[L].get(k), "", 4 if k.endswith("_mm") else 0)
                       for k in extra_keys[:3]])
    p.table(["Laser", "normal n (camera frame)", "d", *(pretty(k) for k in extra_keys[:3])], rows,
            [LEFT, LEFT + 0.06, LEFT + 0.36, LEFT + 0.49, LEFT + 0.61, LEFT + 0.73],
            aligns=["left", "left", "right", "right", "right", "right"], size=7.8)
    if "angle_AB_deg" in la:
        p.text(f"Plane n · p + d = 0 in the camera frame (mm). Angle between the planes: "
               f"{fmt(la['angle_AB_deg'], '°', 4)} (90° is a perfect cross).")
    else:
        p.text("Plane n · p + d = 0 in the camera frame (mm). One-line rig: laser A alone.")
    raw = plots.get("lasers_raw") or {}
    cam_raw = plots.get("camera_raw")
    rig = plots.get("rig")
    # where the planes cut the image, at three depths of the measured volume
    if cam_raw and "K" in cam_raw:
        cam = Camera(np.asarray(cam_raw["K"]), np.asarray(cam_raw["dist"]),
                     tuple(cam_raw["image_size"]))
        ax = p.axes(3.0, left=LEFT + 0.06, right=RIGHT - 0.02)
        W, H = cam.image_size
        ax.add_patch(matplotlib.patches.Rectangle((0, 0), W, H, fill=False, ec="black", lw=0.8))
        if rig is not None and rig.scan_window is not None:
            sw = rig.scan_window
            ax.add_patch(matplotlib.patches.Rectangle((sw.x, sw.y), sw.width, sw.height, fill=False,
                                                      ec="#999999", ls="--", lw=0.8,
                                                      label="scan window"))
        for L in lasers:
            nrm = np.asarray(la[L]["normal"])
            d = la[L]["d_mm"]
            for z, ls in ((115.0, ":"), (150.0, "-"), (185.0, "--")):
                # the line n·p + d = 0 at depth z: n_x x + n_y y = -d - n_z z
                a = nrm[:2]
                rhs = -d - nrm[2] * z
                if np.linalg.norm(a) < 1e-9:
                    continue
                p0 = a * rhs / (a @ a)
                t = np.linspace(-0.5, 0.5, 200) * z
                dirn = np.array([-a[1], a[0]]) / np.linalg.norm(a)
                xy = p0[None] + t[:, None] * dirn[None]
                uv = cam.project(np.column_stack([xy, np.full(len(xy), z)]))
                ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
                if ok.any():
                    ax.plot(uv[ok, 0], uv[ok, 1], ls, color=LASER_COLOURS[L], lw=1.2,
                            label=f"laser {L}, z = {z:.0f} mm")
        ax.set_xlim(-50, W + 50)
        ax.set_ylim(H + 50, -50)
        ax.set_aspect("equal")
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
        ax.set_title("Where the planes cut the image at 115, 150 and 185 mm from the camera",
                     loc="left")
        ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=6.5)
    # residuals: per-pose RMS or a residual histogram, whichever the file holds
    per_pose = {L: _pose_rms(raw.get(L, {})) for L in lasers}
    lists = {L: _numeric_lists(raw.get(L, {})) for L in lasers}
    if any(lists.values()):
        ax = p.axes(2.4, left=LEFT + 0.06)
        for L in lasers:
            for k, v in list(lists[L].items())[:1]:
                ax.hist(v, bins=50, histtype="step", color=LASER_COLOURS[L], lw=1.2,
                        label=f"laser {L}: {k}, RMS {fmt(float(np.sqrt(np.mean(v ** 2))), 'mm')}")
        ax.set_xlabel("distance of the stripe points to their plane (mm)")
        ax.set_ylabel("points (count)")
        ax.set_title("Residuals of the plane fits", loc="left")
        ax.legend(loc="upper right")
    elif any(per_pose.values()):
        ax = p.axes(2.4, left=LEFT + 0.06)
        labels, x0 = [], 0
        for L in lasers:
            vals = per_pose[L]
            xs = np.arange(x0, x0 + len(vals))
            ax.bar(xs, [v[1] for v in vals], color=LASER_COLOURS[L], label=f"laser {L}")
            labels += [f"{L}:{v[0]}" for v in vals]
            x0 += len(vals) + 1
            labels += [""]
        ax.set_xticks(np.arange(len(labels)))
        ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=6.5)
        ax.set_ylabel("RMS distance to the plane (mm)")
        ax.set_title("Residuals of the plane fits per board pose", loc="left")
        ax.set_ylim(0, max(v[1] for L in lasers for v in per_pose[L]) * 1.3)
        ax.legend(loc="upper left", ncol=2)
    else:
        p.gap(0.2)
        p.text("lasers.json holds no per-point or per-pose residuals: only the RMS above.",
               color=COLOURS["N/A"])
    return p.fig


def page_handeye(m: dict[str, Any]) -> Figure:
    """Hand-eye X by each method, with the differences between methods and their residuals."""
    p = Page(m, "Calibration: hand-eye (X = T_tool_cam)")
    he = m["calibration"].get("handeye")
    if not he:
        p.text("No handeye.json: the hand-eye calibration is missing.", color=COLOURS["N/A"])
        return p.fig
    X = np.asarray(he["T_tool_cam"])
    p.text(f"Chosen: {he.get('method') or 'unknown method'}", size=9, weight="bold")
    for r in range(4):
        p.text("  ".join(f"{X[r, c]:+12.6f}" for c in range(4)), size=8, family=MONO)
    p.text("rotation part as a rotation vector (deg): "
           + ", ".join(f"{v:+.5f}" for v in he["rotvec_deg"]), size=8)
    sel = he.get("selection") or {}
    if sel.get("rule"):
        p.text(f"Why this X: {sel['rule']}. Best algebraic method "
               f"{sel.get('best_opencv', '–')}: board consistency "
               f"{fmt(sel.get('best_opencv_consistency_mm'), 'mm', 4)}; the chosen X's is "
               f"{fmt(sel.get('vs_best_opencv_percent'), '', 2, signed=True)} % of it higher "
               "(+) or lower (−).", size=7.8)
    p.gap(0.1)
    methods = he.get("methods") or {}
    if methods:
        rows = []
        for name, e in methods.items():
            X_m = e.get("T_tool_cam")
            t = np.asarray(X_m)[:3, 3] if X_m is not None else None
            rows.append([name + (" (chosen)" if name == he.get("method") else ""),
                         ", ".join(f"{v:+.4f}" for v in e["rotvec_deg"]) if "rotvec_deg" in e
                         else "–",
                         ", ".join(f"{v:+.4f}" for v in t) if t is not None else "–",
                         fmt(e.get("vs_chosen_rotation_deg"), "°", 4),
                         fmt(e.get("vs_chosen_translation_mm"), "mm", 4)])
        p.table(["Method", "rotation vector (deg)", "translation (mm)", "Δrot", "Δtrans"], rows,
                [LEFT, LEFT + 0.17, LEFT + 0.42, LEFT + 0.66, LEFT + 0.76],
                aligns=["left", "left", "left", "right", "right"], size=7.2)
        p.text("Δrot, Δtrans: difference from the chosen X (rotation angle, translation distance).",
               size=7.5)
        for name, e in methods.items():
            if e.get("error"):
                p.text(f"{name} failed: {e['error']}", size=7.5, color=COLOURS["FAIL"])
        pairs = he.get("pairs") or {}
        if pairs:
            p.text(f"Motion pairs: {pairs.get('used', '–')} of {pairs.get('total', '–')} used "
                   f"({pairs.get('rejected', 0)} rejected: arm and camera rotation angles differ by "
                   f"more than {fmt(pairs.get('angle_tolerance_deg'), '°', 4)}, "
                   f"{fmt(pairs.get('mismatch_k'), '', 2)} robust σ of their mismatch).", size=7.5)
        u, nm = he.get("uncertainty") or {}, he.get("noise_model") or {}
        if u:
            p.text(f"Uncertainty of the chosen X (1σ, from its covariance): rotation "
                   f"{fmt(u.get('rotation_deg_1sigma'), '°', 5)}, translation "
                   f"{fmt(u.get('translation_mm_1sigma'), 'mm', 4)}; a point "
                   f"{u.get('board_distance_mm', 0):.0f} mm in front of the camera moves "
                   f"{fmt(u.get('point_mm_1sigma_at_board_distance'), 'mm', 4)}.", size=7.5)
        if nm:
            p.text(f"Noise levels estimated from the data (variance components): image "
                   f"{fmt(nm.get('image_sigma_px'), 'px', 4)}, arm {fmt(nm.get('arm_sigma_mm'), 'mm', 4)} "
                   f"and {fmt(1e6 * nm['arm_sigma_rad'] if 'arm_sigma_rad' in nm else None, 'µrad', 1)} per "
                   "axis.", size=7.5)
        order = ["rotation_residual_deg_rms", "translation_residual_mm_rms",
                 "board_consistency_mm", "reprojection_rms_px"]
        found = {k for e in methods.values() for k in e
                 if k not in ("vs_chosen_rotation_deg", "vs_chosen_translation_mm")
                 and isinstance(e[k], int | float)}
        res_keys = ([k for k in order if k in found] + sorted(found - set(order)))[:5]
        if res_keys:
            p.gap(0.1)
            p.text("Residuals stored by each method", size=10, weight="bold")
            xs = [LEFT] + [LEFT + 0.2 + 0.75 * i / len(res_keys) for i in range(len(res_keys))]
            p.table(["Method", *(pretty(k) for k in res_keys)],
                    [[n, *(fmt(methods[n].get(k), "", 5) for k in res_keys)] for n in methods],
                    xs, aligns=["left"] + ["right"] * len(res_keys), size=7.2)
            shown = res_keys[:3]
            h = 2.2 / A4[1]
            p.gap(0.3)
            y = p.y - h
            w = (RIGHT - LEFT - 0.1) / len(shown)
            names = list(methods)
            for i, k in enumerate(shown):
                ax = p.fig.add_axes((LEFT + 0.07 + i * w, y, w - 0.08, h))
                vals = [methods[n].get(k, np.nan) for n in names]
                cols = ["#1a7f37" if n == he.get("method") else "#4c72b0" for n in names]
                ax.bar(np.arange(len(names)), vals, color=cols)
                ax.set_xticks(np.arange(len(names)))
                ax.set_xticklabels(names, rotation=60, ha="right", fontsize=6.3)
                ax.set_title(pretty(k), loc="left", fontsize=8)
                ax.set_ylabel(pretty(k), fontsize=7)
            p.y = y - 0.95 / A4[1]
    else:
        p.text("handeye.json lists no other methods.", color=COLOURS["N/A"])
    scal = {k: v for k, v in he.items() if isinstance(v, int | float) and not isinstance(v, bool)}
    if scal:
        p.gap(0.1)
        p.text("Figures stored with the chosen X: " + ", ".join(
            f"{k} {fmt(v, '', 5)}" for k, v in sorted(scal.items())), size=7.5)
    return p.fig

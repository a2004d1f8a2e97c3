"""The pages of the calibration certificate, drawn from its metrics (``crossline.report.certificate``).

Page 1 is the certificate: the capture, which stages it allowed, every check against its
limit, every parameter with its 1σ. Then the sensor's coverage and residual field, and the
accuracy report's own calibration pages (camera, laser planes, hand-eye) for the
calibrations the capture has. Saved without dates: same metrics, same bytes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from crossline.report.pages_calibration import page_camera, page_handeye, page_lasers
from crossline.report.pages_common import (
    COLOURS,
    LEFT,
    RC,
    RIGHT,
    Page,
    _short,
    fmt,
    fmt_row_value,
    fmt_tolerance,
)
from crossline.report.pages_validation import page_provenance

__all__ = ["build_certificate_pages", "render_certificate"]

STAGE_NAMES = {"calibrate_camera": "camera", "calibrate_lasers": "laser planes",
               "calibrate_handeye": "hand-eye", "scans": "scans (accuracy report)"}


def _sigma(p: dict[str, Any]) -> str:
    if p.get("fixed"):
        return "fixed at 0"
    s = p.get("sigma")
    if s is None:
        return "–"
    return fmt(s, p["unit"], 4 if p["unit"] else 7)


def page_certificate(m: dict[str, Any]) -> Figure:
    """Page 1: capture, stages, result, the checks and every parameter with its 1σ."""
    p = Page(m, "Calibration certificate")
    cap, sw = m["capture"], m["software"]
    p.fields([("Capture", cap["name"]),
              ("Capture date", cap["date"] or "not recorded (no capture_date in rig.yaml)"),
              ("Data", "simulated (truth.json present)" if cap["simulated"] else "measured"),
              ("Lasers", ", ".join(cap.get("lasers") or []) or "none"),
              ("Software", f"crossline {sw['crossline_version']}, commit {_short(sw['git_commit'])}")])
    p.gap(0.08)
    p.result(m["result"])
    stages = m.get("stages") or {}
    if stages:
        p.gap(0.05)
        p.text("What the capture allows", size=10, weight="bold")
        for k, v in stages.items():
            ok = v.get("allowed")
            p.text(f"{STAGE_NAMES.get(k, k)}: " + ("yes" if ok else f"no ({v.get('why')})"),
                   size=7.8, color="black" if ok else COLOURS["N/A"])
    p.gap(0.08)
    rows = m["checks"]
    cells = [[r["figure"], fmt_row_value(r), fmt_tolerance(r), r["status"]] for r in rows]
    colours = [[None, None, None, COLOURS.get(r["status"])] for r in rows]
    p.table(["Check", "Measured", "Limit", "Result"], cells,
            [LEFT, LEFT + 0.48, LEFT + 0.64, LEFT + 0.80], colours=colours,
            aligns=["left", "right", "right", "left"], size=8.0)
    for k in ("lasers", "handeye"):
        if m.get(f"{k}_missing"):
            p.text(f"No {k} calibration: {m[f'{k}_missing']}", size=7.6, color=COLOURS["N/A"])
    cam = m.get("camera")
    if cam:
        p.gap(0.05)
        p.text("Camera parameters (1σ from the final bundle adjustment)", size=10, weight="bold")
        prm = cam["parameters"]
        cells = [[q["name"], fmt(q["value"], q["unit"], 4 if q["unit"] else 7), _sigma(q)]
                 for q in prm]
        half = (len(cells) + 1) // 2
        y0 = p.y
        p.table(["Parameter", "Value", "1σ"], cells[:half],
                [LEFT, LEFT + 0.1, LEFT + 0.26, LEFT + 0.4], aligns=["left", "right", "right"],
                size=7.8)
        y1 = p.y
        p.y = y0
        p.table(["Parameter", "Value", "1σ"], cells[half:],
                [LEFT + 0.46, LEFT + 0.56, LEFT + 0.72, LEFT + 0.86],
                aligns=["left", "right", "right"], size=7.8)
        p.y = min(p.y, y1)
        dm = cam.get("distortion_model") or {}
        if dm.get("reason"):
            p.text(f"Distortion model: {dm['reason']}.", size=7.5)
    la = m.get("lasers")
    if la:
        p.gap(0.05)
        p.text("Laser planes (n · p + d = 0, camera frame, mm)", size=10, weight="bold")
        cells = []
        for L in sorted(k for k in la if isinstance(la[k], dict)):
            e = la[L]
            n = e["normal"]
            sig = e.get("uncertainty") or {k: v for k, v in e.items() if "std" in k or "sigma" in k}
            cells.append([L, f"[{n[0]:+.6f}, {n[1]:+.6f}, {n[2]:+.6f}]", fmt(e["d_mm"], "mm", 4),
                          fmt(e.get("rms_mm"), "mm", 5),
                          ", ".join(f"{k} {fmt(v, '', 5)}" for k, v in sig.items()
                                    if isinstance(v, int | float)) or "not stored"])
        p.table(["Laser", "normal n", "d", "RMS", "1σ"], cells,
                [LEFT, LEFT + 0.07, LEFT + 0.37, LEFT + 0.5, LEFT + 0.62],
                aligns=["left", "left", "right", "right", "left"], size=7.6)
    he = m.get("handeye")
    if he:
        p.gap(0.05)
        u = he.get("uncertainty") or {}
        p.text("Hand-eye (X = T_tool_cam)", size=10, weight="bold")
        p.text(f"{he.get('method') or 'unknown method'}: translation "
               f"[{', '.join(f'{v:+.4f}' for v in np.asarray(he['T_tool_cam'])[:3, 3])}] mm "
               f"(1σ {fmt(u.get('translation_mm_1sigma'), 'mm', 4)}), rotation vector "
               f"[{', '.join(f'{v:+.4f}' for v in he['rotvec_deg'])}]° "
               f"(1σ {fmt(u.get('rotation_deg_1sigma'), '°', 5)}); board consistency "
               f"{fmt(he.get('board_consistency_mm'), 'mm', 4)}.", size=7.8)
    p.gap(0.08)
    p.text("Result: PASS when every check passes; FAIL if any fails; INCOMPLETE when a check "
           "could not be made. Limits: the configuration's certificate: section.", size=7.5)
    return p.fig


def page_coverage(m: dict[str, Any], plots: dict[str, Any]) -> Figure:
    """The sensor's coverage by board points and the mean residual vector per cell."""
    p = Page(m, "Calibration: sensor coverage and residual field")
    cam = m.get("camera") or {}
    cov, field = cam.get("coverage"), cam.get("residual_field")
    data = plots.get("coverage")
    if not cov or data is None:
        p.text("camera.json holds no residuals with board poses: no coverage.", color=COLOURS["N/A"])
        return p.fig
    w, h = data["size"]
    nc, nr = cov["grid"]
    p.text(f"{cov['points']:,d} board points of the used views; {cov['cells_covered']} of "
           f"{cov['cells']} cells ({nc} × {nr}) hold at least one "
           f"({fmt(cov['share'], '%', 1)}). Corners the board never reached are where the "
           "distortion is least constrained.", size=8.2)
    ax = p.axes(3.6, left=LEFT + 0.06, right=RIGHT - 0.12)
    counts = np.asarray(cov["counts"], dtype=np.float64)
    im = ax.imshow(np.where(counts > 0, counts, np.nan), extent=(-0.5, w - 0.5, h - 0.5, -0.5),
                   cmap="viridis", aspect="equal")
    uv = np.asarray(data["uv"])
    ax.scatter(uv[:, 0], uv[:, 1], s=0.3, color="white", alpha=0.6, rasterized=True)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    ax.set_title("Board points per cell (empty cells blank)", loc="left")
    p.fig.colorbar(im, ax=ax, fraction=0.03, pad=0.02, label="points")
    if field:
        du = np.asarray(field["mean_du_px"], dtype=np.float64)
        dv = np.asarray(field["mean_dv_px"], dtype=np.float64)
        cu = (np.arange(nc) + 0.5) * w / nc - 0.5
        cv = (np.arange(nr) + 0.5) * h / nr - 0.5
        U, V = np.meshgrid(cu, cv)
        mag = np.hypot(du, dv)
        ok = np.isfinite(mag)
        scale = float(np.nanmax(mag)) if ok.any() else 1.0
        ax2 = p.axes(3.6, left=LEFT + 0.06, right=RIGHT - 0.12)
        q = ax2.quiver(U[ok], V[ok], du[ok], dv[ok], mag[ok], angles="xy", scale_units="xy",
                       scale=max(scale, 1e-12) / (0.9 * w / nc), cmap="magma", width=0.004)
        ax2.set_xlim(-0.5, w - 0.5)
        ax2.set_ylim(h - 0.5, -0.5)
        ax2.set_aspect("equal")
        ax2.set_xlabel("u (px)")
        ax2.set_ylabel("v (px)")
        ax2.set_title(f"Mean residual vector per cell (longest {fmt(scale, 'px', 4)} = one cell)",
                      loc="left")
        p.fig.colorbar(q, ax=ax2, fraction=0.03, pad=0.02, label="px")
        p.text("A systematic pattern here (a swirl, arrows growing towards the edges) is model "
               "error the distortion model does not take up; noise alone points every way.",
               size=7.8)
    views = cam.get("views") or []
    if views:
        p.text("Per view: " + "; ".join(
            f"{Path(v['image']).stem} {fmt(v.get('rms_px'), '', 4)}"
            + ("" if v["used"] else " (rejected)") for v in views) + " (RMS, px).", size=6.8)
    return p.fig


def build_certificate_pages(metrics: dict[str, Any], plots: dict[str, Any]) -> list[Figure]:
    """Every page of the certificate, in order, with page numbers."""
    with matplotlib.rc_context(RC):
        figs = [page_certificate(metrics)]
        if metrics.get("camera"):
            figs.append(page_camera(metrics, plots))
            figs.append(page_coverage(metrics, plots))
        if metrics.get("lasers"):
            figs.append(page_lasers(metrics, plots))
        if metrics.get("handeye"):
            figs.append(page_handeye(metrics))
        figs.extend(page_provenance(metrics))
        n = len(figs)
        ver = metrics["software"]["crossline_version"]
        for i, f in enumerate(figs, 1):
            f.text(RIGHT, 0.02, f"page {i} of {n}", fontsize=7, ha="right", color="#57606a")
            f.text(LEFT, 0.02, f"crossline {ver}", fontsize=7, color="#57606a")
    return figs


def render_certificate(data: Any, path: str | Path) -> list[Figure]:
    """Write the certificate as a PDF without dates (same metrics, same bytes)."""
    import logging

    logging.getLogger("fontTools").setLevel(logging.WARNING)
    figs = build_certificate_pages(data.metrics, data.plots)
    meta = {"Title": f"crossline calibration certificate: {data.metrics['capture']['name']}",
            "Author": "crossline", "Subject": "calibration certificate",
            "Creator": f"crossline {data.metrics['software']['crossline_version']}",
            "Producer": "matplotlib", "CreationDate": None, "ModDate": None}
    with matplotlib.rc_context(RC), PdfPages(path, metadata=meta) as pdf:
        for f in figs:
            pdf.savefig(f)
    return figs

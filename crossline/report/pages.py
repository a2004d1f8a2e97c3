"""The pages of the accuracy report, drawn with matplotlib from the report's metrics.

Every number printed comes from the metrics dict (``crossline.report.build_report``) through
the formatters of ``pages_common``, so the PDF and ``metrics.json`` cannot disagree; the plot
arrays only shape the pictures. Figures are built with ``matplotlib.figure.Figure`` (no
pyplot, no global state), laid out by hand on A4 so nothing moves between runs, in DejaVu
fonts that matplotlib ships, and saved without any date: same metrics, same bytes.

The pages live in modules beside this one (issue 21.3): ``pages_common`` (style, formatters,
the A4 ``Page`` and the plot helpers), ``pages_calibration`` (camera, laser planes, hand-eye),
``pages_scan`` (each scan, a freeform against its nominal) and ``pages_validation``
(validation, uncertainty, provenance). This one keeps the summary page and assembles the
report; it re-exports the names its importers use.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from crossline.report.pages_calibration import _find_residuals as _find_residuals
from crossline.report.pages_calibration import _residuals_by_view as _residuals_by_view
from crossline.report.pages_calibration import page_camera, page_handeye, page_lasers
from crossline.report.pages_common import (
    A4,
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
from crossline.report.pages_scan import page_nominal, page_scan
from crossline.report.pages_validation import page_provenance, page_uncertainty, page_validation

__all__ = ["A4", "build_pages", "fmt", "fmt_row_value", "fmt_tolerance", "render_pdf"]


# ----------------------------------------------------------------------------- pages


def page_summary(m: dict[str, Any]) -> Figure:
    """Page 1: the certificate: capture, date, software, result, and the table of checks."""
    p = Page(m, "Accuracy report")
    cap = m["capture"]
    sw = m["software"]
    p.text("Cross-line laser scanner on a measuring arm: calibration and artefact measurements",
           size=9, color="#333333")
    p.gap(0.1)
    info = [
        ("Capture", cap["name"]),
        ("Capture date", cap["date"] or "not recorded (no capture_date in rig.yaml)"),
        ("Data", "simulated (truth.json present: validated below)" if cap["simulated"]
         else "measured (no truth.json)"),
        ("Scans", ", ".join(cap["scans"]) or "none"),
        ("Software", f"crossline {sw['crossline_version']}, commit {_short(sw['git_commit'])}"),
    ]
    p.fields(info)
    p.gap(0.1)
    p.result(m["result"])
    p.gap(0.15)
    rows = m["summary"]
    cells = [[r["figure"], r["scan"] or "", fmt_row_value(r), fmt_tolerance(r), r["status"]]
             for r in rows]
    colours = [[None, None, None, None, COLOURS.get(r["status"])] for r in rows]
    p.table(["Figure", "Scan", "Measured ± U (k = 2)", "Tolerance", "Result"], cells,
            [LEFT, LEFT + 0.36, LEFT + 0.44, LEFT + 0.68, LEFT + 0.83], colours=colours,
            aligns=["left", "left", "right", "right", "left"], size=8.2)
    notes = [r for r in rows if r.get("note")]
    for r in notes:
        p.text(f"{r['scan']}: {r['note']}", size=7.5, color=COLOURS["N/A"])
    p.gap(0.1)
    cal = m.get("calibration", {})
    p.text("Calibration", size=10, weight="bold")
    c = cal.get("camera")
    if c:
        used = c.get("views_used")
        total = len(c.get("views", []))
        views = f", {used} of {total} views used" if total else ""
        proj = (c.get("uncertainty") or {}).get("projection_rms_px") or {}
        pred = (f"; predicted projection error {fmt(proj['scan_window'], 'px', 4)} (1σ, scan window)"
                if proj.get("scan_window") is not None else "")
        p.text(f"Camera: fx {fmt(c['fx_px'], 'px', 2)}, fy {fmt(c['fy_px'], 'px', 2)}, "
               f"reprojection RMS {fmt(c.get('rms_px'), 'px', 4)}{views}{pred}")
    else:
        p.text("Camera: no camera.json", color=COLOURS["N/A"])
    la = cal.get("lasers")
    if la:
        if "B" in la:
            p.text(f"Laser planes: angle between A and B {fmt(la['angle_AB_deg'], '°', 3)}; RMS "
                   f"A {fmt(la['A'].get('rms_mm'), 'mm')}, B {fmt(la['B'].get('rms_mm'), 'mm')}")
        else:
            p.text(f"Laser plane (one-line rig): RMS A {fmt(la['A'].get('rms_mm'), 'mm')}")
    else:
        p.text("Laser planes: no lasers.json", color=COLOURS["N/A"])
    he = cal.get("handeye")
    if he:
        u = he.get("uncertainty") or {}
        pred = (f"; predicted point error {fmt(u['point_mm_1sigma_at_board_distance'], 'mm', 4)} "
                f"(1σ at {u.get('board_distance_mm', 0):.0f} mm)"
                if "point_mm_1sigma_at_board_distance" in u else "")
        p.text(f"Hand-eye: X = T_tool_cam by {he.get('method') or 'unknown method'}; "
               f"{len(he.get('methods', {}))} method(s) compared{pred}")
    else:
        p.text("Hand-eye: no handeye.json", color=COLOURS["N/A"])
    p.gap(0.15)
    p.text("How to read this page", size=10, weight="bold")
    for line in (
        "Each figure is checked against its tolerance (report.tolerances in the configuration);",
        "|x| means the absolute value is compared. INFO rows have no tolerance; N/A: not measured.",
        "Gauge height: the distance of every top-face point to the plane fitted to the plate",
        "around the block (the paper's Fig. 10), away from the block's edges.",
        "Plane: distances to the least-squares plane (the paper's Fig. 16), flatness F their range.",
        "Sphere: least-squares sphere (ISO 10360-8 PSize; PForm the range of radial residuals;",
        "VDI/VDE 2634-2 may discard up to 0.3 % of the points, the largest residuals).",
        "Laser A − laser B: the same artefact measured from each laser's points alone"
        + (" (a one-line rig: omitted)." if m["capture"].get("lasers") == ["A"] else "."),
        "Histograms span 0.1–99.9 % of the values (at most ±8 robust sigmas); the rest are",
        "counted in the end bins.",
        "Result: PASS when every checked figure passes; FAIL if any fails; INCOMPLETE otherwise.",
        "U: expanded uncertainty (k = 2) by Monte Carlo over the calibration's covariances and the",
        "scan's frames; its budget, and the ISO 14253-1 decision against U, are on the page",
        "'Measurement uncertainty'.",
    ):
        p.text(line, size=7.8)
    return p.fig


# ----------------------------------------------------------------------------- assembly


def build_pages(metrics: dict[str, Any], plots: dict[str, Any]) -> list[Figure]:
    """Every page of the report, in order, with page numbers in the footer."""
    with matplotlib.rc_context(RC):
        figs = [page_summary(metrics)]
        figs.append(page_camera(metrics, plots))
        figs.append(page_lasers(metrics, plots))
        figs.append(page_handeye(metrics))
        for name in metrics["scans"]:
            figs.append(page_scan(metrics, name, plots["scans"].get(name, {})))
            if metrics["scans"][name].get("nominal_comparison"):
                figs.append(page_nominal(metrics, name, plots["scans"].get(name, {})))
        unc = page_uncertainty(metrics)
        if unc is not None:
            figs.append(unc)
        if metrics.get("validation"):
            figs.extend(page_validation(metrics, plots))
        figs.extend(page_provenance(metrics))
        n = len(figs)
        ver = metrics["software"]["crossline_version"]
        for i, f in enumerate(figs, 1):
            f.text(RIGHT, 0.02, f"page {i} of {n}", fontsize=7, ha="right", color="#57606a")
            f.text(LEFT, 0.02, f"crossline {ver}", fontsize=7, color="#57606a")
    return figs


def page_texts(fig: Figure) -> list[str]:
    """Every text drawn on a page (for tests: the numbers the reader sees)."""
    from matplotlib.text import Text

    return [t.get_text() for t in fig.findobj(Text) if t.get_text()]


def render_pdf(data: Any, path: str | Path, png_dir: str | Path | None = None) -> list[Figure]:
    """Write the report as a PDF without dates (same metrics, same bytes); optionally PNGs."""
    import logging

    # fontTools logs every font subset at INFO: noise in a stage's log
    logging.getLogger("fontTools").setLevel(logging.WARNING)
    metrics, plots = data.metrics, data.plots
    figs = build_pages(metrics, plots)
    meta = {"Title": f"crossline accuracy report: {metrics['capture']['name']}",
            "Author": "crossline", "Subject": "accuracy report",
            "Creator": f"crossline {metrics['software']['crossline_version']}",
            "Producer": "matplotlib", "CreationDate": None, "ModDate": None}
    with matplotlib.rc_context(RC), PdfPages(path, metadata=meta) as pdf:
        for f in figs:
            pdf.savefig(f)
    if png_dir is not None:
        png_dir = Path(png_dir)
        png_dir.mkdir(parents=True, exist_ok=True)
        with matplotlib.rc_context(RC):
            for i, f in enumerate(figs, 1):
                f.savefig(png_dir / f"page-{i:02d}.png", dpi=110)
    return figs

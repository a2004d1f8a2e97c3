"""The pages of the accuracy report, drawn with matplotlib from the report's metrics.

Every number printed comes from the metrics dict (``crossline.report.build_report``) through
the formatters below, so the PDF and ``metrics.json`` cannot disagree; the plot arrays only
shape the pictures. Figures are built with ``matplotlib.figure.Figure`` (no pyplot, no
global state), laid out by hand on A4 so nothing moves between runs, in DejaVu fonts that
matplotlib ships, and saved without any date: same metrics, same bytes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.lines
import matplotlib.patches
import matplotlib.ticker
import numpy as np
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from crossline.scan.centreline import half_amplitude_columns

__all__ = ["A4", "build_pages", "fmt", "fmt_row_value", "fmt_tolerance", "render_pdf"]

A4 = (8.27, 11.69)  # inches, portrait
RC = {
    "font.family": "DejaVu Sans",
    "font.size": 8.5,
    "axes.titlesize": 9.5,
    "axes.labelsize": 8.5,
    "xtick.labelsize": 7.5,
    "ytick.labelsize": 7.5,
    "legend.fontsize": 7.5,
    "pdf.fonttype": 3,  # subsets drawn by matplotlib: text stays extractable, quicker than 42
    "pdf.compression": 6,
    "path.simplify": True,
    "image.interpolation": "nearest",
    "axes.unicode_minus": True,
    "svg.hashsalt": "crossline",
}
MONO = "DejaVu Sans Mono"
COLOURS = {"PASS": "#1a7f37", "FAIL": "#cf222e", "INFO": "#57606a", "N/A": "#bc4c00",
           "INCOMPLETE": "#bc4c00"}
LASER_COLOURS = {"A": "#1f77b4", "B": "#d62728", "AB": "#7b3294", "off": "#999999"}
LEFT, RIGHT = 0.08, 0.95


# ----------------------------------------------------------------------------- formatting


def fmt(value: Any, unit: str = "", digits: int = 4, signed: bool = False) -> str:
    """One number as printed in the report; None/NaN prints as an en dash."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if unit == "%":
        return f"{100 * value:.2f} %"
    if isinstance(value, int | np.integer) and not isinstance(value, bool):
        return f"{value:,d}" + (f" {unit}" if unit else "")
    s = f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"
    if s.startswith("-") and float(s) == 0.0:  # no "-0.0000": the sign of a rounded zero says nothing
        s = ("+" if signed else "") + s[1:]
    return s + (f" {unit}" if unit else "")


def _um(mm: float | None) -> str:
    """A length given in mm printed in µm, one decimal."""
    return fmt(None if mm is None else 1e3 * mm, "", 1)


def fmt_row_value(row: dict[str, Any]) -> str:
    """The measured value of a summary row, with ``± U`` where it has an uncertainty."""
    signed = row.get("abs", False)
    unit = row.get("unit", "")
    text = fmt(row.get("value"), unit, signed=signed)
    if row.get("U") is None or text == "–":
        return text
    tail = " %" if unit == "%" else f" {unit}" if unit else ""
    return f"{text.removesuffix(tail)} ± {fmt(row['U'], unit)}"


def fmt_tolerance(row: dict[str, Any]) -> str:
    """The tolerance of a summary row, e.g. ``|x| ≤ 0.0030 mm``."""
    if row.get("tolerance") is None:
        return "–"
    sym = "≤" if row.get("comparison", "<=") == "<=" else "≥"
    lhs = "|x| " if row.get("abs") else ""
    return f"{lhs}{sym} {fmt(row['tolerance'], row.get('unit', ''))}"


SHORT = {"rms_mm": "RMS (mm)", "n_used": "used", "n_points": "points", "n_rejected": "rejected",
         "rotation_residual_deg_rms": "rot. RMS (°)", "translation_residual_mm_rms": "trans. RMS (mm)",
         "board_consistency_mm": "board (mm)", "reprojection_rms_px": "reproj. (px)"}


def pretty(key: str) -> str:
    """A JSON key as a column header: ``rms_mm`` -> ``RMS (mm)``."""
    if key in SHORT:
        return SHORT[key]
    units = {"mm": " (mm)", "deg": " (°)", "px": " (px)"}
    words = key.split("_")
    unit = next((units[w] for w in words if w in units), "")
    words = [w for w in words if w not in units]
    if words[:1] == ["n"] and len(words) > 1:  # n_used -> "used"
        words = words[1:]
    words = [w.upper() if w in ("rms", "n", "ab") else w for w in words]
    text = " ".join(words)
    if text == "N points" or text == "N":
        text = "points"
    return text[:1].upper() + text[1:] + unit


def _short(commit: str | None) -> str:
    if not commit:
        return "not in a git repository"
    dirty = commit.endswith("-dirty")
    base = commit[:-6] if dirty else commit
    return base[:12] + (" (modified)" if dirty else "")


# ----------------------------------------------------------------------------- helpers


class Page:
    """An A4 figure with the report's header and a cursor for text blocks (y in figure units)."""

    def __init__(self, metrics: dict[str, Any], section: str):
        self.fig = Figure(figsize=A4)
        self.section = section
        cap = metrics["capture"]["name"]
        self.fig.text(LEFT, 0.972, metrics.get("title", "crossline accuracy report"), fontsize=8,
                      color="#57606a")
        self.fig.text(RIGHT, 0.972, f"capture {cap}", fontsize=8, color="#57606a", ha="right")
        self.fig.add_artist(matplotlib.lines.Line2D([LEFT, RIGHT], [0.966, 0.966], lw=0.6,
                                                    color="#57606a"))
        self.fig.text(LEFT, 0.94, section, fontsize=14, weight="bold", va="top")
        self.y = 0.905

    def text(self, s: str, *, size: float = 8.5, x: float = LEFT, dy: float | None = None,
             **kw: Any) -> None:
        """Text at the cursor, wrapped to the page width; the cursor moves below it."""
        import textwrap

        mono = kw.get("family") == MONO
        width = int((RIGHT - x) * A4[0] * 72 / (size * (0.61 if mono else 0.55)))
        for line in textwrap.wrap(s, width=max(20, width)) or [""]:
            self.fig.text(x, self.y, line, fontsize=size, va="top", **kw)
            self.y -= dy if dy is not None else size * 1.45 / 72 / A4[1]

    def gap(self, inches: float = 0.08) -> None:
        """Move the cursor down."""
        self.y -= inches / A4[1]

    def fields(self, pairs: list[tuple[str, str]], *, size: float = 9) -> None:
        """Label / value lines at the cursor, labels in bold."""
        for k, v in pairs:
            self.fig.text(LEFT, self.y, k, fontsize=size, va="top", weight="bold")
            self.fig.text(LEFT + 0.17, self.y, v, fontsize=size, va="top")
            self.y -= size * 1.5 / 72 / A4[1]

    def result(self, res: str) -> None:
        """The document's overall result line, coloured by its verdict."""
        self.fig.text(LEFT, self.y, "Result", fontsize=12, va="top", weight="bold")
        self.fig.text(LEFT + 0.17, self.y, res, fontsize=12, va="top", weight="bold",
                      color=COLOURS[res])
        self.y -= 12 * 1.6 / 72 / A4[1]

    def table(self, columns: list[str], rows: list[list[str]], xs: list[float], *,
              size: float = 8.0, colours: list[list[str | None]] | None = None,
              aligns: list[str] | None = None, bold_header: bool = True, mono: bool = False) -> None:
        """A simple ruled table at the cursor; ``xs`` are the columns' x (figure units)."""
        lh = size * 1.55 / 72 / A4[1]
        aligns = aligns or ["left"] * len(columns)
        family = MONO if mono else RC["font.family"]

        def xpos(i: int) -> float:
            if aligns[i] == "right":
                return xs[i + 1] - 0.008 if i + 1 < len(xs) else RIGHT
            return xs[i]

        for i, c in enumerate(columns):
            self.fig.text(xpos(i), self.y, c, fontsize=size, va="top", ha=aligns[i],
                          weight="bold" if bold_header else "normal")
        self.y -= lh
        self.fig.add_artist(matplotlib.lines.Line2D([LEFT, RIGHT], [self.y + 0.3 * lh] * 2,
                                                    lw=0.5, color="black"))
        for r, row in enumerate(rows):
            for i, cell in enumerate(row):
                col = colours[r][i] if colours and colours[r][i] else "black"
                self.fig.text(xpos(i), self.y, cell, fontsize=size, va="top", ha=aligns[i],
                              color=col, family=family,
                              weight="bold" if col in COLOURS.values() else "normal")
            self.y -= lh
        self.fig.add_artist(matplotlib.lines.Line2D([LEFT, RIGHT], [self.y + 0.3 * lh] * 2,
                                                    lw=0.5, color="black"))
        self.gap(0.06)

    def axes(self, height_in: float, *, left: float = LEFT + 0.05, right: float = RIGHT,
             gap_in: float = 0.45) -> Any:
        """Axes below the cursor, ``height_in`` inches high (room for a title above, labels below)."""
        self.gap(0.32)
        h = height_in / A4[1]
        ax = self.fig.add_axes((left, self.y - h, right - left, h))
        self.y -= h + gap_in / A4[1]
        return ax


def _hist(ax: Any, values: np.ndarray, bins: int, xlabel: str, clip: float = 0.1) -> tuple:
    """Histogram of values over their 0.1–99.9 % range, at most ±8 robust sigmas wide (the rest
    counted in the end bins)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:  # nothing measured (e.g. a gauge whose second face was not found)
        ax.text(0.5, 0.5, "no values to show", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel(xlabel)
        return np.zeros(0, dtype=np.int64), np.zeros(1)
    lo, hi = np.percentile(v, [clip, 100 - clip])
    # heavy tails (edges, stray points) would squash the body into a few bins: at most
    # 8 robust sigmas either side of the median
    med = float(np.median(v))
    rs = 1.4826 * float(np.median(np.abs(v - med)))
    if rs > 0:
        lo, hi = max(lo, med - 8 * rs), min(hi, med + 8 * rs)
    if hi <= lo:
        lo, hi = lo - 1e-3, hi + 1e-3
    counts, edges = np.histogram(np.clip(v, lo, hi), bins=bins, range=(lo, hi))
    ax.bar(edges[:-1], counts, width=np.diff(edges), align="edge", color="#4c72b0",
           edgecolor="white", linewidth=0.3)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("points (count)")
    ax.set_xlim(lo, hi)
    ax.ticklabel_format(axis="x", useOffset=False, style="plain")
    ax.set_ylim(0, counts.max() * 1.35 if counts.size and counts.max() else 1)
    return counts, edges


def _textbox(ax: Any, lines: list[str], loc: str = "right") -> None:
    x, ha = (0.98, "right") if loc == "right" else (0.02, "left")
    ax.text(x, 0.96, "\n".join(lines), transform=ax.transAxes, ha=ha, va="top", fontsize=7.5,
            family=MONO, multialignment="left",
            bbox={"boxstyle": "round,pad=0.4", "fc": "white", "ec": "#999999", "alpha": 0.9})


def _binned_image(xy: np.ndarray, h: np.ndarray, max_bins: int = 320) -> tuple:
    """Mean of h on a regular grid over xy: image (ny, nx) with NaN where empty, and extent."""
    lo = xy.min(0)
    hi = xy.max(0)
    span = np.maximum(hi - lo, 1e-6)
    # cells of about two points each on average (sparse stripes would print as dust)
    cell = max(span.max() / max_bins, float(np.sqrt(span[0] * span[1] * 2.0 / max(len(xy), 1))))
    nb = np.maximum(np.ceil(span / cell).astype(int), 1)
    rng = [[lo[0], lo[0] + nb[0] * cell], [lo[1], lo[1] + nb[1] * cell]]
    s, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=nb, range=rng, weights=h)
    c, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=nb, range=rng)
    with np.errstate(invalid="ignore", divide="ignore"):
        img = (s / c).T
    return img, (rng[0][0], rng[0][1], rng[1][0], rng[1][1])


def _map(page: Page, xy: np.ndarray, h: np.ndarray, label: str, title: str, *,
         height_in: float = 3.3, cmap: str = "viridis", symmetric: bool = False) -> None:
    img, extent = _binned_image(xy, h)
    if symmetric:
        m = float(np.nanpercentile(np.abs(img), 99)) or 1e-6
        vmin, vmax = -m, m
    else:
        vmin, vmax = (float(x) for x in np.nanpercentile(img, [1, 99]))
        if vmax <= vmin:
            vmax = vmin + 1e-6
    ax = page.axes(height_in, right=RIGHT - 0.16)
    im = ax.imshow(img, origin="lower", extent=extent, cmap=cmap, vmin=vmin, vmax=vmax,
                   aspect="equal", interpolation="nearest")
    ax.set_xlabel("u along the surface (mm)")
    ax.set_ylabel("v along the surface (mm)")
    ax.set_title(title, loc="left")
    ax.apply_aspect()  # the image's real box, once its aspect is fixed
    pos = ax.get_position()
    cax = page.fig.add_axes((pos.x1 + 0.02, pos.y0, 0.018, pos.height))
    cb = page.fig.colorbar(im, cax=cax)
    cb.set_label(label)


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


def _ab_rows(ab: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    art = ab["artefact"]
    A, B, D = ab["A"], ab["B"], ab["A_minus_B"]
    if art == "gauge_block":
        return (["", "laser A", "laser B", "A − B"],
                [["mean height", fmt(A["mean_mm"], "mm"), fmt(B["mean_mm"], "mm"),
                  fmt(D["height_mm"], "mm", signed=True)],
                 ["std of heights", fmt(A["std_mm"], "mm"), fmt(B["std_mm"], "mm"), ""],
                 ["top / plate points", f"{A['n']:,d} / {A['n_plate']:,d}",
                  f"{B['n']:,d} / {B['n_plate']:,d}", ""],
                 ["plate plane offset", "", "", fmt(D["plate_offset_mm"], "mm", signed=True)],
                 ["plate plane angle", "", "", fmt(D["plate_angle_deg"], "°", 5)]])
    if art == "plane":
        return (["", "laser A", "laser B", "A − B"],
                [["points", f"{A['n']:,d}", f"{B['n']:,d}", ""],
                 ["RMS to own plane", fmt(A["rms_mm"], "mm"), fmt(B["rms_mm"], "mm"), ""],
                 ["within band", fmt(A["share_within_band"], "%"),
                  fmt(B["share_within_band"], "%"), ""],
                 ["plane offset", "", "", fmt(D["plane_offset_mm"], "mm", signed=True)],
                 ["plane angle", "", "", fmt(D["plane_angle_deg"], "°", 5)]])
    return (["", "laser A", "laser B", "A − B"],
            [["points", f"{A['n']:,d}", f"{B['n']:,d}", ""],
             ["diameter", fmt(A["diameter_mm"], "mm"), fmt(B["diameter_mm"], "mm"),
              fmt(D["diameter_mm"], "mm", signed=True)],
             ["centre distance", "", "", fmt(D["centre_distance_mm"], "mm")]])


def page_scan(m: dict[str, Any], name: str, plots: dict[str, Any]) -> Figure:
    """One scan: counts and the gain of the cross, top view by height, the artefact's histogram."""
    s = m["scans"][name]
    art = s["artefact"]
    nominal = ", ".join(f"nominal {k} {v:g} mm" for k, v in s["nominal"].items())
    p = Page(m, f"Scan '{name}': {art.replace('_', ' ')}" + (f" ({nominal})" if nominal else ""))
    c = s.get("counts", {})
    y0 = p.y
    lines = []
    if "points" in c:
        by = c.get("points_by_laser", {})
        if "B" in by or s.get("lasers") != ["A"]:
            lines.append(f"points {fmt(c['points'])} (A {fmt(by.get('A', 0))}, B {fmt(by.get('B', 0))})")
        else:
            lines.append(f"points {fmt(c['points'])} (laser A: a one-line rig)")
    if "frames" in c:
        lines.append(f"frames {fmt(c['frames'])}")
    tri = c.get("triangulation") or {}
    win = (tri.get("params") or {}).get("smooth_px")
    if win is not None:
        name = tri.get("extractor", "?").replace("_", " ")
        if win > 1:
            lines += [f"centres: {name}, smoothed over {win} columns",
                      f"  along the stripe (half amplitude at a "
                      f"{half_amplitude_columns(int(win)):.1f}-column ripple)"]
        else:
            lines.append(f"centres: {name}, each column on its own")
    by_order = (tri.get("counts") or {}).get("labelled_by_order")
    if by_order:  # a scan without A or B frames
        lines += [f"labels: no A or B frames; AB frames told apart by the order of the cross "
                  f"({fmt(by_order['frames'])} frames),",
                  f"  then followed: {fmt(by_order['by_previous_frames'])} centres from the frames "
                  f"before, {fmt(by_order['by_order'])} by the order"]
    if c.get("points_per_frame") is not None:
        lines.append(f"points per frame {fmt(c['points_per_frame'], '', 1)}")
    if c.get("points_per_single_laser_frame") is not None:
        lines.append(f"per single-laser frame {fmt(c['points_per_single_laser_frame'], '', 1)}")
    if c.get("gain_over_single_line") is not None:
        lines.append(f"gain over a single line {fmt(c['gain_over_single_line'], '', 3)}× "
                     "(the paper: 1.33× ideally)")
    fz = c.get("fused")
    if fz:
        lines.append(f"fused cloud {fmt(fz.get('n_output'))} points "
                     f"({fmt(fz.get('n_outliers'))} outliers removed)")
        pr = fz.get("pose_refinement")
        if pr and pr.get("skipped"):
            lines.append(f"arm poses as reported: refinement skipped ({pr['skipped']})")
        elif pr:
            lines.append(f"arm poses refined: {fmt(pr.get('used'))} A-B crossings, "
                         f"{fmt(pr.get('frames_with_crossings'))} of {fmt(pr.get('frames'))} frames")
            lines.append(f"  crossing gaps {_um(pr.get('gap_rms_before_mm'))} -> "
                         f"{_um(pr.get('gap_rms_after_mm'))} µm RMS, corrections "
                         f"{_um(pr.get('correction_rms_mm'))} µm")
    if s.get("cloud_source"):
        lines.append(f"measured on {s['cloud_source']}")
    for ln in lines:
        p.text(ln, size=8.2)
    if s.get("error"):
        p.text(f"measurement failed: {s['error']}", size=8, color=COLOURS["FAIL"])
    # points per frame by laser state, beside the counts
    fc = plots.get("frame_counts")
    if fc is not None and len(fc):
        st = plots["frame_states"]
        h = 1.55 / A4[1]
        ax = p.fig.add_axes((LEFT + 0.50, y0 - h - 0.02, RIGHT - LEFT - 0.50, h))
        k = min(len(fc), 36)
        cols = [LASER_COLOURS.get(x, "#999999") for x in st[:k]]
        ax.bar(np.arange(k), fc[:k], color=cols, width=0.85)
        ax.set_xlabel(f"frame (first {k} of {len(fc)})")
        ax.set_ylabel("points per frame")
        handles = [matplotlib.patches.Patch(color=LASER_COLOURS[x], label=x)
                   for x in ("A", "B", "AB", "off") if x in set(st[:k])]
        ax.legend(handles=handles, loc="upper right", fontsize=6.5, ncol=len(handles),
                  title="lasers on", title_fontsize=6.5)
        ax.set_ylim(0, max(1, fc[:k].max()) * 1.45)
        p.y = min(p.y, y0 - h - 0.02 - 0.45 / A4[1])
    top = plots.get("top")
    if top is not None:
        label = {"gauge_block": "height above the plate plane (mm)",
                 "plane": "distance to the fitted plane (mm)"}.get(art, "height (mm)")
        _map(p, top["xy"], top["h"], label, "Top view of the fused cloud", height_in=2.6)
    hist = plots.get("hist")
    meas = s.get("measurement") or {}
    if hist is not None and meas:
        ax = p.axes(2.25, left=LEFT + 0.06)
        _, edges = _hist(ax, hist["values"], hist["bins"], hist["xlabel"])
        lo, hi = edges[0], edges[-1]
        if hist["kind"] == "gauge":
            ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.3f"))
            ax.axvline(meas["mean_mm"], color="black", lw=1.0, label="mean")
            if lo <= meas["nominal_mm"] <= hi:
                ax.axvline(meas["nominal_mm"], color="#cf222e", lw=1.0, ls="--", label="nominal")
            ax.set_title("Histogram of heights (as the paper's Fig. 10: there mean 19.989 mm, "
                         "std 0.006 mm)", loc="left")
            _textbox(ax, [f"mean     {fmt(meas['mean_mm'], 'mm')}",
                          f"std      {fmt(meas['std_mm'], 'mm')}",
                          f"nominal  {fmt(meas['nominal_mm'], 'mm')}",
                          f"error    {fmt(meas['error_mm'], 'mm', signed=True)}",
                          f"SEM      {fmt(meas['sem_mm'], 'mm', 5)}",
                          f"n        {fmt(meas['n'])}"])
            ax.legend(loc="upper left")
        elif hist["kind"] in ("plane", "freeform"):
            b = hist["band"]
            for x in (-b, b):
                if lo <= x <= hi:
                    ax.axvline(x, color="#1a7f37", lw=1.0, ls="--",
                               label=f"±{b:g} mm" if x > 0 or not lo <= b <= hi else None)
            if hist["kind"] == "plane":
                ax.set_title("Histogram of distances to the plane (as the paper's Fig. 16: there "
                             "96 % within ±0.05 mm)", loc="left")
                _textbox(ax, [f"n          {fmt(meas['n'])}",
                              f"RMS        {fmt(meas['rms_mm'], 'mm')}",
                              f"within ±{b:g} {fmt(meas['share_within_band'], '%')}",
                              f"flatness   {fmt(meas['flatness_mm'], 'mm')}",
                              f"  2.5–97.5 {fmt(meas['flatness_95_mm'], 'mm')}"])
            else:
                dev = (s.get("truth") or {}).get("deviation_to_true_mesh", {})
                ax.set_title("Signed distance to the true surface", loc="left")
                _textbox(ax, [f"n          {fmt(dev.get('n'))}",
                              f"mean       {fmt(dev.get('mean_mm'), 'mm', signed=True)}",
                              f"RMS        {fmt(dev.get('rms_mm'), 'mm')}",
                              f"|d| 95 %   {fmt(dev.get('abs_p95_mm'), 'mm')}",
                              f"within ±{b:g} {fmt(dev.get('share_within_band'), '%')}"])
            if lo <= b <= hi or lo <= -b <= hi:
                ax.legend(loc="upper left")
            else:
                ax.text(0.02, 0.96, f"the ±{b:g} mm band lies\nbeyond the plotted range",
                        transform=ax.transAxes, va="top", fontsize=7)
        elif hist["kind"] == "sphere":
            ax.set_title("Radial residuals of the least-squares sphere", loc="left")
            _textbox(ax, [f"diameter   {fmt(meas['diameter_mm'], 'mm')}",
                          f"nominal    {fmt(meas['nominal_diameter_mm'], 'mm')}",
                          f"size error {fmt(meas['size_error_mm'], 'mm', signed=True)}",
                          f"form (all) {fmt(meas['form_error_mm'], 'mm')}",
                          f"form (D95) {fmt(meas['form_error_d95_mm'], 'mm')}",
                          f"n          {fmt(meas['n'])}"])
        inc = s.get("incidence")
        if inc and inc.get("bands"):
            p.gap(0.02)
            p.text("Mean radial residual by angle of incidence (between the surface normal and "
                   "the view): " + ", ".join(
                       f"{b['from_deg']:.0f}–{b['to_deg']:.0f}° {1000 * b['mean_residual_mm']:+.1f} µm"
                       for b in inc["bands"]) + (
                       f". Size error from the points seen within {inc['max_incidence_deg']:.0f}°: "
                       f"{fmt(inc['size_error_steep_mm'], 'mm', signed=True)}"
                       if "size_error_steep_mm" in inc else "") + ".", size=7.6)
        if s.get("a_vs_b"):
            p.gap(0.02)
            p.text("Laser A against laser B: the artefact measured from each laser's points alone",
                   size=9, weight="bold")
            cols, rows = _ab_rows(s["a_vs_b"])
            p.table(cols, rows, [LEFT, LEFT + 0.28, LEFT + 0.50, LEFT + 0.72],
                    aligns=["left", "right", "right", "right"], size=7.8)
        elif s.get("a_vs_b_error"):
            p.text(f"Laser A against laser B: not compared ({s['a_vs_b_error']})", size=8,
                   color=COLOURS["N/A"])
        elif s.get("a_vs_b_note"):
            p.text(f"Laser A against laser B: {s['a_vs_b_note']}", size=8, color=COLOURS["INFO"])
    if art == "freeform":
        p.gap(0.1)
        nc = s.get("nominal_comparison")
        if nc:
            p.text(f"Against its nominal {nc['nominal']}: the next page.", size=8)
        elif s.get("nominal_error"):
            p.text(f"No comparison with its nominal: {s['nominal_error']}", size=8,
                   color=COLOURS["N/A"])
        else:
            p.text("A freeform part without a nominal mesh (rig.yaml nominal:) is not compared "
                   "with a drawing; with truth.json, its deviation from the true surface is on "
                   "the validation page.", size=8)
    return p.fig


def page_nominal(m: dict[str, Any], name: str, plots: dict[str, Any]) -> Figure:
    """A freeform scan against its nominal mesh: alignment, deviation map, histogram, regions."""
    from crossline.report.accuracy import deviation_limit_mm
    from crossline.report.nominal import deviation_map_figure

    s = m["scans"][name]
    nc = s["nominal_comparison"]
    p = Page(m, f"Scan '{name}' against its nominal ({nc['nominal']})")
    al = nc["alignment"]
    coarse = {"datum": "the datum given", "fpfh_ransac": "RANSAC on FPFH features"}.get(
        al.get("coarse"), str(al.get("coarse")))
    p.text(f"Aligned to the nominal ({fmt(nc['triangles'])} triangles): coarse by {coarse}, then "
           f"point-to-plane ICP on the mesh's closest points with a Tukey kernel "
           f"({fmt(al.get('iterations'))} iterations; fitness {fmt(al.get('fitness'), '', 3)}, "
           f"inlier RMS {fmt(al.get('inlier_rmse_mm'), 'mm')}). Signed distance to the nominal "
           "surface, positive: material excess.", size=8.2)
    p.text(f"{fmt(nc.get('share_within_tolerance'), '%')} of {fmt(nc['n'])} points within "
           f"±{nc['tolerance_mm']:g} mm; mean {fmt(nc.get('mean_mm'), 'mm', signed=True)}, RMS "
           f"{fmt(nc.get('rms_mm'), 'mm')}, 2.5–97.5 % {fmt(nc.get('p2_5_mm'), 'mm', signed=True)}"
           f" to {fmt(nc.get('p97_5_mm'), 'mm', signed=True)}, min / max "
           f"{fmt(nc.get('min_mm'), 'mm', signed=True)} / {fmt(nc.get('max_mm'), 'mm', signed=True)}."
           f" Not compared: {fmt(nc.get('n_support', 0))} points on the plane the part stands on "
           f"(which the drawing leaves open), {fmt(nc.get('n_excluded', 0))} farther than "
           f"{fmt(nc.get('max_distance_mm'), 'mm', 1)} from it.", size=8.2)
    data = plots.get("nominal")
    if data is not None and len(data["dev"]):
        limit = deviation_limit_mm(data["dev"], nc["tolerance_mm"])
        top = p.y - 0.01
        deviation_map_figure(data["points"], data["dev"], limit, regions=data["regions"],
                             tolerance_mm=float(nc["tolerance_mm"]), fig=p.fig,
                             rect=(LEFT + 0.05, top - 0.5, RIGHT - 0.05, top))
        p.y = top - 0.54
    regions = nc.get("regions") or []
    if regions:
        p.text(f"Regions beyond ±{nc['tolerance_mm']:g} mm ({fmt(nc.get('n_regions'))} in all; "
               "the largest, numbered as on the map; depth: median of the region's 10 % most "
               "extreme points, at their mean)", size=9, weight="bold")
        rows = [[str(g["id"]), fmt(g["n"]),
                 ", ".join(f"{v:.2f}" for v in g.get("depth_at_mm", g["centroid_mm"])),
                 fmt(g["extreme_mm"], "mm", signed=True), fmt(g["depth_mm"], "mm", signed=True)]
                for g in regions]
        p.table(["#", "points", "deepest at (nominal frame, mm)", "extreme", "depth"], rows,
                [LEFT, LEFT + 0.05, LEFT + 0.16, LEFT + 0.5, LEFT + 0.68],
                aligns=["left", "right", "left", "right", "right"], size=7.6)
    else:
        p.text(f"No region beyond ±{nc['tolerance_mm']:g} mm.", size=8.2)
    return p.fig


def page_validation(m: dict[str, Any], plots: dict[str, Any]) -> list[Figure]:
    """Every estimate against the simulator's truth: calibrations, artefacts, freeform map."""
    v = m["validation"]
    p = Page(m, "Validation against truth (simulated capture)")
    z = v.get("volume_z_mm") or [float("nan")] * 2
    p.text(f"Calibration errors over the measured volume: {z[0]:.1f}–{z[1]:.1f} mm in front of the "
           f"camera ({v.get('volume_from', 'configuration')}), over the scan window.", size=8.2)
    rows = []
    c = v.get("camera")
    if c:
        rows.append(["camera K, dist", "projection difference RMS / max",
                     f"{fmt(c['rms_px'], 'px')} / {fmt(c['max_px'], 'px')}"])
        pred = ((m["calibration"].get("camera") or {}).get("uncertainty") or {}).get("projection_rms_px")
        if pred and pred.get("scan_window") is not None:
            rows.append(["", "predicted by the calibration (1σ RMS, scan window)",
                         fmt(pred["scan_window"], "px")])
        rows.append(["", "fx, fy, cx, cy − true",
                     ", ".join(f"{c[k]:+.3f}" for k in ("dfx_px", "dfy_px", "dcx_px", "dcy_px"))
                     + " px"])
    for L, e in (v.get("lasers") or {}).items():
        if not isinstance(e, dict):
            continue
        rows.append([f"laser plane {L}", "normal angle / d − true",
                     f"{fmt(e['angle_deg'], '°', 5)} / {fmt(e['d_diff_mm'], 'mm', signed=True)}"])
        if "rms_mm" in e:
            rows.append(["", "distance to true plane RMS / max",
                         f"{fmt(e['rms_mm'], 'mm')} / {fmt(e['max_mm'], 'mm')}"])
            rows.append(["", "point shift along the ray RMS",
                         fmt(e["ray_rms_mm"], "mm")])
    la = v.get("lasers") or {}
    if "angle_AB_error_deg" in la:
        rows.append(["laser planes", "angle A–B − true", fmt(la["angle_AB_error_deg"], "°", 5)])
    he = v.get("handeye") or {}
    for name, e in he.items():
        if not isinstance(e, dict):
            continue
        label = f"hand-eye ({he.get('method') or 'chosen'})" if name == "chosen" else \
            f"hand-eye: {name}"
        rows.append([label, "rotation / translation error",
                     f"{fmt(e['rotation_deg'], '°', 5)} / {fmt(e['translation_mm'], 'mm')}"])
        rows.append(["", "point displacement RMS / max",
                     f"{fmt(e['rms_mm'], 'mm')} / {fmt(e['max_mm'], 'mm')}"])
    p.table(["Estimate", "Figure", "Error"], rows, [LEFT, LEFT + 0.27, LEFT + 0.62],
            aligns=["left", "left", "left"], size=7.6)
    p.gap(0.1)
    p.text("Artefacts against their true geometry", size=10, weight="bold")
    rows = []
    for name, s in m["scans"].items():
        t = s.get("truth")
        if not t:
            continue
        art = s["artefact"]
        if art == "gauge_block":
            rows.append([name, "mean height − true height", fmt(t["mean_error_mm"], "mm", signed=True)])
            rows.append(["", "central length − true height",
                         fmt(t["central_length_error_mm"], "mm", signed=True)])
            hp = t.get("heights_over_true_plate")
            if hp:
                rows.append(["", "top points over the TRUE plate: mean − true",
                             fmt(hp["error_mm"], "mm", signed=True)])
            pp = t.get("plate_points_to_true_plate")
            if pp:
                rows.append(["", "plate points to the true plate: mean / RMS",
                             f"{fmt(pp['mean_mm'], 'mm', signed=True)} / {fmt(pp['rms_mm'], 'mm')}"])
            if "plate_normal_angle_deg" in t:
                rows.append(["", "plate normal angle to truth",
                             fmt(t["plate_normal_angle_deg"], "°", 5)])
        elif art == "plane":
            d = t["distance_to_true_plane"]
            rows.append([name, "distance to the TRUE plane: mean / RMS",
                         f"{fmt(d['mean_mm'], 'mm', signed=True)} / {fmt(d['rms_mm'], 'mm')}"])
            rows.append(["", f"share within ±{d['band_mm']:g} mm of the true plane",
                         fmt(d["share_within_band"], "%")])
            rows.append(["", "fitted normal angle to truth", fmt(t["normal_angle_deg"], "°", 5)])
        elif art == "sphere":
            if "centre_distance_mm" in t:
                rows.append([name, "centre − true centre (distance)",
                             fmt(t["centre_distance_mm"], "mm")])
            if "diameter_error_mm" in t:
                rows.append(["", "diameter − true diameter", fmt(t["diameter_error_mm"], "mm",
                                                                  signed=True)])
        elif art == "freeform":
            na = t.get("nominal_alignment")
            if na:
                rows.append([name, "nominal aligned vs its true placement: rotation / points "
                             "moved RMS (max)", f"{fmt(na['rotation_deg'], '°', 5)} / "
                             f"{fmt(na['rms_mm'], 'mm', 5)} ({fmt(na['max_mm'], 'mm', 5)})"])
            d = t.get("deviation_to_true_mesh")
            if not d:
                continue
            if not d.get("n"):  # the cloud is nowhere near the part (a calibration far off)
                rows.append([name, "signed distance to true mesh",
                             f"no point within {fmt(d.get('max_distance_mm'), 'mm', 1)} of the part "
                             f"(of {fmt(d.get('n_total'))})"])
                continue
            rows.append([name, "signed distance to true mesh: mean / RMS",
                         f"{fmt(d['mean_mm'], 'mm', signed=True)} / {fmt(d['rms_mm'], 'mm')}"])
            rows.append(["", "|distance| 95th percentile / max",
                         f"{fmt(d['abs_p95_mm'], 'mm')} / {fmt(d['max_abs_mm'], 'mm')}"])
            rows.append(["", f"share within ±{d['band_mm']:g} mm", fmt(d["share_within_band"], "%")])
            if "n_total" in d:
                rows.append(["", "points used / on the table / off the part",
                             f"{fmt(d['n'])} / {fmt(d['n_table'])} / {fmt(d['n_off_part'])}"])
    if rows:
        p.table(["Scan", "Figure", "Error"], rows, [LEFT, LEFT + 0.14, LEFT + 0.62],
                aligns=["left", "left", "left"], size=7.6)
    else:
        p.text("No scan has true geometry in truth.json.", color=COLOURS["N/A"])
    rows = []
    ref: dict[str, Any] = {}
    for name, s in m["scans"].items():
        lt = s.get("truth_labels")
        if lt and lt.get("checked"):
            ref = lt
            rows.append([name, f"{fmt(lt['checked'])} of {fmt(lt['points'])}",
                         f"{fmt(lt['wrong'])} ({fmt(lt['wrong_rate'], '%')})",
                         f"{fmt(lt['wrong_away_from_crossing'])} / {fmt(lt['wrong_in_crossing_band'])}"])
    if rows:
        p.gap(0.1)
        p.text("A/B labels of the AB frames against the true centre lines", size=10, weight="bold")
        p.text("A point is checked where one true line passes within "
               f"{fmt(ref['near_px'], 'px', 1)} of it in its column and the other does not; the "
               f"crossing band is where the two true lines are within {fmt(ref['crossing_px'], 'px', 0)}.",
               size=8)
        p.table(["Scan", "AB points checked", "wrong labels", "away / in crossing band"], rows,
                [LEFT, LEFT + 0.14, LEFT + 0.42, LEFT + 0.62], aligns=["left"] * 4, size=7.6)
    rows = []
    for name, s in m["scans"].items():
        for laser, sl in sorted(((s.get("truth_labels") or {}).get("speckle_limit") or {}).items()):
            rows.append([name, laser, f"{fmt(sl['bound_px'], 'px', 3)} / "
                         f"{fmt(sl.get('bound_smoothed_px'), 'px', 3)}",
                         fmt(sl["achieved_sigma_px"], "px", 3),
                         f"{sl['ratio']:.2f}× / {sl['ratio_smoothed']:.2f}×"
                         if sl.get("ratio_smoothed") is not None else "–"])
    if rows:
        p.gap(0.1)
        p.text("Stripe centres against the speckle limit", size=10, weight="bold")
        p.text("Bound: the speckle-limited uncertainty of one centre (Dorsch, Häusler & Herrmann "
               "1994: contrast × wavelength × f-number × (1 + magnification) / π, per pixel "
               "pitch), for one profile / after the centre lines' smoothing along the stripe "
               "with independent columns (speckle grains span a column or two, so the smoothed "
               "centres' bound lies between the two); achieved: the robust sigma of the checked "
               "centres' offsets from their true line along the column, away from the crossing "
               "band. Sensor noise and blur add to the speckle.", size=8)
        p.table(["Scan", "Laser", "bound (profile / smoothed)", "achieved", "ratio"], rows,
                [LEFT, LEFT + 0.14, LEFT + 0.24, LEFT + 0.42, LEFT + 0.62], aligns=["left"] * 5,
                size=7.6)
    figs = [p.fig]
    for name, s in m["scans"].items():
        sp = plots["scans"].get(name, {})
        if (s["artefact"] == "freeform" and sp.get("deviation") is not None
                and len(sp["deviation"]) and sp.get("top")):
            q = Page(m, f"Validation: '{name}' against its true surface")
            d = s["truth"]["deviation_to_true_mesh"]
            q.text(f"Signed distance of each point to the true mesh (positive: outside, towards the "
                   f"scanner); RMS {fmt(d['rms_mm'], 'mm')}, 95 % within "
                   f"{fmt(d['abs_p95_mm'], 'mm')}. Not the part's and left out: "
                   f"{fmt(d.get('n_table', 0))} points on the table, {fmt(d.get('n_off_part', 0))} "
                   f"farther than {fmt(d.get('max_distance_mm'), 'mm', 1)} from the part "
                   f"(of {fmt(d.get('n_total', d['n']))}).", size=8.2)
            xy = sp["top"]["xy"][sp["deviation_mask"]] if "deviation_mask" in sp else sp["top"]["xy"]
            _map(q, xy, sp["deviation"], "signed distance to the true surface (mm)",
                 "Deviation map (top view, mean per cell)", height_in=5.0, cmap="coolwarm",
                 symmetric=True)
            figs.append(q.fig)
    return figs


def _json_lines(obj: Any) -> list[str]:
    return json.dumps(obj, indent=1, sort_keys=True, ensure_ascii=False).splitlines()


def page_provenance(m: dict[str, Any]) -> list[Figure]:
    """Version, commit, capture date, tolerances, parameters and the inputs' checksums."""
    pr = m["provenance"]
    p = Page(m, "Provenance")
    for k, val in (("crossline version", pr["crossline_version"]),
                   ("git commit", pr["git_commit"] or "not in a git repository"),
                   ("capture date", pr["capture_date"] or "not recorded in rig.yaml")):
        p.fig.text(LEFT, p.y, k, fontsize=8.5, va="top", weight="bold")
        p.fig.text(LEFT + 0.2, p.y, str(val), fontsize=8.5, va="top", family=MONO)
        p.y -= 8.5 * 1.5 / 72 / A4[1]
    p.gap(0.1)
    p.text("Input files (SHA-256)", size=10, weight="bold")
    rows = [[f"{f['root']}:{f['file']}", f"{f['bytes']:,d}", f["sha256"]] for f in pr["inputs"]]
    figs = [p.fig]
    size = 6.6
    lh = size * 1.55 / 72 / A4[1]
    while rows:
        room = max(1, int((p.y - 0.06) / lh) - 2)
        chunk, rows = rows[:room], rows[room:]
        p.table(["file", "bytes", "sha256"], chunk, [LEFT, LEFT + 0.28, LEFT + 0.36],
                aligns=["left", "right", "left"], size=size, mono=True)
        if rows:
            p = Page(m, "Provenance (continued)")
            figs.append(p.fig)
    lines = ["tolerances:", *_json_lines(pr["tolerances"]),
             "metrology settings:", *_json_lines(pr["metrology"]),
             "parameters (the configuration as given):", *_json_lines(pr["parameters"])]
    p.gap(0.1)
    p.text("Parameters", size=10, weight="bold")
    size = 6.4
    lh = size * 1.4 / 72 / A4[1]
    col_w = (RIGHT - LEFT) / 2
    col = 0
    top = p.y
    for ln in lines:
        if p.y < 0.05:
            if col == 0:
                col, p.y = 1, top
            else:
                p = Page(m, "Provenance: parameters (continued)")
                figs.append(p.fig)
                col, top = 0, p.y
        p.fig.text(LEFT + col * col_w, p.y, ln[:70], fontsize=size, va="top", family=MONO)
        p.y -= lh
    return figs


# ----------------------------------------------------------------------------- assembly


UNCERTAINTY_FIGURES = {"mean_mm": "gauge height (mean)", "flatness_mm": "flatness (all points)",
                       "flatness_95_mm": "flatness (2.5–97.5 %)", "rms_mm": "RMS to the plane",
                       "share_within_band": "share within the band", "diameter_mm": "diameter",
                       "form_error_mm": "form error (all)", "form_error_d95_mm": "form error (D95)",
                       "form_error_vdi_mm": "form error (VDI/VDE 2634-2, 0.3 % discarded)",
                       "form_error_p95_mm": "form error (2.5–97.5 %)"}
BUDGET = {"camera": "camera", "laser_planes": "planes", "handeye": "hand-eye",
          "repeatability": "frames"}


def page_uncertainty(m: dict[str, Any]) -> Figure | None:
    """The uncertainty budget: each figure's U (k = 2), 95 % interval and contributors."""
    scans = {n: s["uncertainty"] for n, s in m["scans"].items() if s.get("uncertainty")}
    errors = {n: s["uncertainty_error"] for n, s in m["scans"].items() if s.get("uncertainty_error")}
    if not scans and not errors:
        return None
    p = Page(m, "Measurement uncertainty")
    first = next(iter(scans.values()), {})
    p.text(f"GUM Supplement 1 Monte Carlo, {first.get('draws', '–')} draws per contributor and as "
           "many of all together. Each draw re-triangulates the scan's own stripe centres with a "
           "calibration drawn from the calibration's covariances (camera intrinsics and "
           "distortion, both laser planes, hand-eye X) and draws the scan's frames again with "
           "replacement (repeatability: stripe noise, speckle and the arm's pose noise as this "
           "scan realised them); the figure is measured again with the report's definition and "
           "segmentation. U = 2 u of all together; the 95 % interval of the draws, from the value; "
           "u: the standard uncertainty of each contributor alone. Lengths in µm, shares in %.",
           size=8)
    p.gap(0.08)
    cells, colours = [], []
    for name, unc in scans.items():
        for key, f in unc["figures"].items():
            share = key == "share_within_band"  # a fraction: in %, the lengths in µm
            scale = 100 if share else 1e3
            lo, hi = (x - f["value"] for x in f["interval_95"])
            cells.append([name, UNCERTAINTY_FIGURES.get(key, key),
                          fmt(f["value"], "%") if share else fmt(f["value"], "mm"),
                          fmt(f["U"] * scale, "", 2),
                          f"{fmt(lo * scale, '', 2, signed=True)} … {fmt(hi * scale, '', 2, signed=True)}",
                          *[fmt(f["budget"][c]["u"] * scale, "", 2) for c in BUDGET],
                          BUDGET.get(f["dominant"], f["dominant"])])
            colours.append([None] * 11)
    if cells:
        p.table(["Scan", "Figure", "Value", "U", "95 % interval − value",
                 *[f"u {v}" for v in BUDGET.values()], "Dominant"], cells,
                [LEFT, LEFT + 0.07, LEFT + 0.24, LEFT + 0.35, LEFT + 0.42, LEFT + 0.56, LEFT + 0.63,
                 LEFT + 0.69, LEFT + 0.76, LEFT + 0.82], size=6.8,
                aligns=["left", "left", "right", "right", "right", "right", "right", "right",
                        "right", "left"])
    for name, why in errors.items():
        p.text(f"{name}: no uncertainty: {why}", size=7.5, color=COLOURS["N/A"])
    for name, unc in scans.items():
        for why in unc.get("incomplete", []):
            p.text(f"{name}: incomplete, {why}: that contributor counts as zero.", size=7.5,
                   color=COLOURS["N/A"])
    decided = [r for r in m["summary"] if r.get("decision")]
    if decided:
        p.gap(0.12)
        p.text("Decision rule (ISO 14253-1)", size=10, weight="bold")
        p.text("Conformance is proven where the value lies inside the limit by at least U, "
               "non-conformance where it lies outside by more than U; in between the result is "
               "inconclusive. The summary's PASS/FAIL compares the value alone.", size=8)
        p.gap(0.04)
        p.table(["Figure", "Scan", "Measured ± U", "Tolerance", "Decision"],
                [[r["figure"], r["scan"] or "", fmt_row_value(r), fmt_tolerance(r), r["decision"]]
                 for r in decided],
                [LEFT, LEFT + 0.33, LEFT + 0.41, LEFT + 0.63, LEFT + 0.78], size=7.5,
                aligns=["left", "left", "right", "right", "left"])
    p.gap(0.1)
    p.text("What U covers, and what it does not", size=10, weight="bold")
    p.text("Covered: the calibration's own noise (as its fits estimate it) and the scan's "
           "repeatability; a camera draw moves the laser planes with it, as they were fitted "
           "through it. Not covered: hand-eye's share of the camera's error (drawn "
           "independently), the camera's model error where distortion terms were fixed, "
           "the arm's systematic error beyond what hand-eye absorbed, biases of the stripe "
           "centres with the angle of incidence (see the sphere's size by incidence), the "
           "artefact's own calibration and temperature. How often the true value lies within "
           "±U on simulated captures: benchmarks/bench_uncertainty.py.", size=8)
    return p.fig


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

"""Style and helpers shared by the accuracy report's pages: the matplotlib settings, colours and
page geometry, the number formatters every printed figure goes through, the A4 ``Page`` with
its text cursor and tables, and the histogram, text box and binned-map plots. Split from
:mod:`crossline.report.pages` (issue 21.3), which assembles the report from them.
"""

from __future__ import annotations

import json
import math
import textwrap
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.font_manager
import matplotlib.lines
import matplotlib.textpath
import numpy as np
from matplotlib.figure import Figure

from crossline.robust import robust_sigma

__all__ = [
    "A4",
    "COLOURS",
    "LASER_COLOURS",
    "LEFT",
    "MONO",
    "RC",
    "RIGHT",
    "SHORT",
    "Page",
    "fmt",
    "fmt_row_value",
    "fmt_tolerance",
    "pretty",
]

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
        # a cell wider than its column wraps onto more lines of its row (a long note would
        # otherwise run off the page or under the next column)
        room = [((xs[i + 1] if i + 1 < len(xs) else RIGHT) - xs[i] - 0.008) * A4[0] * 72
                for i in range(len(columns))]  # points
        prop = matplotlib.font_manager.FontProperties(family=family, size=size)

        def fits(s: str, i: int) -> bool:
            return matplotlib.textpath.TextPath((0, 0), s, prop=prop).get_extents().width <= room[i]

        def wrapped(cell: str, i: int) -> list[str]:
            # text averages well under 0.7 em a character in the report's fonts (digits 0.64):
            # cells that short are not measured
            if aligns[i] != "left" or len(cell) * size * 0.7 <= room[i] or fits(cell, i):
                return [cell]
            lines: list[str] = []
            for word in cell.split():  # greedy, each line measured; a word too long stays whole
                if lines and fits(f"{lines[-1]} {word}", i):
                    lines[-1] += f" {word}"
                else:
                    lines.append(word)
            return lines or [""]

        for r, row in enumerate(rows):
            lines = [wrapped(cell, i) for i, cell in enumerate(row)]
            for i, cell in enumerate(lines):
                col = colours[r][i] if colours and colours[r][i] else "black"
                for k, line in enumerate(cell):
                    self.fig.text(xpos(i), self.y - k * lh, line, fontsize=size, va="top",
                                  ha=aligns[i], color=col, family=family,
                                  weight="bold" if col in COLOURS.values() else "normal")
            self.y -= lh * max(len(x) for x in lines)
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
    rs = robust_sigma(v)
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


def _map(page: Page, xy: np.ndarray | None, h: np.ndarray | None, label: str, title: str, *,
         height_in: float = 3.3, cmap: str = "viridis", symmetric: bool = False,
         image: tuple[np.ndarray, tuple] | None = None) -> None:
    """A map of h over xy binned (:func:`crossline.report.top_view.binned_image`), or of a
    binned ``image`` = (image, extent) already made."""
    from crossline.report.top_view import binned_image

    img, extent = image if image is not None else binned_image(xy, h)
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


def _json_lines(obj: Any) -> list[str]:
    return json.dumps(obj, indent=1, sort_keys=True, ensure_ascii=False).splitlines()

"""The deviations drawn: a colour per point, the coloured cloud's PLY, the deviation map figure.

``deviation_colours`` (a diverging colour map, symmetric about zero), ``write_coloured_ply``
(the points, their colours and the deviation as a scalar field, atomically) and
``deviation_map_figure`` (three orthographic views, the histogram, the regions numbered).
Split from ``crossline.report.nominal`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from crossline.errors import CrosslineError

__all__ = ["deviation_colours", "deviation_map_figure", "write_coloured_ply"]

COLOUR_MAP = "coolwarm"


def deviation_colours(dev: np.ndarray, limit_mm: float) -> np.ndarray:
    """RGB (N, 3) in [0, 1] of deviations on a diverging map, symmetric ±limit_mm, clipped."""
    import matplotlib

    lim = float(limit_mm)
    if not lim > 0:
        raise ValueError("limit_mm must be positive")
    dev = np.asarray(dev, dtype=np.float64).reshape(-1)
    t = np.clip((dev / lim + 1.0) / 2.0, 0.0, 1.0)
    rgb = np.asarray(matplotlib.colormaps[COLOUR_MAP](np.nan_to_num(t, nan=0.5)), dtype=np.float64)[:, :3]
    rgb[~np.isfinite(dev)] = 0.5  # no deviation: neutral grey
    return rgb


def write_coloured_ply(
    path: str | Path, points: np.ndarray, colours: np.ndarray, *, deviation: np.ndarray | None = None
) -> None:
    """Write points (N, 3) mm with RGB colours (N, 3) in [0, 1] as a binary PLY, atomically.

    Coordinates are doubles, colours 8-bit; ``deviation`` (N,) mm, when given, is an extra
    ``double deviation`` vertex property, which CloudCompare reads as a scalar field.
    """
    import open3d as o3d

    path = Path(path)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c = np.clip(np.asarray(colours, dtype=np.float64).reshape(-1, 3), 0.0, 1.0)
    if len(p) != len(c):
        raise ValueError(f"points ({len(p)}) and colours ({len(c)}) differ in number")
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(p)))
    pc.point.colors = o3d.core.Tensor(np.rint(c * 255.0).astype(np.uint8))
    if deviation is not None:
        dv = np.asarray(deviation, dtype=np.float64).reshape(-1, 1)
        if len(dv) != len(p):
            raise ValueError(f"points ({len(p)}) and deviations ({len(dv)}) differ in number")
        pc.point.deviation = o3d.core.Tensor(np.ascontiguousarray(dv))
    if len(p) == 0:
        raise CrosslineError(f"{path}: no points to write (PLY needs at least one)")
    path.parent.mkdir(parents=True, exist_ok=True)
    # Open3D picks the writer by the file's suffix: the temporary file must end in .ply
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.ply", dir=path.parent)
    os.close(fd)
    try:
        if not o3d.t.io.write_point_cloud(tmp, pc, write_ascii=False, compressed=False):
            raise CrosslineError(f"{path}: the coloured cloud could not be written")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def deviation_map_figure(
    points_nominal: np.ndarray,
    dev: np.ndarray,
    limit_mm: float,
    *,
    regions: list[dict[str, Any]] | None = None,
    tolerance_mm: float | None = None,
    max_points: int = 150_000,
    title: str | None = None,
    fig: Figure | None = None,
    rect: tuple[float, float, float, float] | None = None,
) -> Figure:
    """Top, front and side views of the part coloured by deviation, the histogram, a colour bar in mm.

    Views are orthographic along the nominal frame's axes (third-angle layout), nearest
    points drawn last; ``regions`` (from ``deviation_summary``) are marked and numbered
    at their centroids.
    """
    p = np.asarray(points_nominal, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dev, dtype=np.float64).reshape(-1)
    if len(p) != len(d):
        raise ValueError(f"points ({len(p)}) and deviations ({len(d)}) differ in number")
    lim = float(limit_mm)
    ok = np.flatnonzero(np.isfinite(d))
    if len(ok) > max_points:
        ok = np.sort(np.random.default_rng(0).choice(ok, max_points, replace=False))
    p, d = p[ok], d[ok]

    if fig is None:  # a figure of its own; else drawn into ``rect`` (left, bottom, right, top)
        fig = Figure(figsize=(11.0, 8.0), layout="constrained")
        grid = fig.add_gridspec(2, 2)
    else:
        left, bottom, right, top = rect or (0.08, 0.08, 0.92, 0.92)
        grid = fig.add_gridspec(2, 2, left=left, bottom=bottom, right=right, top=top,
                                wspace=0.35, hspace=0.35)
    # (axes position, horizontal axis, vertical axis, depth axis towards the viewer, name)
    views = (((0, 0), 0, 1, 2, "top (x-y)"), ((1, 0), 0, 2, 1, "front (x-z)"),
             ((1, 1), 1, 2, 0, "side (y-z)"))
    axes = []
    sc = None
    for (row, col), h, v, depth, name in views:
        ax = fig.add_subplot(grid[row, col])
        sign = -1.0 if depth == 1 else 1.0  # the front view looks along +y
        order = np.argsort(sign * p[:, depth], kind="stable")
        sc = ax.scatter(p[order, h], p[order, v], c=d[order], s=1.0, cmap=COLOUR_MAP,
                        vmin=-lim, vmax=lim, linewidths=0, rasterized=True)
        for g in regions or []:
            cxyz = g["centroid_mm"]
            ax.plot(cxyz[h], cxyz[v], marker="o", ms=9, mfc="none", mec="k", mew=1.2)
            ax.annotate(str(g.get("id", "")), (cxyz[h], cxyz[v]), xytext=(5, 5),
                        textcoords="offset points", fontsize=9, fontweight="bold")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("xyz"[h] + " (mm)")
        ax.set_ylabel("xyz"[v] + " (mm)")
        ax.set_title(name, fontsize=10)
        axes.append(ax)
    ax = fig.add_subplot(grid[0, 1])
    bins = np.linspace(-lim, lim, 61)
    ax.hist(np.clip(d, -lim, lim), bins=bins, color="0.35")
    if tolerance_mm is not None:
        for t in (-tolerance_mm, tolerance_mm):
            ax.axvline(t, color="k", ls="--", lw=1.0)
    ax.set_xlabel("deviation (mm), clipped at ±limit")
    ax.set_ylabel("points")
    ax.set_title("deviation histogram", fontsize=10)
    if sc is not None:
        bar = fig.colorbar(sc, ax=axes, shrink=0.8, extend="both")
        bar.set_label("deviation from nominal (mm), + = material excess")
    if title:
        fig.suptitle(title)
    return fig

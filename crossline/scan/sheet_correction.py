"""The sheet-curvature correction of a points file: each centre moved by its bias, triangulated again.

A laser sheet of finite thickness on a curved surface lights a profile whose grey centre is
not the sheet's centre (:mod:`crossline.scan.sheet_curvature` models the bias from the
surface's shape and the sheet's thickness). :func:`correct_points_file` reads the points that
:func:`crossline.scan.triangulate.run_triangulate` wrote, measures each laser's sheet
thickness from the centres' widths, moves every centre by its modelled bias and writes the
points again; the stage calls it when ``sheet_curvature`` is on.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from crossline.camera import Camera
from crossline.geometry import transform_points
from crossline.laser import LaserPlanes
from crossline.scan.sheet_curvature import (
    FWHM,
    CellSums,
    centre_shift,
    sheet_sigma,
    skew_response,
    stripe_gradient,
)
from crossline.scan.stripe_gaussian import ACROSS_SLOPE
from crossline.scan.stripes import _frame_work
from crossline.scan.triangulate import POINTS_SCHEMA, triangulate

log = logging.getLogger(__name__)

__all__ = ["correct_points_file"]


def _median(values: Any, default: float) -> float:
    x = np.asarray(values if values is not None else [], dtype=np.float64)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else default


KAPPA_MIN = 0.01  # 1/mm: a flat plate's cells scatter up to ~0.007 with the points' noise
KAPPA_MAX = 2.0  # 1/mm: a surface curved more than this is finer than the shape's cells
# surfaces flatter than gives this bias (3 sigma_f^2 kappa) keep their centres. The estimate
# is a centre's at normal view: at grazing view the bias is several times it, and a cap's fit
# turns a bias that changes with elevation into several times that in diameter (docs/method.md)
BIAS_FLOOR_MM = 0.0002
SHEET_SAMPLE = 60000  # centres whose widths tell the sheet's thickness from the blur


def correct_points_file(
    first: Path, out: Path, cam: Camera, planes: LaserPlanes, T_base_cam: np.ndarray,
    by_number: np.ndarray, sorted_frames: np.ndarray, smeta: dict[str, Any], cells: CellSums,
    meta_of: Any, meta: dict[str, Any],
) -> dict[str, Any]:
    """Write ``out``: the points of ``first`` with each centre moved by its sheet-curvature bias
    (:mod:`crossline.scan.sheet_curvature`) and triangulated again; return the correction's
    figures. ``cells`` holds the scan's points in the base frame (the surface's shape);
    ``meta_of(meta)`` gives the file's key-value metadata.

    Each laser's emitter, which Lambert's term needs, is taken at the foot of the perpendicular
    from the camera centre to its plane: no calibration here measures it, and 50 mm off there
    turns the light's direction by a few degrees at the working distance.
    """
    t0 = time.perf_counter()
    shape = cells.shape()
    del cells
    pf = pq.ParquetFile(first)
    levels, noise = smeta.get("levels") or {}, smeta.get("noise") or {}
    background = _median(levels.get("background"), 0.0)
    data_max = float((smeta.get("data_range") or {}).get("max") or 255.0)
    extractor, params = smeta.get("extractor"), smeta.get("params")
    info: dict[str, Any] = {"enabled": True, "cells": len(shape.keys)}
    kmin = np.inf
    sheet: dict[str, tuple[float, float]] = {}
    if extractor is None or not isinstance(params, dict):
        info["skipped"] = "the stripes file does not name its extractor and parameters"
    else:
        sheet, sampled = _sheet_sigmas(pf, cam, planes, T_base_cam, by_number, sorted_frames, shape)
        blur = next(iter(sheet.values()), (0.0, float("nan")))[1]
        info["sheet_sigma_mm"] = {k: round(v[0], 5) for k, v in sheet.items()}
        info["blur_sigma_px"] = round(blur, 4)
        work = _frame_work(str(extractor), params, data_max)
        wk, kk = skew_response(
            lambda imT: work(0, imT), sampled, blur=blur,
            peak=max(_median(levels.get("peak"), data_max) - background, 1.0), background=background,
            relative_noise=_median(noise.get("relative_noise"), 0.15),
            noise_dn=_median(noise.get("background_noise_dn"), _median(levels.get("noise"), 1.0)),
            data_max=data_max)
        info["response"] = {"sheet_sigma_px": wk.round(3).tolist(), "k": kk.round(3).tolist()}
        # which profiles ran across the stripe instead of along their column (row)
        across = (0.0 if extractor == "steger"
                  else ACROSS_SLOPE if extractor == "gaussian" and params.get("fit_across") else np.inf)
        if len(wk) == 0:
            info["skipped"] = "no sheet resolved from the blur, or the extractor found no synthetic stripe"
        else:
            # curved enough for a bias of BIAS_FLOOR_MM (about 3 sigma_f^2 kappa), and above the
            # curvature that the points' noise gives a flat surface
            thick = max((v[0] for v in sheet.values()), default=0.0)
            kmin = max(KAPPA_MIN, BIAS_FLOOR_MM / (3.0 * thick**2)) if thick > 0 else np.inf
            if not kmin <= KAPPA_MAX:
                kmin = np.inf  # the sheet is too thin to matter on any surface the cells resolve
            info["curvature_min_per_mm"] = round(float(kmin), 5) if np.isfinite(kmin) else None
    moved, shifts = 0, []
    with pq.ParquetWriter(out, POINTS_SCHEMA, compression="zstd",
                          use_dictionary=["frame", "laser", "lasers", "flags"],
                          write_statistics=["frame"]) as w:
        for g in range(pf.num_row_groups):
            t = pf.read_row_group(g)
            if "skipped" not in info and np.isfinite(kmin):
                t, sh = _corrected_group(t, cam, planes, T_base_cam, by_number, sorted_frames,
                                         shape, kmin, wk, kk, across, sheet)
                moved += sh.size
                shifts.append(sh)
            w.write_table(t, row_group_size=t.num_rows)
        sh = np.abs(np.concatenate(shifts)) if shifts else np.empty(0)
        info.update({
            "cells_fitted": int(shape.fitted),
            "points_moved": int(moved),
            "median_shift_px": float(np.median(sh)) if sh.size else 0.0,
            "p95_shift_px": float(np.quantile(sh, 0.95)) if sh.size else 0.0,
        })  # no timing here: the file is byte-identical run to run (it goes to the log)
        meta["sheet_curvature"] = info
        w.add_key_value_metadata(meta_of(meta))
    log.info("sheet curvature: %d centres on curved surfaces moved (median %.4f px, 95 %% %.4f px); "
             "sheet sigma %s mm; %.2f s", moved, info["median_shift_px"], info["p95_shift_px"],
             info.get("sheet_sigma_mm"), time.perf_counter() - t0)
    return info


def _frame_geometry(t: pa.Table, T_base_cam: np.ndarray, by_number: np.ndarray,
                    sorted_frames: np.ndarray, shape: Any, rows: np.ndarray):
    """Camera-frame points and surface shapes of ``rows`` of a points table."""
    frame = t.column("frame").to_numpy()[rows]
    fpos = by_number[np.searchsorted(sorted_frames, frame)]
    pc = np.stack([t.column(c).to_numpy()[rows] for c in ("x_cam", "y_cam", "z_cam")], 1)
    pb = np.stack([t.column(c).to_numpy()[rows] for c in ("x", "y", "z")], 1)
    return fpos, pc, shape.cell_of(pb)


def _to_cam(R: np.ndarray, shape: Any, cell: np.ndarray) -> list[np.ndarray]:
    return [np.einsum("nji,nj->ni", R, a[cell]) for a in (shape.normal, shape.e1, shape.e2)]


def _sheet_sigmas(pf: pq.ParquetFile, cam: Camera, planes: LaserPlanes, T_base_cam: np.ndarray,
                  by_number: np.ndarray, sorted_frames: np.ndarray, shape: Any
                  ) -> tuple[dict[str, tuple[float, float]], np.ndarray]:
    """Each laser's sheet sigma (mm) and the blur (px), from a sample of the scan's centres,
    and the sheet's sigma across the stripe (px) at those centres."""
    step = max(1, -(-pf.metadata.num_rows // SHEET_SAMPLE))
    got: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {n: [] for n in planes.names}
    start = 0
    for g in range(pf.num_row_groups):
        t = pf.read_row_group(g, columns=["frame", "laser", "u", "v", "x_cam", "y_cam", "z_cam",
                                          "x", "y", "z", "width_n"])
        rows = np.arange((-start) % step, t.num_rows, step)
        start += t.num_rows
        fpos, pc, cell = _frame_geometry(t, T_base_cam, by_number, sorted_frames, shape, rows)
        lab = t.column("laser").to_numpy(zero_copy_only=False).astype(str)[rows]
        uv = np.stack([t.column("u").to_numpy()[rows], t.column("v").to_numpy()[rows]], 1)
        wn = t.column("width_n").to_numpy()[rows].astype(np.float64)
        shape.ensure(cell[cell >= 0])
        ok = cell >= 0
        ok[ok] = shape.ok[cell[ok]]
        R = T_base_cam[fpos, :3, :3]
        for name in planes.names:
            m = np.flatnonzero(ok & (lab == name))
            if m.size:
                pl = planes[name]
                geo = (*_to_cam(R[m], shape, cell[m]), shape.second[cell[m]])
                grad, _ = stripe_gradient(cam, pl.normal, pl.d, uv[m], pc[m], *geo)
                got[name].append((grad, wn[m] / FWHM))
    joined = {k: (np.concatenate([a for a, _ in v]), np.concatenate([b for _, b in v]))
              for k, v in got.items() if v}
    sig, blur = sheet_sigma(joined)
    # the sheet's own sigma (px, across the stripe) at the sampled centres: the synthetic
    # profiles of the extractor's response cover these
    with np.errstate(divide="ignore"):  # |grad f| = 0: no profile (left out by skew_response)
        sampled = np.concatenate([sig[k] / g for k, (g, _) in joined.items() if sig.get(k, 0) > 0] or [[]])
    return {k: (v, blur) for k, v in sig.items()}, sampled


def _corrected_group(t: pa.Table, cam: Camera, planes: LaserPlanes, T_base_cam: np.ndarray,
                     by_number: np.ndarray, sorted_frames: np.ndarray, shape: Any, kmin: float,
                     wk: np.ndarray, kk: np.ndarray, across: float,
                     sheet: dict[str, tuple[float, float]]) -> tuple[pa.Table, np.ndarray]:
    """One row group with the centres on curved surfaces corrected; (table, their shifts px)."""
    n_rows = t.num_rows
    fpos, pc, cell = _frame_geometry(t, T_base_cam, by_number, sorted_frames, shape, np.arange(n_rows))
    lab = t.column("laser").to_numpy(zero_copy_only=False).astype(str)
    uv = np.stack([t.column("u").to_numpy(), t.column("v").to_numpy()], 1)
    pb = np.stack([t.column(c).to_numpy() for c in ("x", "y", "z")], 1)
    wn = t.column("width_n").to_numpy().astype(np.float64)
    axis = t.column("axis").to_numpy()
    use = (cell >= 0) & np.isfinite(wn) & np.isfinite(pc).all(1)
    shape.ensure(cell[use])
    use[use] = shape.ok[cell[use]] & (shape.curvature(cell[use]) > kmin)
    R = T_base_cam[fpos, :3, :3]  # base <- cam of each point's frame
    bias = np.full(n_rows, np.nan)
    scale = np.ones(n_rows)  # px along the column (row) per px along the profile
    for name in planes.names:
        m = np.flatnonzero(use & (lab == name))
        sig = sheet.get(name, (0.0, np.nan))[0]
        if m.size == 0 or not sig > 0:
            continue
        pl = planes[name]
        c = cell[m]
        geo = (*_to_cam(R[m], shape, c), shape.second[c])
        g, ph = stripe_gradient(cam, pl.normal, pl.d, uv[m], pc[m], *geo)
        # a profile fitted across the stripe (the extractor's steep stripes) is along the normal
        with np.errstate(invalid="ignore", divide="ignore"):
            a_, b_ = np.abs(ph[:, 0]), np.abs(ph[:, 1])
            steep = np.where(axis[m] == 1, b_ / a_, a_ / b_) > across
            along = np.where((axis[m] == 1)[:, None], [1.0, 0.0], [0.0, 1.0])
            along[steep] = np.nan
            # the extractor's response at the sheet's width along the profile it took
            p_ = np.where(np.isfinite(along), along, ph)
            cos = np.abs(np.einsum("ij,ij->i", p_, ph))
            k = np.interp(sig / (g * cos), wk, kk)
            bias[m], _, _ = centre_shift(cam, pl.normal, pl.d, uv[m], pc[m], *geo, sigma_f=sig, k=k,
                                         along=along, emitter=-pl.d * np.asarray(pl.normal),
                                         gradient=(g, ph))
            # a centre stays on its column (row): one fitted across the stripe was carried
            # along the line to it, and so is its shift
            scale[m] = np.where(steep, np.where(axis[m] == 0, ph[:, 1], ph[:, 0]), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = bias / scale
    # a shift beyond half the profile's width is no skew but a wrong shape (an edge, a step)
    ok = np.isfinite(shift) & (np.abs(shift) <= 0.5 * wn / FWHM)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return t, np.empty(0)
    new = uv.copy()
    col = axis[idx] == 0
    new[idx[col], 1] -= shift[idx[col]]
    new[idx[~col], 0] -= shift[idx[~col]]
    pc[idx] = triangulate(cam, planes, new[idx], lab[idx])
    pb[idx] = transform_points(T_base_cam, pc[idx], fpos[idx])
    for names, arr in ((("u", "v"), new), (("x_cam", "y_cam", "z_cam"), pc), (("x", "y", "z"), pb)):
        for i, c in enumerate(names):
            t = t.set_column(t.schema.get_field_index(c), c, pa.array(arr[:, i]))
    return t, shift[idx]

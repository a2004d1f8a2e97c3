"""The accuracy report of a capture: every figure measured, checked and written twice.

``run_report`` reads the calibrations, the points and the fused clouds of a capture,
measures each scan's artefact (``crossline.report.metrics``), compares laser A with laser B,
scores everything against ``truth.json`` when the capture is simulated, and writes

- ``metrics.json``: every figure of the report, with its tolerance and PASS/FAIL, and the
  provenance (version, commit, parameters, input checksums, capture date);
- ``accuracy.pdf``: the same numbers as pages a metrologist reads like a calibration
  certificate (``crossline.report.pages`` draws them from the metrics, never from anything
  else, so the two cannot disagree).

Both are deterministic: same inputs, same bytes. Nothing here depends on the clock.

The configuration (``--config`` file or ``--config-json`` text) is the workflow's parameter
set; the report reads ``report.tolerances`` and ``report.metrology`` from it (defaults
below) and records all of it as provenance.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from crossline import __version__
from crossline.errors import CrosslineError
from crossline.geometry import make_transform
from crossline.io.atomic import atomic_path, to_jsonable, write_json
from crossline.io.settings import read_settings

__all__ = [
    "DEFAULT_METROLOGY",
    "DEFAULT_TOLERANCES",
    "ReportData",
    "build_report",
    "load_config",
    "points_per_frame",
    "read_mesh",
    "run_report",
]

log = logging.getLogger(__name__)

FORMAT = "crossline-metrics/1"

DEFAULT_TOLERANCES: dict[str, float] = {
    "gauge_mean_error_mm": 0.003,  # |mean height − nominal|
    "gauge_std_mm": 0.006,  # standard deviation of the heights
    "plane_within_share": 0.99,  # share of plate points within ±plane_band_mm of the plane
    "plane_band_mm": 0.05,  # the band of the plane histogram (the paper: ±0.05 mm)
    "sphere_size_error_mm": 0.01,  # |fitted − nominal diameter|
    "sphere_form_error_mm": 0.03,  # range of radial residuals (statistic: see below)
    "ab_height_difference_mm": 0.005,  # |gauge height from A points − from B points|
    "nominal_within_share": 0.95,  # freeform with a nominal: share within ±nominal_band_mm of it
    "nominal_band_mm": 0.05,  # the tolerance band around the nominal surface
}

DEFAULT_METROLOGY: dict[str, Any] = {
    "edge_margin_mm": 1.0,  # gauge: leave out points this close to the block's edges
    "segment_band_mm": 0.2,  # gauge: half-width of the layer of points that counts as a face
    "sphere_ransac_mm": 0.2,  # sphere: RANSAC inlier band around the nominal sphere
    "sphere_trim_sigma": 5.0,  # sphere: inliers re-selected at this many robust sigmas
    "sphere_form_statistic": "all",  # which form error is checked: all | vdi | d95 | p95
    # gauge heights referenced to the plate in the same frame ("frame", cancels the arm's pose
    # error of each frame) or to the plate plane of the whole scan ("plane", the paper's)
    "gauge_reference": "frame",
    # validation: the measured volume's depths in front of the camera; None = the depths the
    # scans measured at, else where the true laser planes cross the scan window
    "volume_z_mm": None,
    "freeform_max_distance_mm": 1.0,  # validation: farther from the true part = not the part's
    "histogram_bins": 60,
    "seed": 0,
    # Monte Carlo draws per contributor for each figure's uncertainty (0: none); u to about
    # 1 / sqrt(2 (draws - 1)) of itself, 5 % at 200
    "uncertainty_draws": 200,
    # points the Monte Carlo is run on at most (a uniform sample of a longer scan; 0 = all):
    # each draw re-triangulates them, so its time grows with them
    "uncertainty_points": 200000,
}

FORM_KEYS = {"all": "form_error_mm", "vdi": "form_error_vdi_mm", "d95": "form_error_d95_mm",
             "p95": "form_error_p95_mm"}


# ----------------------------------------------------------------------------- config


def load_config(config: str | Path | dict | None) -> tuple[dict, dict, dict]:
    """The full parameter set, the tolerances and the metrology settings of a report.

    ``config`` is a dict, a JSON file, JSON text, or None (defaults). Tolerances are read
    from ``report.tolerances`` (or a top-level ``tolerances``), settings from
    ``report.metrology`` (or ``metrology``); unknown keys are kept as provenance only.
    """
    full = read_settings(config, "report configuration")
    rep = full.get("report", {}) if isinstance(full.get("report", {}), dict) else {}
    tol = dict(DEFAULT_TOLERANCES)
    tol.update(rep.get("tolerances", full.get("tolerances", {})) or {})
    met = dict(DEFAULT_METROLOGY)
    met.update(rep.get("metrology", full.get("metrology", {})) or {})
    if met["gauge_reference"] not in ("frame", "plane"):
        raise ValueError(f"report.metrology.gauge_reference must be 'frame' or 'plane', "
                         f"got {met['gauge_reference']!r}")
    if met["sphere_form_statistic"] not in FORM_KEYS:
        raise CrosslineError(
            f"report.metrology.sphere_form_statistic must be one of {sorted(FORM_KEYS)}, "
            f"got {met['sphere_form_statistic']!r}"
        )
    for k, v in tol.items():
        if not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
            raise CrosslineError(f"report.tolerances.{k} must be a number >= 0, got {v!r}")
    return full, tol, met


# ----------------------------------------------------------------------------- inputs


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable (%s); its section is left out", path, exc)
        return None
    return data if isinstance(data, dict) else None


def _finite(value: Any, shape: tuple[int, ...]) -> bool:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return a.shape == shape and bool(np.isfinite(a).all())


def calibration_problem(kind: str, data: dict) -> str | None:
    """Why ``data`` (camera.json, lasers.json or handeye.json as read) lacks what the report
    and the certificate read of a ``kind`` calibration, or None when it has it."""
    if kind == "camera":
        size, dist = data.get("image_size"), data.get("dist")
        if not (_finite(data.get("K"), (3, 3)) and isinstance(dist, list) and _finite(dist, (len(dist),))
                and isinstance(size, list) and len(size) == 2):
            return "expected finite 'K' (3x3), 'dist' and 'image_size' [width, height]"
    elif kind == "lasers":
        for L in ("A", "B"):
            if L == "A" or L in data:
                pl = data.get(L)
                if not (isinstance(pl, dict) and _finite(pl.get("normal"), (3,))
                        and _finite(pl.get("d"), ()) and np.linalg.norm(pl["normal"]) > 0):
                    return (f"expected the plane of laser {L} as {{'normal': [nx, ny, nz], 'd': d}}, "
                            f"finite, the normal not zero")
    elif kind == "handeye" and not _finite(data.get("T_tool_cam"), (4, 4)):
        return "expected 'T_tool_cam', a finite 4x4 matrix"
    return None


def _sha256(path: Path) -> str:
    from crossline.io.provenance import file_sha256

    return file_sha256(path)


def _git_commit() -> str | None:
    try:
        from crossline.io.provenance import git_commit

        return git_commit()
    except Exception:  # provenance must never stop a report
        return None


@dataclass
class ScanData:
    """What the report knows about one scan (arrays for plots included)."""

    name: str
    artefact: str
    nominal: dict[str, float]
    states: np.ndarray | None = None  # laser state per frame, in frame order
    frame_ids: np.ndarray | None = None
    point_frames: np.ndarray | None = None  # frame of each triangulated point
    point_lasers: np.ndarray | None = None
    cloud: dict[str, np.ndarray] | None = None  # points, normals, laser (codes), frame
    cloud_source: str = ""
    fuse_stats: dict | None = None
    points_path: Path | None = None
    points_info: dict | None = None
    mesh: str | None = None  # a freeform's nominal mesh, relative to the capture
    T_base_nominal: np.ndarray | None = None  # its placement as rig.yaml gives it (a datum)
    plots: dict[str, Any] = field(default_factory=dict)


@dataclass
class ReportData:
    """Everything measured for a report: the metrics (JSON) and the arrays its plots need."""

    metrics: dict[str, Any]
    plots: dict[str, Any]


def points_per_frame(
    frame_ids: np.ndarray, states: np.ndarray, point_frames: np.ndarray
) -> dict[str, Any]:
    """Points per frame, by laser state, and the gain of the cross-line over a single line.

    The gain is the mean number of points per frame over all frames of the scan (every
    frame costs the same time) divided by the mean per single-laser frame (A or B): the
    paper's 4/3 for the pattern A, B, AB when each stripe gives the same number of points.
    """
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    states = np.asarray(states).astype(str)
    order = np.argsort(frame_ids, kind="stable")
    frame_ids, states = frame_ids[order], states[order]
    point_frames = np.asarray(point_frames, dtype=np.int64)
    if len(frame_ids):
        pos = np.clip(np.searchsorted(frame_ids, point_frames), 0, len(frame_ids) - 1)
        known = frame_ids[pos] == point_frames
    else:
        pos = np.zeros(len(point_frames), dtype=np.int64)
        known = np.zeros(len(point_frames), dtype=bool)
    counts = np.bincount(pos[known], minlength=len(frame_ids)).astype(np.int64)
    by_state = {}
    for s in ("A", "B", "AB", "off"):
        m = states == s
        if m.any():
            by_state[s] = {"frames": int(m.sum()), "points": int(counts[m].sum()),
                           "points_per_frame": float(counts[m].mean())}
    single = (states == "A") | (states == "B")
    n = len(frame_ids)
    out: dict[str, Any] = {
        "frames": n,
        "points": int(counts.sum()),
        "points_outside_frames": int((~known).sum()),
        "points_per_frame": float(counts.sum() / n) if n else None,
        "by_state": by_state,
        "points_per_single_laser_frame": float(counts[single].mean()) if single.any() else None,
    }
    ppf, ps = out["points_per_frame"], out["points_per_single_laser_frame"]
    out["gain_over_single_line"] = ppf / ps if ppf is not None and ps else None
    out["_counts"] = counts  # for the plot; removed before JSON
    return out


def _load_scan(
    name: str, spec: Any, root: Path, interim: Path, processed: Path, files: list
) -> ScanData:
    import pandas as pd

    from crossline.fuse import read_ply

    sd = ScanData(name, spec.artefact, dict(spec.nominal), mesh=getattr(spec, "mesh", None),
                  T_base_nominal=getattr(spec, "T_base_nominal", None))
    if sd.mesh and (root / sd.mesh).is_file():
        files.append(("capture", sd.mesh, root / sd.mesh))
    fcsv = root / "scans" / name / "frames.csv"
    if fcsv.is_file():
        files.append(("capture", f"scans/{name}/frames.csv", fcsv))
        try:
            fr = pd.read_csv(fcsv, usecols=["frame", "lasers"], dtype={"lasers": str},
                             keep_default_na=False)
            sd.frame_ids = fr["frame"].to_numpy(np.int64)
            sd.states = fr["lasers"].str.strip().to_numpy(str)
        except (ValueError, KeyError) as exc:
            log.warning("%s: unreadable (%s)", fcsv, exc)
    pq = interim / "points" / f"{name}.parquet"
    if pq.is_file():
        sd.points_path = pq
        files.append(("interim", f"points/{name}.parquet", pq))
        try:
            df = pd.read_parquet(pq, columns=["frame", "laser"])
            sd.point_frames = df["frame"].to_numpy(np.int64)
            lab = df["laser"].astype(str)
            sd.point_lasers = np.select([lab == "A", lab == "B"], [1, 2], 0).astype(np.uint8)
        except Exception as exc:  # pyarrow raises several types for broken files
            log.warning("%s: unreadable (%s)", pq, exc)
    side = interim / "points" / f"{name}.json"
    if side.is_file():
        files.append(("interim", f"points/{name}.json", side))
        sd.points_info = _read_json(side)
    ply = processed / f"{name}.ply"
    if ply.is_file():
        files.append(("processed", f"{name}.ply", ply))
        try:
            sd.cloud = read_ply(ply)
            sd.cloud_source = f"{name}.ply"
        except (ValueError, KeyError, OSError) as exc:
            log.warning("%s: unreadable (%s)", ply, exc)
    if sd.cloud is None and pq.is_file():
        try:
            df = pd.read_parquet(pq, columns=["x", "y", "z", "laser", "frame"])
            codes = np.select([df["laser"].astype(str) == "A", df["laser"].astype(str) == "B"],
                              [1, 2], 0).astype(np.uint8)
            sd.cloud = {"points": df[["x", "y", "z"]].to_numpy(np.float64), "laser": codes,
                        "frame": df["frame"].to_numpy(np.int64)}
            sd.cloud_source = f"points/{name}.parquet (no fused cloud)"
        except Exception as exc:
            log.warning("%s: no usable points (%s)", pq, exc)
    for cand in (processed / f"{name}.fuse.json", processed / f"{name}.json"):
        if cand.is_file():
            files.append(("processed", cand.name, cand))
            sd.fuse_stats = _read_json(cand)
            break
    return sd


# ----------------------------------------------------------------------------- checks


def _check(
    rows: list, cid: str, label: str, scan: str | None, value: float | None, unit: str,
    limit: float | None, comparison: str = "<=", use_abs: bool = False, note: str = "",
) -> None:
    """Append one summary row: a figure, its tolerance and whether it passes."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        status = "N/A"
    elif limit is None:
        status = "INFO"
    else:
        v = abs(value) if use_abs else value
        status = "PASS" if (v <= limit if comparison == "<=" else v >= limit) else "FAIL"
    rows.append({"id": cid, "figure": label, "scan": scan, "value": value, "unit": unit,
                 "abs": use_abs, "comparison": comparison, "tolerance": limit,
                 "status": status, "note": note})


# the Monte Carlo figure whose uncertainty a summary row's value has
# (sphere_form_error_mm: the configured form statistic's)
ROW_FIGURES = {"gauge_mean_error_mm": "mean_mm", "plane_within_share": "share_within_band",
               "plane_flatness_95_mm": "flatness_95_mm", "sphere_size_error_mm": "diameter_mm",
               "sphere_form_error_d95_mm": "form_error_d95_mm",
               "sphere_form_error_vdi_mm": "form_error_vdi_mm", "plane_flatness_mm": "flatness_mm"}


def _with_uncertainty(row: dict, unc: dict | None, form_key: str) -> None:
    """Give a summary row its expanded uncertainty U (k = 2) and the ISO 14253-1 decision.

    Conformance is proven where the value is inside the limit by at least U, non-conformance
    where it is outside by more than U; in between the result is inconclusive (the PASS/FAIL
    status stays the plain comparison of the value).
    """
    key = form_key if row["id"] == "sphere_form_error_mm" else ROW_FIGURES.get(row["id"])
    fig = ((unc or {}).get("figures") or {}).get(key) if key else None
    if fig is None or row["value"] is None or not np.isfinite(fig["U"]):
        return  # no U where the draws leave it undetermined (too few frames): no decision either
    U = float(fig["U"])
    row["U"] = U
    row["k"] = fig["k"]
    row["dominant"] = fig["dominant"]
    if row["tolerance"] is None:
        return
    v = abs(row["value"]) if row["abs"] else row["value"]
    lim = row["tolerance"]
    inside, outside = (v + U <= lim, v - U > lim) if row["comparison"] == "<=" else \
        (v - U >= lim, v + U < lim)
    row["decision"] = ("conforms" if inside else "does not conform" if outside
                       else "inconclusive (within U of the limit)")


# ----------------------------------------------------------------------------- measure


def _up_vector(cloud: dict[str, np.ndarray]) -> np.ndarray | None:
    n = cloud.get("normals")
    if n is None or len(n) == 0:
        return None
    m = np.asarray(n, dtype=np.float64).mean(0)
    norm = np.linalg.norm(m)
    return m / norm if norm > 0.1 else None


def _basis(up: np.ndarray) -> np.ndarray:
    from crossline.report.metrics import plane_basis

    return plane_basis(up)


def _nominal_comparison(P: np.ndarray, mesh: Path, tol: dict, met: dict,
                        T_base_nominal: np.ndarray | None = None,
                        frames: np.ndarray | None = None) -> tuple[dict, dict]:
    """A freeform cloud (base frame) against its nominal mesh: alignment, signed deviations
    within the tolerance band, the out-of-tolerance regions; and the arrays of its page.

    ``T_base_nominal`` (rig.yaml's ``nominal_pose``, the part's placement probed on its datums)
    starts the fine alignment in place of the feature-based search, which a part's symmetry or
    a nearly flat patch leaves ambiguous."""
    from crossline.report import nominal as nm

    V, F = nm.load_nominal(mesh)
    initial = None if T_base_nominal is None else np.linalg.inv(T_base_nominal)
    al = nm.align_to_nominal(P, V, F, seed=int(met["seed"]), initial=initial)
    if al["ambiguous"]:
        why = (f"{al['rival_poses']} other pose(s) fit the scanned surface as well but place it "
               "elsewhere on the part" if al["rival_poses"] else
               f"the scanned surface fixes one motion of the part {al['weakest_mode_ratio']:.1e} "
               f"as firmly as another (under {nm.WEAK_MODE_RATIO:g}): it could slide on its drawing")
        raise CrosslineError(
            f"{mesh.name}: the alignment is ambiguous: {why} (a symmetric part, or too little of "
            "it scanned): scan more of the part, or give a datum")
    T = np.asarray(al["T_nominal_cloud"], dtype=np.float64)
    Q = P @ T[:3, :3].T + T[:3, 3]
    dev = nm.signed_deviation(Q, V, F)
    keep = np.isfinite(dev)
    support = nm.support_plane(V, F)
    n_support = 0
    if support is not None:
        # the surface the part stands on, which its drawing leaves open: points within a few
        # noise sigmas of that plane (the table, the part's very foot) are not compared
        margin = max(0.1, 5.0 * float(al["inlier_rmse_mm"]))
        on_support = (Q @ support[0] + support[1]) < margin
        n_support = int((on_support & keep).sum())
        keep &= ~on_support
    band = float(tol["nominal_band_mm"])
    summ = nm.deviation_summary(dev[keep], tolerance_mm=band, points=Q[keep],
                                max_distance_mm=float(met["freeform_max_distance_mm"]),
                                frames=None if frames is None else np.asarray(frames)[keep])
    out = {
        "nominal": mesh.name, "triangles": len(F),
        "alignment": {k: v for k, v in al.items() if k != "T_nominal_cloud"},
        "T_nominal_cloud": T.tolist(),
        "n_support": n_support, "support_margin_mm": margin if support is not None else None,
        **summ,
    }
    shown = keep & (np.abs(dev) <= float(met["freeform_max_distance_mm"]))
    return out, {"points": Q[shown], "dev": dev[shown], "regions": summ.get("regions") or [],
                 "band": band}


def _alignment_error(T_nominal_cloud: np.ndarray, T_base_nominal: np.ndarray,
                     P: np.ndarray) -> dict[str, float]:
    """The alignment against the true placement: rotation, translation, and how far the
    cloud's points land from where the true transform puts them (RMS, max)."""
    from crossline.report import metrics as mt

    true = np.linalg.inv(T_base_nominal)
    e = mt.transform_error(T_nominal_cloud, true, P)
    return {k: v for k, v in e.items() if isinstance(v, int | float)}


def _whole_cloud(figures: Any, subset: np.ndarray | None = None) -> Any:
    """A figures function that needs no per-point state: the same on any subset."""
    return figures


def _uncertainty(sd: ScanData, figures: Any, model: Any, met: dict, root: Path) -> dict[str, Any]:
    """Each figure's Monte Carlo uncertainty (:mod:`crossline.report.uncertainty`) on the scan's cloud."""
    from crossline.io.capture import read_frames_table
    from crossline.report import uncertainty as uc

    table = read_frames_table(root / "scans" / sd.name / "frames.csv")
    c = sd.cloud
    sub = uc.subsample(len(c["points"]), int(met["uncertainty_points"]))
    pick = slice(None) if sub is None else sub
    laser = np.where(np.asarray(c["laser"])[pick] == 2, "B", "A")
    sp = uc.scan_points(np.asarray(c["points"])[pick], laser, np.asarray(c["frame"])[pick],
                        table.frames, table.T_base_tool, model)
    draws = int(met["uncertainty_draws"])
    out = {"figures": uc.monte_carlo(sp, model, figures(subset=sub), draws=draws,
                                     seed=int(met["seed"])),
           "draws": draws, "frames": sp.n_frames, "points": len(sp.points),
           "points_of_cloud": len(c["points"]),
           "contributors": list(uc.CONTRIBUTORS), "coverage_factor": uc.COVERAGE_FACTOR,
           "method": uc.METHOD}
    if model.missing:
        out["incomplete"] = list(model.missing)
    return out


def _measure_scan(sd: ScanData, tol: dict, met: dict, truth: dict | None, root: Path,
                  files: list, lasers: tuple[str, ...] = ("A", "B"), model: Any = None
                  ) -> dict[str, Any]:
    """The figures of one scan (counts, artefact, A vs B, truth) and its plot arrays.

    With a calibration ``model`` (:func:`crossline.report.uncertainty.calibration_model`) each
    checked figure gets its Monte Carlo uncertainty under ``uncertainty``.
    """
    from crossline.io.capture import truth_file
    from crossline.report import metrics as mt
    from crossline.report import uncertainty as uc

    out: dict[str, Any] = {"artefact": sd.artefact, "nominal": sd.nominal,
                           "cloud_source": sd.cloud_source or None}
    if tuple(lasers) != ("A", "B"):  # said only where it is not the two-laser rig
        out["lasers"] = list(lasers)
    counts: dict[str, Any] = {}
    if sd.point_frames is not None:
        counts["points"] = len(sd.point_frames)
        nl = np.bincount(sd.point_lasers, minlength=3)
        counts["points_by_laser"] = {L: int(nl[1 + i]) for i, L in enumerate(("A", "B"))
                                     if L in lasers or nl[1 + i]}
        if nl[0]:
            counts["points_by_laser"]["other"] = int(nl[0])
    if sd.frame_ids is not None and sd.point_frames is not None:
        ppf = points_per_frame(sd.frame_ids, sd.states, sd.point_frames)
        sd.plots["frame_counts"] = ppf.pop("_counts")
        sd.plots["frame_states"] = np.asarray(sd.states)[np.argsort(sd.frame_ids, kind="stable")]
        counts.update(ppf)
    elif sd.frame_ids is not None:
        counts["frames"] = len(sd.frame_ids)
    if sd.fuse_stats:
        fs = sd.fuse_stats
        counts["fused"] = {k: fs[k] for k in ("n_input", "n_outliers", "n_after_outlier_removal",
                                              "n_output") if k in fs}
        if isinstance(fs.get("parameters"), dict):
            counts["fused"]["parameters"] = fs["parameters"]
        ref = fs.get("refine")
        if isinstance(ref, dict) and ref.get("skipped"):
            counts["fused"]["pose_refinement"] = {"skipped": ref["skipped"]}
        elif isinstance(ref, dict):
            # what the pose refinement saw and did: it changes every figure of the scan
            counts["fused"]["pose_refinement"] = {
                k: ref[k] for k in ("crossings", "used", "frames", "frames_with_crossings",
                                    "gap_rms_before_mm", "gap_rms_after_mm", "ab_offset_mm",
                                    "correction_rms_mm", "correction_max_mm") if k in ref}
    if sd.points_info:
        counts["triangulation"] = sd.points_info
    out["counts"] = counts
    if sd.cloud is None or len(sd.cloud["points"]) == 0:
        out["error"] = "no points (neither a fused cloud nor a points file)"
        return out

    P = sd.cloud["points"]
    labels = np.asarray(sd.cloud.get("laser", np.zeros(len(P), np.uint8))).astype(np.uint8)
    out["cloud_points"] = len(P)
    up = _up_vector(sd.cloud)
    seed = int(met["seed"])
    band = float(tol["plane_band_mm"])
    bins = int(met["histogram_bins"])
    tscan = (truth or {}).get("scans", {}).get(sd.name) if truth else None
    sd.plots["hist"] = None
    height_ref: tuple[np.ndarray, float] | None = None  # plane the top view's height is from
    # the artefact's figures as a function of its points, given the indices of the points
    # they are evaluated on (None: all), for the uncertainty
    figures = None
    try:
        if sd.artefact == "gauge_block":
            nominal = float(sd.nominal.get("height", np.nan))
            frames = sd.cloud.get("frame") if met["gauge_reference"] == "frame" else None
            g = mt.measure_gauge_block(P, nominal, edge_margin_mm=float(met["edge_margin_mm"]),
                                       band_mm=float(met["segment_band_mm"]), up=up, seed=seed,
                                       frame=frames)
            f = g.figures()
            out["measurement"] = f
            out["a_vs_b"] = _ab(mt.compare_lasers, "gauge_block", P, labels, out, gauge=g)
            sd.plots["hist"] = {"values": g.heights, "xlabel": "height above the plate plane (mm)",
                                "nominal": nominal, "bins": bins, "kind": "gauge"}
            height_ref = (g.plate_normal, g.plate_d)
            figures = partial(uc.gauge_figures, g, P, frames)
            if tscan:
                out["truth"] = _gauge_truth(g, P, tscan, nominal)
        elif sd.artefact == "plane":
            r = mt.measure_plane(P, band_mm=band, up=up)
            out["measurement"] = r.figures()
            out["a_vs_b"] = _ab(mt.compare_lasers, "plane", P, labels, out, plane=r, band_mm=band)
            sd.plots["hist"] = {"values": r.distances, "xlabel": "distance to the fitted plane (mm)",
                                "band": band, "bins": bins, "kind": "plane"}
            height_ref = (r.normal, r.d)
            figures = partial(_whole_cloud, uc.plane_figures(r, band))
            if tscan and "plane_base" in tscan:
                nt, dt = _plane4(tscan["plane_base"], r.normal)
                dev = P @ nt + dt
                out["truth"] = {"distance_to_true_plane": mt.deviation_stats(dev, band),
                                "normal_angle_deg": float(np.degrees(
                                    mt.angle_between(nt, r.normal)))}
        elif sd.artefact == "sphere":
            nominal = float(sd.nominal.get("diameter", np.nan))
            s = mt.measure_sphere(P, nominal, ransac_threshold_mm=float(met["sphere_ransac_mm"]),
                                  trim_sigma=float(met["sphere_trim_sigma"]), seed=seed)
            out["measurement"] = s.figures()
            out["a_vs_b"] = _ab(mt.compare_lasers, "sphere", P, labels, out, sphere=s)
            figures = partial(uc.sphere_figures, s)
            views = _viewpoints(sd)
            if views is not None:
                out["incidence"] = mt.sphere_by_incidence(P, s, views)
            sd.plots["hist"] = {"values": s.residuals, "xlabel": "radial residual (mm)",
                                "bins": bins, "kind": "sphere"}
            if tscan:
                t: dict[str, Any] = {}
                if "center_base" in tscan:
                    dc = s.centre - np.asarray(tscan["center_base"], dtype=np.float64)
                    t["centre_error_mm"] = dc.tolist()
                    t["centre_distance_mm"] = float(np.linalg.norm(dc))
                if "diameter" in tscan:
                    t["true_diameter_mm"] = float(tscan["diameter"])
                    t["diameter_error_mm"] = 2 * s.radius - float(tscan["diameter"])
                out["truth"] = t
        elif sd.artefact == "freeform":
            out["measurement"] = {"n": len(P)}
            if sd.mesh:
                try:
                    out["nominal_comparison"], sd.plots["nominal"] = _nominal_comparison(
                        P, root / sd.mesh, tol, met, sd.T_base_nominal, sd.cloud.get("frame"))
                except (CrosslineError, ValueError) as exc:
                    out["nominal_error"] = str(exc)
                    log.warning("scan %s: no comparison with its nominal: %s", sd.name, exc)
                nc = out.get("nominal_comparison")
                if nc and tscan and "T_base_nominal" in tscan:
                    out.setdefault("truth", {})["nominal_alignment"] = _alignment_error(
                        np.asarray(nc["T_nominal_cloud"]), np.asarray(tscan["T_base_nominal"]), P)
            if tscan and "mesh" in tscan:
                dev = _mesh_deviation(P, truth_file(root, sd.name, tscan, "mesh"), files, towards=up)
                if dev is not None:
                    # the part stands on the table, which the stripes cross too: points nearer
                    # the table plane than the part, or farther from the part than
                    # freeform_max_distance_mm, are not the part's and are counted apart
                    on = np.abs(dev) <= float(met["freeform_max_distance_mm"])
                    n_table = 0
                    if isinstance(truth.get("table_z_base"), int | float):
                        table = np.abs(P[:, 2] - float(truth["table_z_base"])) < np.abs(dev)
                        n_table = int(table.sum())
                        on &= ~table
                    stats = mt.deviation_stats(dev[on], band)
                    stats.update(n_total=len(P), n_table=n_table,
                                 n_off_part=int(len(P) - on.sum() - n_table),
                                 max_distance_mm=float(met["freeform_max_distance_mm"]))
                    out.setdefault("truth", {})["deviation_to_true_mesh"] = stats
                    sd.plots["deviation"] = dev[on]
                    sd.plots["deviation_mask"] = on
                    sd.plots["hist"] = {"values": dev[on], "xlabel": "signed distance to the true "
                                        "surface (mm)", "band": band, "bins": bins,
                                        "kind": "freeform"}
    except ValueError as exc:
        out["error"] = str(exc)
        log.warning("scan %s: %s", sd.name, exc)
    if figures is not None and model is not None and int(met["uncertainty_draws"]) > 1:
        if sd.cloud.get("frame") is None:
            out["uncertainty_error"] = "the cloud has no frame of each point"
        else:
            try:
                out["uncertainty"] = _uncertainty(sd, figures, model, met, root)
            except (CrosslineError, ValueError, np.linalg.LinAlgError) as exc:
                out["uncertainty_error"] = str(exc)
                log.warning("scan %s: no uncertainty: %s", sd.name, exc)
    if tscan and tscan.get("centrelines") and sd.points_path is not None:
        out["truth_labels"] = _label_truth(sd.points_path, truth_file(root, sd.name, tscan, "centrelines"),
                                           files)
        if out["truth_labels"] and truth:
            smooth = ((sd.points_info or {}).get("params") or {}).get("smooth_px")
            bound = _speckle_limit(out["truth_labels"].get("centre_error") or {}, truth,
                                   sd.points_path, smooth)
            if bound:
                out["truth_labels"]["speckle_limit"] = bound

    # top view, coloured by height (above the artefact's reference plane, else along `up`)
    if height_ref is not None:
        n, d = height_ref
        heights = P @ n + d
        axis = n
    else:
        axis = up if up is not None else np.array([0.0, 0.0, 1.0])
        heights = P @ axis
        heights = heights - np.percentile(heights, 0.5)
    B = _basis(axis)
    sd.plots["top"] = {"xy": P @ B.T, "h": heights}
    return out


def _label_truth(points: Path, centrelines: Path, files: list) -> dict[str, Any] | None:
    """Wrong A/B labels of the AB-frame points against the simulator's true centre lines."""
    import pandas as pd

    from crossline.report import metrics as mt

    if not centrelines.is_file():
        return None
    files.append(("capture", f"truth/{centrelines.name}", centrelines))
    try:
        p = pd.read_parquet(points, columns=["frame", "laser", "lasers", "u", "v"])
        t = pd.read_parquet(centrelines, columns=["frame", "laser", "u", "v", "visible"])
    except Exception as exc:  # pyarrow raises several types for broken files
        log.warning("label validation skipped: %s", exc)
        return None
    p = p[p["lasers"] == "AB"]
    t = t[t["visible"]]
    return mt.label_errors(p["frame"].to_numpy(), p["laser"].to_numpy(), p["u"].to_numpy(),
                           p["v"].to_numpy(), t["frame"].to_numpy(), t["laser"].to_numpy(),
                           t["u"].to_numpy(), t["v"].to_numpy())


def _speckle_limit(centre: dict, truth: dict, points: Path,
                   smooth_px: int | None = None) -> dict[str, Any] | None:
    """Per laser: the speckle bound on one profile's centre (px, :mod:`crossline.report.speckle`,
    from the rig's optics in truth.json), the same after the centre lines' smoothing
    (``smooth_px`` columns, as if the columns' speckle were independent: the lower end), the
    centres' achieved robust sigma against the true lines, and its ratio to each."""
    import pandas as pd

    from crossline.report.speckle import centre_bound_px, smoothing_gain

    sensor, cam = truth.get("sensor") or {}, truth.get("camera") or {}
    pitch, fno = sensor.get("pixel_pitch_um"), sensor.get("f_number")
    if not (pitch and fno and cam.get("K") and centre):
        return None
    try:
        z = pd.read_parquet(points, columns=["laser", "z_cam"])
    except Exception:  # an older points file without camera coordinates
        return None
    fx = float(cam["K"][0][0])
    out: dict[str, Any] = {}
    for name, ce in centre.items():
        las = (truth.get("lasers") or {}).get(name) or {}
        zl = z["z_cam"][z["laser"] == name].to_numpy(np.float64)
        if not (las.get("speckle_contrast") is not None and las.get("wavelength_nm") and zl.size):
            continue
        # magnification at the points' median depth: f / z, f = fx * pitch
        m = fx * float(pitch) * 1e-3 / float(np.median(zl))
        b = centre_bound_px(float(las["speckle_contrast"]), float(las["wavelength_nm"]),
                            float(fno), float(pitch), m)
        gain = smoothing_gain(int(smooth_px)) if smooth_px else 1.0
        out[name] = {"bound_px": b, "achieved_sigma_px": ce["sigma_px"],
                     "ratio": ce["sigma_px"] / b if b > 0 else None,
                     "smooth_px": smooth_px, "bound_smoothed_px": b * gain,
                     "ratio_smoothed": ce["sigma_px"] / (b * gain) if b > 0 else None,
                     "contrast": float(las["speckle_contrast"]),
                     "wavelength_nm": float(las["wavelength_nm"]), "f_number": float(fno),
                     "pixel_um": float(pitch), "magnification": m}
    return out or None


def _viewpoints(sd: ScanData) -> np.ndarray | None:
    """The camera centre (base frame) that saw each cloud point, from the points file."""
    import pandas as pd

    from crossline.fuse import camera_centres

    if sd.points_path is None or sd.cloud is None or "frame" not in sd.cloud:
        return None
    try:
        df = pd.read_parquet(sd.points_path, columns=["frame", "x_cam", "y_cam", "z_cam",
                                                      "x", "y", "z"])
    except Exception:  # an older points file without camera coordinates: no incidence
        return None
    frames, centres = camera_centres(df["frame"].to_numpy(np.int64),
                                     df[["x_cam", "y_cam", "z_cam"]].to_numpy(np.float64),
                                     df[["x", "y", "z"]].to_numpy(np.float64))
    fr = np.asarray(sd.cloud["frame"], dtype=np.int64)
    pos = np.clip(np.searchsorted(frames, fr), 0, len(frames) - 1)
    if not np.isfinite(centres).all() or not (frames[pos] == fr).all():
        return None
    return centres[pos]


ONE_LINE_NOTE = "omitted: the rig has one laser (A), so there is no laser B to compare with"


def _ab(fn: Any, art: str, P: np.ndarray, labels: np.ndarray, out: dict, **kw: Any) -> dict | None:
    """Laser A against laser B, or None with the reason in ``out["a_vs_b_error"]`` (or, on a
    one-line rig, ``out["a_vs_b_note"]``)."""
    if out.get("lasers") == ["A"]:
        out["a_vs_b_note"] = ONE_LINE_NOTE
        return None
    try:
        ab = fn(art, P, labels, **kw)
    except ValueError as exc:
        out["a_vs_b_error"] = str(exc)
        return None
    if ab is None:
        out["a_vs_b_error"] = "too few points of one laser on the artefact"
        return None
    return ab.figures()


def _plane4(v: list, like: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    n = np.asarray(v[:3], dtype=np.float64)
    s = np.linalg.norm(n)
    n, d = n / s, float(v[3]) / s
    if like is not None and float(n @ like) < 0:
        n, d = -n, -d
    return n, d


def _gauge_truth(g: Any, P: np.ndarray, tscan: dict, nominal: float) -> dict[str, Any]:
    from crossline.report import metrics as mt

    t: dict[str, Any] = {"true_height_mm": float(tscan.get("height", nominal))}
    f = g.figures()
    t["mean_error_mm"] = f["mean_mm"] - t["true_height_mm"]
    t["central_length_error_mm"] = f["central_length_mm"] - t["true_height_mm"]
    if "plate_plane_base" in tscan:
        nt, dt = _plane4(tscan["plate_plane_base"], g.plate_normal)
        h = P[g.top_mask] @ nt + dt
        t["heights_over_true_plate"] = {"mean_mm": float(h.mean()),
                                        "std_mm": float(h.std(ddof=1)) if h.size > 1 else 0.0,
                                        "error_mm": float(h.mean()) - t["true_height_mm"]}
        dev = P[g.plate_mask] @ nt + dt
        t["plate_points_to_true_plate"] = mt.deviation_stats(dev)
        t["plate_normal_angle_deg"] = float(np.degrees(mt.angle_between(nt, g.plate_normal)))
    if "top_plane_base" in tscan:
        nt, dt = _plane4(tscan["top_plane_base"], g.plate_normal)
        t["top_points_to_true_top"] = mt.deviation_stats(P[g.top_mask] @ nt + dt)
    return t


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (float64) and triangles of a PLY mesh.

    Binary little-endian PLYs with ``double``/``float`` x, y, z and ``list uchar int``
    triangles (as the simulator writes them) are read exactly here; anything else through
    Open3D.
    """
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    head = data[:end].decode("ascii", "replace").splitlines() if end > 0 else []
    if "format binary_little_endian 1.0" in head:
        nv = nf = 0
        vprops: list[tuple[str, str]] = []
        flist = None
        element = None
        types = {"double": "<f8", "float": "<f4", "float64": "<f8", "float32": "<f4",
                 "uchar": "u1", "uint8": "u1", "int": "<i4", "int32": "<i4", "uint": "<u4",
                 "uint32": "<u4"}
        ok = True
        for ln in head:
            w = ln.split()
            if w[:1] == ["element"]:
                element = w[1]
                if element == "vertex":
                    nv = int(w[2])
                elif element == "face":
                    nf = int(w[2])
                else:
                    ok = False
            elif w[:1] == ["property"] and element == "vertex":
                ok &= w[1] in types
                vprops.append((w[-1], types.get(w[1], "u1")))
            elif w[:2] == ["property", "list"] and element == "face":
                flist = (types.get(w[2]), types.get(w[3]))
        if ok and flist is not None and None not in flist and {"x", "y", "z"} <= {n for n, _ in vprops}:
            off = end + len(b"end_header\n")
            vt = np.dtype(vprops)
            V = np.frombuffer(data, vt, nv, off)
            ft = np.dtype([("n", flist[0]), ("i", flist[1], (3,))])
            F = np.frombuffer(data, ft, nf, off + nv * vt.itemsize)
            if (F["n"] == 3).all():
                return (np.column_stack([V[k].astype(np.float64) for k in "xyz"]),
                        F["i"].astype(np.int64))
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).copy()


def _mesh_deviation(P: np.ndarray, path: Path, files: list,
                    towards: np.ndarray | None = None) -> np.ndarray | None:
    """Signed distance of the points to the true mesh, positive outside (towards the scanner)."""
    from crossline.report.metrics import mesh_signed_distance

    if not path.is_file():
        log.warning("%s: the true mesh is missing; no freeform validation", path)
        return None
    files.append(("capture", str(path.name if path.parent.name != "truth" else
                                 f"truth/{path.name}"), path))
    V, F = read_mesh(path)
    if len(F) == 0:
        log.warning("%s: the true mesh has no triangles", path)
        return None
    dev = mesh_signed_distance(P, V, F)
    if towards is not None:
        # the scanner sees the outside: if the triangles' area-weighted normal points away
        # from it, the mesh is wound inwards and the sign is flipped
        a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        if float(np.cross(b - a, c - a).sum(0) @ towards) < 0:
            dev = -dev
    return dev


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
    import pyarrow.parquet as pq

    try:
        z = pq.read_table(points, columns=["z_cam"]).column("z_cam").to_numpy()
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


# ----------------------------------------------------------------------------- build


def build_report(
    capture: Path, interim_dir: Path, processed_dir: Path, config: Any = None
) -> ReportData:
    """Measure everything a report shows; return the metrics (JSON-ready) and plot arrays."""
    from crossline.io.capture import read_rig

    capture, interim_dir, processed_dir = Path(capture), Path(interim_dir), Path(processed_dir)
    full, tol, met = load_config(config)
    rig = read_rig(capture / "rig.yaml")
    files: list[tuple[str, str, Path]] = [("capture", "rig.yaml", capture / "rig.yaml")]
    for rel in ("calibration/handeye/poses.csv",):
        if (capture / rel).is_file():
            files.append(("capture", rel, capture / rel))
    truth = None
    if (capture / "truth.json").is_file():
        files.append(("capture", "truth.json", capture / "truth.json"))
        truth = _read_json(capture / "truth.json")
    inputs: dict[str, dict | None] = {}
    for k in ("camera", "lasers", "handeye"):
        p = interim_dir / "calibration" / f"{k}.json"
        if p.is_file():
            files.append(("interim", f"calibration/{k}.json", p))
        inputs[k] = _read_json(p)
        why = calibration_problem(k, inputs[k]) if inputs[k] is not None else None
        if why is not None:
            log.warning("%s: not a %s calibration (%s); its section is left out", p, k, why)
            inputs[k] = None
    if (interim_dir / "check.json").is_file():
        files.append(("interim", "check.json", interim_dir / "check.json"))

    date = rig.extra.get("capture_date")
    metrics: dict[str, Any] = {
        "format": FORMAT,
        "capture": {"name": capture.name, "date": str(date) if date is not None else None,
                    "simulated": truth is not None, "scans": sorted(rig.scans)},
        "software": {"crossline_version": __version__, "git_commit": _git_commit()},
    }
    lasers = tuple(getattr(rig, "lasers", ("A", "B")))
    if lasers != ("A", "B"):
        metrics["capture"]["lasers"] = list(lasers)
    plots: dict[str, Any] = {"scans": {}}
    cal = _calibration(inputs)
    metrics["calibration"] = cal
    plots["camera_raw"] = inputs.get("camera")
    plots["lasers_raw"] = inputs.get("lasers")
    plots["handeye_raw"] = inputs.get("handeye")
    plots["rig"] = rig

    rows: list[dict[str, Any]] = []
    scans: dict[str, Any] = {}
    form_key = FORM_KEYS[met["sphere_form_statistic"]]
    model = None
    if all(inputs.get(k) for k in ("camera", "lasers", "handeye")):
        from crossline.report.uncertainty import calibration_model

        try:
            model = calibration_model(inputs["camera"], inputs["lasers"], inputs["handeye"])
        except (KeyError, ValueError, TypeError) as exc:
            log.warning("no measurement uncertainty: the calibration cannot be read (%s)", exc)
    depths: list[np.ndarray] = []
    for name in sorted(rig.scans):
        sd = _load_scan(name, rig.scans[name], capture, interim_dir, processed_dir, files)
        if truth and sd.points_path is not None:
            depths.append(_point_depths(sd.points_path))
        s = _measure_scan(sd, tol, met, truth, capture, files, lasers, model)
        scans[name] = s
        first_row = len(rows)
        plots["scans"][name] = sd.plots
        m = s.get("measurement") or {}
        ab = (s.get("a_vs_b") or {}).get("A_minus_B", {})
        err = s.get("error", "")
        gain = (s.get("counts") or {}).get("gain_over_single_line")
        if (s.get("counts") or {}).get("by_state", {}).get("AB"):
            # throughput, not accuracy: shown beside the paper's 4/3, never a FAIL
            _check(rows, "gain_over_single_line", "points per frame over a single line (paper: 1.33)",
                   name, gain, "×", None)
        lt = s.get("truth_labels")
        if lt and lt.get("checked"):
            _check(rows, "wrong_labels", "AB frames: wrong A/B labels (vs truth)", name,
                   lt["wrong"], "", None)
        if sd.artefact == "gauge_block":
            _check(rows, "gauge_mean_error_mm", "gauge height: mean − nominal", name,
                   m.get("error_mm"), "mm", tol["gauge_mean_error_mm"], use_abs=True, note=err)
            _check(rows, "gauge_std_mm", "gauge height: standard deviation", name,
                   m.get("std_mm"), "mm", tol["gauge_std_mm"], note=err)
            if "plane_reference_std_mm" in m:
                _check(rows, "gauge_plane_reference_error_mm",
                       "gauge height, paper's method: mean − nominal", name,
                       m.get("plane_reference_error_mm"), "mm", None)
                _check(rows, "gauge_plane_reference_std_mm",
                       "gauge height, paper's method: std", name,
                       m.get("plane_reference_std_mm"), "mm", None)
            if "a_vs_b_note" not in s:  # a one-line rig has no laser B to compare with
                _check(rows, "ab_height_difference_mm", "gauge height: laser A − laser B", name,
                       ab.get("height_mm"), "mm", tol["ab_height_difference_mm"], use_abs=True,
                       note=err or ("" if ab else s.get("a_vs_b_error", "")))
        elif sd.artefact == "plane":
            _check(rows, "plane_within_share", f"plane: share within ±{tol['plane_band_mm']:g} mm",
                   name, m.get("share_within_band"), "%", tol["plane_within_share"],
                   comparison=">=", note=err)
            _check(rows, "plane_flatness_mm", "plane: flatness F (all points)", name,
                   m.get("flatness_mm"), "mm", None, note=err)
            _check(rows, "plane_flatness_95_mm", "plane: flatness (2.5–97.5 %)", name,
                   m.get("flatness_95_mm"), "mm", None, note=err)
        elif sd.artefact == "sphere":
            _check(rows, "sphere_size_error_mm", "sphere: size error (PSize)", name,
                   m.get("size_error_mm"), "mm", tol["sphere_size_error_mm"], use_abs=True,
                   note=err)
            label = {"all": "all points, ISO 10360-8", "vdi": "VDI/VDE 2634-2",
                     "d95": "D95 %", "p95": "2.5–97.5 %"}[met["sphere_form_statistic"]]
            _check(rows, "sphere_form_error_mm", f"sphere: form error (PForm, {label})", name,
                   m.get(form_key), "mm", tol["sphere_form_error_mm"], note=err)
            if met["sphere_form_statistic"] != "vdi":
                # both standards' readings: the acceptance test names which one it applies
                _check(rows, "sphere_form_error_vdi_mm",
                       "sphere: form error (VDI/VDE 2634-2)", name,
                       m.get(FORM_KEYS["vdi"]), "mm", None, note=err)
            if met["sphere_form_statistic"] != "d95":
                _check(rows, "sphere_form_error_d95_mm",
                       "sphere: form error, D95 % (ISO 10360-13)", name,
                       m.get(FORM_KEYS["d95"]), "mm", None, note=err)
            if "a_vs_b_note" not in s:
                _check(rows, "ab_diameter_difference_mm", "sphere: diameter A − B", name,
                       ab.get("diameter_mm"), "mm", None, note=err)
            inc = s.get("incidence") or {}
            if "size_error_steep_mm" in inc:
                _check(rows, "sphere_size_error_steep_mm",
                       f"sphere: size error, incidence ≤ {inc['max_incidence_deg']:.0f}°", name,
                       inc["size_error_steep_mm"], "mm", None, use_abs=True)
        elif sd.artefact == "freeform":
            nc = s.get("nominal_comparison")
            if nc or s.get("nominal_error"):
                _check(rows, "nominal_within_share",
                       f"freeform: share within ±{tol['nominal_band_mm']:g} mm of its nominal",
                       name, (nc or {}).get("share_within_tolerance"), "%",
                       tol["nominal_within_share"], comparison=">=",
                       note=s.get("nominal_error", ""))
            dev = (s.get("truth") or {}).get("deviation_to_true_mesh")
            if dev:
                _check(rows, "freeform_rms_mm", "freeform: RMS deviation from true surface",
                       name, dev.get("rms_mm"), "mm", None)
        for row in rows[first_row:]:
            _with_uncertainty(row, s.get("uncertainty"), form_key)
    metrics["summary"] = rows
    statuses = [r["status"] for r in rows]
    if "FAIL" in statuses:
        overall = "FAIL"
    elif "N/A" in statuses or not any(s == "PASS" for s in statuses):
        overall = "INCOMPLETE"
    else:
        overall = "PASS"
    metrics["result"] = overall
    metrics["scans"] = scans
    metrics["validation"] = _validation(inputs, truth, rig, met,
                                        np.concatenate(depths) if depths else None) if truth else None
    files_out = []
    for root_label, rel, path in sorted(set(files), key=lambda f: (f[0], f[1])):
        files_out.append({"root": root_label, "file": rel, "sha256": _sha256(path),
                          "bytes": path.stat().st_size})
    metrics["provenance"] = {
        "crossline_version": __version__,
        "git_commit": metrics["software"]["git_commit"],
        "capture_date": metrics["capture"]["date"],
        "tolerances": tol,
        "metrology": met,
        "parameters": full,
        "inputs": files_out,
    }
    return ReportData(to_jsonable(metrics), plots)


def deviation_limit_mm(dev: np.ndarray, tolerance_mm: float) -> float:
    """The colour scale's half range of a deviation map: twice the tolerance band, or the 99th
    percentile of |deviation| where that is wider (the page and the coloured cloud share it)."""
    return max(2.0 * float(tolerance_mm), float(np.nanpercentile(np.abs(dev), 99)))


def write_deviation_clouds(data: ReportData, folder: Path) -> list[Path]:
    """``<scan>.ply`` in ``folder`` for every freeform scan compared with its nominal: the
    aligned points (the drawing's frame, mm) coloured by signed deviation on the page's scale,
    the deviation itself as a ``deviation`` scalar field (CloudCompare reads it). The folder is
    made even when no scan was compared, so that the workflow finds its output."""
    from crossline.report.nominal import deviation_colours, write_coloured_ply

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, sp in sorted(data.plots.get("scans", {}).items()):
        nom = sp.get("nominal")
        nc = data.metrics["scans"].get(name, {}).get("nominal_comparison")
        if not nom or not nc or len(nom["dev"]) == 0:
            continue
        limit = deviation_limit_mm(nom["dev"], nc["tolerance_mm"])
        path = folder / f"{name}.ply"
        write_coloured_ply(path, nom["points"], deviation_colours(nom["dev"], limit), deviation=nom["dev"])
        written.append(path)
    return written


def run_report(
    capture: Path, interim_dir: Path, processed_dir: Path, pdf: Path, metrics: Path, *,
    config: Any = None, deviation_dir: Path | None = None,
) -> dict[str, Any]:
    """The ``report`` stage: measure, then write ``metrics.json`` and ``accuracy.pdf`` (and,
    with ``deviation_dir``, the freeform scans' clouds coloured by deviation from nominal)."""
    from crossline.report.pages import render_pdf

    capture = Path(capture)
    if not (capture / "rig.yaml").is_file():
        raise CrosslineError(f"{capture}: not a capture folder (no rig.yaml)")
    data = build_report(capture, interim_dir, processed_dir, config)
    if deviation_dir is not None:
        write_deviation_clouds(data, deviation_dir)
    with atomic_path(pdf) as tmp:
        render_pdf(data, tmp)
    write_json(metrics, data.metrics)
    log.info("report %s: %s", capture.name, data.metrics["result"])
    return data.metrics

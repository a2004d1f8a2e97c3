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

The code lives in modules beside this one (issue 21.3): ``scan_data`` (a scan's points,
cloud and frames as read), ``measure`` (the figures of one scan), ``scan_truth`` (a scan
against the simulator's truth), ``calibration`` (the calibration files, their figures and
their errors against truth) and ``summary`` (the summary rows, their tolerances and
uncertainty decisions). This one keeps the configuration, ``build_report`` and
``run_report``, and re-exports the names its importers use.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from crossline import __version__
from crossline.errors import CrosslineError
from crossline.io.atomic import atomic_path, to_jsonable, write_json
from crossline.io.settings import read_settings
from crossline.report.calibration import _calibration, _point_depths, _validation, calibration_problem
from crossline.report.measure import _measure_scan
from crossline.report.measure import _nominal_comparison as _nominal_comparison
from crossline.report.scan_data import _load_scan, _read_json, points_per_frame
from crossline.report.scan_truth import read_mesh
from crossline.report.summary import _check, _with_uncertainty

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
    "ball_bar_sd_mm": 0.02,  # |ball bar centre distance − nominal| (ISO 10360-8 MPE_SD)
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


def _sha256(path: Path) -> str:
    from crossline.io.provenance import file_sha256

    return file_sha256(path)


def _git_commit() -> str | None:
    try:
        from crossline.io.provenance import git_commit

        return git_commit()
    except Exception:  # provenance must never stop a report
        return None


def _inside_capture(capture: Path, files: list[str]) -> None:
    """Refuse the capture when one of ``files`` (the capture's files the report opens, relative
    to it) leads outside it once symbolic links are followed: CaptureError naming each."""
    from crossline.io.contract import CaptureError, Problem, _Inside

    inside = _Inside(capture)
    problems = [Problem(rel, why) for rel in files if (why := inside.why_not(capture / rel)) is not None]
    if problems:
        raise CaptureError(capture, problems)


@dataclass
class ReportData:
    """Everything measured for a report: the metrics (JSON) and the arrays its plots need."""

    metrics: dict[str, Any]
    plots: dict[str, Any]


# ----------------------------------------------------------------------------- build


def build_report(
    capture: Path, interim_dir: Path, processed_dir: Path, config: Any = None
) -> ReportData:
    """Measure everything a report shows; return the metrics (JSON-ready) and plot arrays."""
    from crossline.io.capture import read_frames_table, read_rig
    from crossline.io.contract import LASERS

    capture, interim_dir, processed_dir = Path(capture), Path(interim_dir), Path(processed_dir)
    full, tol, met = load_config(config)
    rig = read_rig(capture / "rig.yaml")
    _inside_capture(capture, ["truth.json", "calibration/handeye/poses.csv",
                              *(f"scans/{name}/frames.csv" for name in sorted(rig.scans))])
    for name in sorted(rig.scans):
        # the capture's own checks of each frames table the report reads (a faulty row named),
        # as the stages before it made them: the points per frame and laser state come from it
        if (capture / "scans" / name / "frames.csv").is_file():
            read_frames_table(capture / "scans" / name / "frames.csv", tuple(getattr(rig, "lasers", LASERS)))
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
    lack = [x for x in getattr(rig, "lasers", LASERS) if x not in (inputs.get("lasers") or {})]
    if inputs.get("lasers") and lack:  # the uncertainty draws the plane of every point's laser
        log.warning("no measurement uncertainty: %s has no plane of laser %s, which rig.yaml names",
                    interim_dir / "calibration" / "lasers.json", ", ".join(lack))
    elif all(inputs.get(k) for k in ("camera", "lasers", "handeye")):
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
        elif sd.artefact == "ball_bar":
            _check(rows, "ball_bar_sd_mm", "ball bar: sphere-spacing error SD (distance − nominal)",
                   name, m.get("length_error_mm"), "mm", tol["ball_bar_sd_mm"], use_abs=True,
                   note=err)
            _check(rows, "ball_bar_size_error_mm", "ball bar: size error, larger of the two balls",
                   name, m.get("size_error_max_mm"), "mm", None, use_abs=True, note=err)
            _check(rows, "ball_bar_form_error_mm", "ball bar: form error (all points), larger ball",
                   name, m.get("form_error_max_mm"), "mm", None, note=err)
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

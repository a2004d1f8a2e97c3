"""The closing pages of the accuracy report: validation against the simulator's truth, the
provenance (version, commit, inputs' checksums, parameters) and the measurement uncertainty
budget with its decision rule. Split from :mod:`crossline.report.pages` (issue 21.3).
"""

from __future__ import annotations

from typing import Any

from matplotlib.figure import Figure

from crossline.report.pages_common import (
    A4,
    COLOURS,
    LEFT,
    MONO,
    RIGHT,
    Page,
    _json_lines,
    _map,
    fmt,
    fmt_row_value,
    fmt_tolerance,
)

__all__ = ["BUDGET", "UNCERTAINTY_FIGURES", "page_provenance", "page_uncertainty", "page_validation"]


def _coverage_rows(truth: dict, figure: str) -> list[list[str]]:
    """The row saying whether the figure's expanded uncertainty U covers its error (E_n)."""
    c = (truth.get("uncertainty_coverage") or {}).get(figure)
    if not c:
        return []
    verdict = "U covers it" if c["covered"] else "NOT covered: U misses a contributor"
    return [["", "error / U (k = 2), E_n", f"{c['E_n']:+.2f} (U {fmt(c['U_mm'], 'mm')}; {verdict})"]]


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
            rows += _coverage_rows(t, "mean_mm")
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
                rows += _coverage_rows(t, "diameter_mm")
        elif art == "ball_bar":
            if "length_error_mm" in t:
                rows.append([name, "centre distance − true distance (SD against truth)",
                             fmt(t["length_error_mm"], "mm", signed=True)])
                rows += _coverage_rows(t, "length_mm")
            if "centre_distances_mm" in t:
                rows.append(["", "centres − true centres (distance), ball 1 / 2",
                             " / ".join(fmt(x, "mm") for x in t["centre_distances_mm"])])
            if "diameter_errors_mm" in t:
                rows.append(["", "diameters − true diameter, ball 1 / 2",
                             " / ".join(fmt(x, "mm", signed=True) for x in t["diameter_errors_mm"])])
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
            rows.append([name, laser, f"{fmt(sl['bound_px'], '', 3)} / "
                         f"{fmt(sl.get('bound_smoothed_px'), '', 3)}",
                         fmt(sl.get("sensor_bound_px"), "", 3),
                         f"{fmt(sl.get('combined_bound_px'), '', 3)} / "
                         f"{fmt(sl.get('combined_bound_smoothed_px'), '', 3)}",
                         fmt(sl["achieved_sigma_px"], "", 3),
                         f"{sl['ratio']:.2f}× / {sl['ratio_smoothed']:.2f}×"
                         if sl.get("ratio_smoothed") is not None else "–",
                         f"{sl['ratio_combined']:.2f}× / {sl['ratio_combined_smoothed']:.2f}×"
                         if sl.get("ratio_combined_smoothed") is not None else "–",
                         f"{fmt(sl.get('spacing_mm'), '', 3)} / {fmt(sl.get('half_amplitude_mm'), '', 2)}"
                         if sl.get("spacing_mm") is not None else "–"])
    figs = [p.fig]
    if rows:
        # a page of its own: below the calibration, artefact and label tables it ran off the page
        p = Page(m, "Validation: stripe centres against the speckle limit")
        figs.append(p.fig)
        p.text("Figure: the speckle-limited uncertainty of one centre (Dorsch, Häusler & "
               "Herrmann 1994: contrast × wavelength × f-number × (1 + magnification) / π, per "
               "pixel pitch; the centroid's figure for a stripe about as wide as the aperture's "
               "spot: a fitted profile can beat it on narrow stripes, wide stripes exceed it), "
               "for one profile / after the centre lines' smoothing along the stripe with "
               "independent columns (speckle grains span a column or two, so the smoothed "
               "figure lies between the two); achieved: the robust sigma of the checked "
               "centres' distances from their true line, across it, away from the crossing "
               "band. Sensor: the Cramér-Rao bound of one profile as the extractor takes it "
               "(column or row) from shot, background and read noise, across the line (the "
               "true stripes' peak, width and background in the simulator's truth; the robust "
               "sigma over the true points). Bound: speckle of the rig's contrast and grain and "
               "the sensor's noise together, for each profile's width (the best weighted "
               "least-squares fit of the profile; after the smoothing, neighbouring profiles "
               "share grains). Ratios: achieved over the speckle figure and over the bound "
               "(profile / smoothed). Resolution: the points' spacing along the stripe and the "
               "ripple the smoothing passes at half its amplitude (mm).",
               size=8)
        p.table(["Scan", "Laser", "figure px", "sensor px", "bound px", "achieved px",
                 "÷ figure", "÷ bound", "resolution mm"], rows,
                [LEFT, LEFT + 0.065, LEFT + 0.11, LEFT + 0.225, LEFT + 0.3, LEFT + 0.415,
                 LEFT + 0.5, LEFT + 0.62, LEFT + 0.74],
                aligns=["left"] * 9, size=7.0)
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


UNCERTAINTY_FIGURES = {"mean_mm": "gauge height (mean)", "flatness_mm": "flatness (all points)",
                       "flatness_95_mm": "flatness (2.5–97.5 %)", "rms_mm": "RMS to the plane",
                       "share_within_band": "share within the band", "diameter_mm": "diameter",
                       "form_error_mm": "form error (all)", "form_error_d95_mm": "form error (D95)",
                       "form_error_vdi_mm": "form (VDI/VDE 2634-2)",
                       "form_error_p95_mm": "form error (2.5–97.5 %)",
                       "length_mm": "ball bar distance (SD)",
                       "deviation_mean_mm": "mean deviation", "deviation_rms_mm": "RMS deviation",
                       "share_within_tolerance": "share within band"}
BUDGET = {"camera": "camera", "laser_planes": "planes", "handeye": "hand-eye", "arm": "arm",
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
           "distortion, both laser planes, hand-eye X), moves every frame by a draw of the arm's "
           "pose error left in it (arm: the pose refinement's posterior, else its prior: the arm's "
           "noise as the hand-eye views measured it, or its stated precision) and draws the "
           "scan's frames again with replacement (frames: stripe "
           "noise, speckle and the arm's pose noise as this scan realised them); the figure is "
           "measured again with the report's definition and "
           "segmentation. U = 2 u of all together; the 95 % interval of the draws, less the value; "
           "camera … frames: the standard uncertainty u of each contributor alone. Lengths in µm, "
           "shares in %; form (VDI/VDE 2634-2): the range after 0.3 % of the points are discarded.",
           size=8)
    p.gap(0.08)
    cells, colours = [], []
    for name, unc in scans.items():
        for key, f in unc["figures"].items():
            share = key.startswith("share_within")  # a fraction: in %, the lengths in µm
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
        p.table(["Scan", "Figure", "Value", "U", "95 % interval",
                 *BUDGET.values(), "Dominant"], cells,
                # left edges; a right-aligned column ends where the next begins
                [LEFT, LEFT + 0.06, LEFT + 0.21, LEFT + 0.29, LEFT + 0.34, LEFT + 0.46, LEFT + 0.52,
                 LEFT + 0.58, LEFT + 0.655, LEFT + 0.71, LEFT + 0.77], size=6.8,
                aligns=["left", "left", "right", "right", "right", "right", "right", "right",
                        "right", "right", "left"])
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
                [LEFT, LEFT + 0.28, LEFT + 0.34, LEFT + 0.49, LEFT + 0.61], size=7.5,
                aligns=["left", "left", "right", "right", "left"])
    p.gap(0.1)
    p.text("What U covers, and what it does not", size=10, weight="bold")
    p.text("Covered: the calibration's own noise (as its fits estimate it), the arm's pose "
           "error that pose refinement leaves (drawn from its posterior: the drift the frames of "
           "a pass share) and the scan's repeatability; a camera draw moves the laser planes with "
           "it, as they were fitted through it. Not covered: hand-eye's share of the camera's "
           "error (drawn independently), the camera's model error where distortion terms were "
           "fixed, the arm's systematic error beyond what hand-eye absorbed, an arm less "
           "precise than the draws' prior (fuse.arm_precision_mm: auto, the hand-eye views' "
           "estimate of its noise, or a stated precision), "
           "biases of the stripe "
           "centres with the angle of incidence (see the sphere's size by incidence), the "
           "artefact's own calibration and temperature. How often the true value lies within "
           "±U on simulated captures: benchmarks/bench_uncertainty.py.", size=8)
    return p.fig

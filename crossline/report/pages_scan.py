"""The scan pages of the accuracy report: one page per scan (counts, the gain of the cross, the
top view, the artefact's histogram, laser A against laser B) and a freeform scan against its
nominal mesh. Split from :mod:`crossline.report.pages` (issue 21.3).
"""

from __future__ import annotations

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
    RIGHT,
    Page,
    _hist,
    _map,
    _textbox,
    _um,
    fmt,
)
from crossline.scan.centreline import half_amplitude_columns

__all__ = ["page_nominal", "page_scan"]


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


def _arm_prior_lines(prior: dict[str, Any] | None, lines: list[str]) -> str | None:
    """The refinement's arm prior as lines of the scan's counts; a warning where the hand-eye
    views measured the arm ``ARM_PRIOR_WARN`` times noisier than the stated figure."""
    from crossline.fuse.cloud import ARM_PRIOR_ADVICE, ARM_PRIOR_WARN

    if not isinstance(prior, dict) or prior.get("precision_mm") is None:
        return None
    lines.append(f"  arm prior {fmt(prior['precision_mm'], '', 3)} mm (2σ 3-D): {prior.get('source', '')}")
    ratio = prior.get("handeye_ratio")
    if ratio is None:
        return None
    lines.append(f"  the hand-eye views measured {fmt(ratio, '', 1)}× that")
    if ratio <= ARM_PRIOR_WARN:
        return None
    return (f"The hand-eye views put the arm's noise at {fmt(ratio, '', 1)}× the stated precision: "
            f"{ARM_PRIOR_ADVICE}.")


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
    sc = tri.get("sheet_curvature") or {}
    if sc.get("points_moved"):
        sig = ", ".join(f"{k} {v * 1e3:.0f}" for k, v in (sc.get("sheet_sigma_mm") or {}).items())
        lines += [f"sheet on curved surfaces: {fmt(sc['points_moved'])} centres moved, median "
                  f"{fmt(sc.get('median_shift_px'), '', 3)} px,",
                  f"  95 % within {fmt(sc.get('p95_shift_px'), '', 3)} px (sheet sigma {sig} µm)"]
    elif sc.get("skipped"):
        lines.append(f"sheet on curved surfaces: not corrected ({sc['skipped']})")
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
    warn = None
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
        warn = _arm_prior_lines(fz.get("arm_prior"), lines)
    if s.get("cloud_source"):
        lines.append(f"measured on {s['cloud_source']}")
    for ln in lines:
        p.text(ln, size=8.2)
    if warn:
        p.text(warn, size=8, color=COLOURS["FAIL"])
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
        _map(p, None, None, label, "Top view of the fused cloud", height_in=2.6,
             image=(top["image"], top["extent"]))
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
            if meas.get("reference_note"):
                p.text(f"Heights: {meas['reference_note']}.", size=7.5, color=COLOURS["N/A"])
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
        elif hist["kind"] == "ball_bar":
            ax.set_title("Radial residuals of both balls' least-squares spheres", loc="left")
            b1, b2 = meas["balls"]
            _textbox(ax, [f"distance   {fmt(meas['length_mm'], 'mm')}",
                          f"nominal    {fmt(meas['nominal_length_mm'], 'mm')}",
                          f"SD         {fmt(meas['length_error_mm'], 'mm', signed=True)}",
                          f"size error {fmt(b1['size_error_mm'], 'mm', signed=True)} / "
                          f"{fmt(b2['size_error_mm'], 'mm', signed=True)}",
                          f"form (all) {fmt(b1['form_error_mm'], 'mm')} / "
                          f"{fmt(b2['form_error_mm'], 'mm')}",
                          f"n          {fmt(b1['n'])} / {fmt(b2['n'])}"])
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

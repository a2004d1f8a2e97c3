"""The figures of one scan: counts, its artefact, laser A against B, truth, uncertainty.

``_measure_scan`` measures a scan's artefact (gauge block, plane, sphere, freeform) with
``crossline.report.metrics`` and gives its plot arrays; beside it its helpers: the cloud's up
vector and plane basis, a freeform against its nominal mesh (``_nominal_comparison``) and
that alignment against the true placement, each figure's Monte Carlo uncertainty, the
camera centre that saw each point, and laser A against laser B (``_ab``). Split from
``crossline.report.accuracy`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

import logging
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from crossline.errors import CrosslineError
from crossline.report.scan_data import ScanData, points_per_frame
from crossline.report.scan_truth import (
    _gauge_truth,
    _label_truth,
    _mesh_deviation,
    _plane4,
    _speckle_limit,
    uncertainty_coverage,
)
from crossline.report.top_view import top_view

__all__ = ["ONE_LINE_NOTE"]

# the report stage's logger, as before the split: its records keep their name
log = logging.getLogger("crossline.report.accuracy")


def _up_vector(cloud: dict[str, np.ndarray]) -> np.ndarray | None:
    n = cloud.get("normals")
    if n is not None and len(n):
        m = np.asarray(n).mean(0, dtype=np.float64)
    elif cloud.get("normal_mean") is not None and len(cloud["points"]):
        m = np.asarray(cloud["normal_mean"], dtype=np.float64)  # read_ply(normals=False)
    else:
        return None
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
    dev, grad = nm.signed_deviation(Q, V, F, directions=True)
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
    # "mc": what the uncertainty's figures need (uncertainty.freeform_figures), popped there
    return out, {"points": Q[shown], "dev": dev[shown], "regions": summ.get("regions") or [],
                 "band": band, "mc": {"T": T, "dev": dev, "grad": grad, "keep": shown}}


def _alignment_error(T_nominal_cloud: np.ndarray, T_base_nominal: np.ndarray,
                     P: np.ndarray) -> dict[str, float]:
    """The alignment against the true placement: rotation, translation, and how far the
    cloud's points land from where the true transform puts them (RMS, max)."""
    from crossline.report import metrics as mt

    true = np.linalg.inv(T_base_nominal)
    e = mt.transform_error(T_nominal_cloud, true, P)
    return {k: v for k, v in e.items() if isinstance(v, int | float)}


def _ball_bar_truth(b: Any, tscan: dict) -> dict[str, Any]:
    """The ball bar against its true centres: each measured ball matched to the nearer true
    one, the centres' errors and the centre distance's error against the TRUE distance."""
    t: dict[str, Any] = {}
    if "diameter" in tscan:
        t["true_diameter_mm"] = float(tscan["diameter"])
        t["diameter_errors_mm"] = [2 * s.radius - float(tscan["diameter"]) for s in b.balls]
    cs = np.asarray(tscan.get("centers_base") or [], dtype=np.float64)
    if cs.shape == (2, 3):
        m = np.array([s.centre for s in b.balls])
        swap = (np.linalg.norm(m - cs[::-1], axis=1).sum() < np.linalg.norm(m - cs, axis=1).sum())
        cs = cs[::-1] if swap else cs
        t["centre_errors_mm"] = (m - cs).tolist()
        t["centre_distances_mm"] = np.linalg.norm(m - cs, axis=1).tolist()
        t["true_length_mm"] = float(np.linalg.norm(cs[0] - cs[1]))
        t["length_error_mm"] = b.length - t["true_length_mm"]
    return t


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
                                     seed=int(met["seed"]), arm=sd.arm),
           "draws": draws, "frames": sp.n_frames, "points": len(sp.points),
           "points_of_cloud": len(c["points"]),
           "contributors": list(uc.CONTRIBUTORS), "coverage_factor": uc.COVERAGE_FACTOR,
           "method": uc.METHOD}
    missing = list(model.missing)
    if sd.arm is None:
        missing.append(f"{sd.arm_error or 'no arm draws'}: the arm's pose error that the frames "
                       "of a pass share is not drawn")
    else:
        out["arm_draws"] = {"draws": len(sd.arm.draws), "kind": sd.arm.kind}
    if missing:
        out["incomplete"] = missing
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
        counts["points"] = int(sd.point_frames[1].sum())
        nl = sd.point_lasers
        counts["points_by_laser"] = {L: int(nl[1 + i]) for i, L in enumerate(("A", "B"))
                                     if L in lasers or nl[1 + i]}
        if nl[0]:
            counts["points_by_laser"]["other"] = int(nl[0])
    if sd.frame_ids is not None and sd.point_frames is not None:
        ppf = points_per_frame(sd.frame_ids, sd.states, None, counts_of=sd.point_frames)
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
        if isinstance(fs.get("arm_prior"), dict):
            counts["fused"]["arm_prior"] = fs["arm_prior"]
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
    labels = np.asarray(sd.cloud.get("laser", np.zeros(len(P), np.uint8))).astype(np.uint8,
                                                                                 copy=False)
    out["cloud_points"] = len(P)
    up = _up_vector(sd.cloud)
    # nothing after the up vector reads the normals: 24 B a point less at the figures' peak
    sd.cloud.pop("normals", None)
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
        elif sd.artefact == "ball_bar":
            b = mt.measure_ball_bar(P, float(sd.nominal.get("diameter", np.nan)),
                                    float(sd.nominal.get("length", np.nan)),
                                    ransac_threshold_mm=float(met["sphere_ransac_mm"]),
                                    trim_sigma=float(met["sphere_trim_sigma"]), seed=seed)
            out["measurement"] = b.figures()
            figures = partial(uc.ball_bar_figures, b)
            sd.plots["hist"] = {"values": b.residuals, "xlabel": "radial residual, both balls (mm)",
                                "bins": bins, "kind": "ball_bar"}
            if tscan:
                out["truth"] = _ball_bar_truth(b, tscan)
        elif sd.artefact == "freeform":
            out["measurement"] = {"n": len(P)}
            if sd.mesh:
                try:
                    out["nominal_comparison"], sd.plots["nominal"] = _nominal_comparison(
                        P, root / sd.mesh, tol, met, sd.T_base_nominal, sd.cloud.get("frame"))
                except (CrosslineError, ValueError) as exc:
                    out["nominal_error"] = str(exc)
                    log.warning("scan %s: no comparison with its nominal: %s", sd.name, exc)
                else:
                    mc = sd.plots["nominal"].pop("mc")
                    figures = partial(uc.freeform_figures, P, mc["T"], mc["dev"], mc["grad"],
                                      mc["keep"], float(tol["nominal_band_mm"]))
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
    if out.get("truth") and (out.get("uncertainty") or {}).get("figures"):
        cover = uncertainty_coverage(out["truth"], out["uncertainty"]["figures"])
        if cover:
            out["truth"]["uncertainty_coverage"] = cover
    if tscan and tscan.get("centrelines") and sd.points_path is not None:
        lines = truth_file(root, sd.name, tscan, "centrelines")
        out["truth_labels"] = _label_truth(sd.points_path, lines, files)
        if out["truth_labels"] and truth:
            smooth = ((sd.points_info or {}).get("params") or {}).get("smooth_px")
            bound = _speckle_limit(out["truth_labels"].get("centre_error") or {}, truth,
                                   sd.points_path, smooth, lines)
            if bound:
                out["truth_labels"]["speckle_limit"] = bound

    # top view, coloured by height (above the artefact's reference plane, else along `up`)
    if height_ref is not None:
        n, d = height_ref
    else:
        n, d = (up if up is not None else np.array([0.0, 0.0, 1.0])), 0.0
    B = _basis(n)
    # binned now, by blocks: a long scan's map arrays are not held until the pages are drawn;
    # the freeform's deviation map (validation) needs the coordinates
    sd.plots["top"] = top_view(P, np.vstack([B[:2], n]), np.array([0.0, 0.0, d]),
                               from_low=height_ref is None, keep_xy=sd.artefact == "freeform")
    return out


def _viewpoints(sd: ScanData) -> np.ndarray | None:
    """The camera centre (base frame) that saw each cloud point, from the points file."""
    from crossline.fuse import camera_centres
    from crossline.io.columns import read_columns

    if sd.points_path is None or sd.cloud is None or "frame" not in sd.cloud:
        return None
    names = ["frame", "x_cam", "y_cam", "z_cam", "x", "y", "z"]
    try:  # a number stored as text is refused, not cast (the scan's loading named the file)
        c = read_columns(sd.points_path, names)
    except Exception:  # pyarrow raises several types for broken files
        return None
    if any(len(c[k]) != len(c["frame"]) for k in names):  # an older points file without
        return None  # camera coordinates: no incidence
    frames, centres = camera_centres(c["frame"].astype(np.int64),
                                     np.column_stack([c[k] for k in names[1:4]]).astype(np.float64),
                                     np.column_stack([c[k] for k in names[4:]]).astype(np.float64))
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

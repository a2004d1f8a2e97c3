"""Pose refinement from the A-B stripe crossings (fuse.refine_poses): does it help, and where?

    python benchmarks/bench_refine.py                       # demo, compact-0, paper-1, compact-1
    python benchmarks/bench_refine.py --captures demo --draws 0

For each capture (``demo`` = data/raw/demo, the paper's rig, seed 0; ``compact`` = the
compact preset, seed 0; ``paper-1`` and ``compact-1`` = both rigs again with seed 1, i.e.
other stripes, noise and arm draws; the last three rendered once into
benchmarks/.cache/refine/, ~2 min each) the workflow
runs in a private copy under benchmarks/.cache/refine/wd-<capture>/ (stages cached by
Snakemake), twice: with ``fuse.refine_poses`` false and true, the rest of config.yaml as it
is. Then, for every scan and both runs:

- pose error against the true poses (truth/<scan>_poses.parquet), at the points: each point
  of the points file carried to the base frame with the reported pose (refined with the
  per-frame corrections of <scan>.fuse.json) against the same point with the true pose
  (same hand-eye matrix), RMS of the 3-D difference, and RMS of its component along the
  surface normal after the best rigid motion of the whole scan is taken out (an error
  common to all frames is invisible to any self-referencing; µm);
- the artefact's figures from the fused cloud (<scan>.ply) by crossline.report.metrics as the
  report computes them: gauge height mean/std (per-frame plate reference and plate plane),
  plate share within ±0.05 mm and flatness (full range, 2.5-97.5 %), sphere size and form
  error (all points, D95), freeform RMS to the true mesh; laser A against laser B;
- the fuse rule's wall time (Snakemake's benchmark file) and the refinement's own seconds.

One capture is one draw of the arm's error. So the same points (real rendered stripes,
estimated calibration) are also re-posed with ``--draws`` fresh draws of the simulator's
arm model (crossline.sim.arm, the capture's own arm figures) and refined in memory with the
config's prior (for compact a mismatched one: config 0.02 mm / 0.3 s against the rig's
0.03 mm / 0.5 s); the tables give the RMS over draws of each figure (raw points, no outlier
removal), beside the floor with the true poses.

Results: benchmarks/results/refine.txt and refine.json. Timings are from a shared 2-core
machine: noisy; the lead re-runs on a quiet one.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crossline.fuse import arm_prior, camera_centres, estimate_normals, orient_normals, read_ply  # noqa: E402
from crossline.geometry import transform_from_pose, transform_points  # noqa: E402
from crossline.io.capture import open_capture  # noqa: E402
from crossline.report import metrics as mt  # noqa: E402
from crossline.scan.refine import (  # noqa: E402
    HALF_MM,
    MAX_WIDTH_RATIO,
    MIN_ANGLE_DEG,
    ArmPrior,
    correction_transforms,
    refine_frames,
    usable_centres,
)

CACHE = REPO / "benchmarks" / ".cache" / "refine"
RESULTS = REPO / "benchmarks" / "results"
LINES: list[str] = []


def say(text: str = "") -> None:
    print(text, flush=True)
    LINES.append(text)


# ----------------------------------------------------------------------------- captures


def capture_path(name: str) -> Path | None:
    """The capture folder of ``name`` (rendering a ``<preset>-<seed>`` one if needed), or None.

    ``demo`` is data/raw/demo; ``compact`` is ``compact-0``; ``<preset>-<seed>`` (e.g.
    ``paper-1``) is that preset rendered with that seed into benchmarks/.cache/refine/ (all
    scans, ~2 min); anything else is taken as a capture folder.
    """
    if name == "demo":
        p = REPO / "data" / "raw" / "demo"
        return p if (p / "truth.json").is_file() else None
    from crossline.sim.presets import PRESETS

    name = "compact-0" if name == "compact" else name
    preset, _, seed = name.rpartition("-")
    if preset in PRESETS and seed.isdigit():
        p = CACHE / name
        if not (p / "truth.json").is_file():
            from crossline.sim import simulate

            say(f"rendering the {preset} preset (seed {seed}) into {p} ...")
            shutil.rmtree(p, ignore_errors=True)
            simulate(p, preset=preset, seed=int(seed), threads=2, progress=False)
        return p
    p = Path(name)
    return p if (p / "truth.json").is_file() else None


def workdir(name: str, capture: Path) -> Path:
    """A private copy of the workflow with the capture linked as data/raw/<name>."""
    wd = CACHE / f"wd-{name}"
    wd.mkdir(parents=True, exist_ok=True)
    shutil.copy(REPO / "Snakefile", wd)
    for d in ("workflow", "profiles", "crossline"):
        shutil.rmtree(wd / d, ignore_errors=True)
        shutil.copytree(REPO / d, wd / d, ignore=shutil.ignore_patterns("__pycache__"))
    link = wd / "data" / "raw" / name
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink() and link.resolve() != capture.resolve():
        link.unlink()
    if not link.exists():
        link.symlink_to(capture.resolve(), target_is_directory=True)
    return wd


def set_config(wd: Path, name: str, refine: bool) -> dict:
    cfg = yaml.safe_load((REPO / "config.yaml").read_text())
    cfg["captures"] = [name]
    cfg["simulate"] = {}
    cfg.setdefault("fuse", {})["refine_poses"] = refine
    (wd / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return cfg


def snakemake(wd: Path, *targets: str) -> None:
    proc = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", *targets], cwd=wd,
                          capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"snakemake failed in {wd}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")


# ----------------------------------------------------------------------------- measuring


def true_points(capture: Path, scan: str, df: pd.DataFrame, X: np.ndarray) -> np.ndarray:
    """Each point carried to the base frame with its frame's TRUE pose (same hand-eye)."""
    truth = json.loads((capture / "truth.json").read_text())
    tp = pd.read_parquet(capture / truth["scans"][scan]["poses"]).sort_values("frame")
    T = transform_from_pose(tp[["x", "y", "z"]].to_numpy(), tp[["qw", "qx", "qy", "qz"]].to_numpy()) @ X
    pos = np.searchsorted(tp["frame"].to_numpy(), df["frame"].to_numpy())
    pc = df[["x_cam", "y_cam", "z_cam"]].to_numpy()
    return transform_points(T[pos], pc)


def pose_error(q: np.ndarray, p_true: np.ndarray, normals: np.ndarray) -> dict[str, float]:
    """3-D RMS and rigid-removed normal RMS of q against p_true (µm)."""
    d = q - p_true
    dn = np.sum(d * normals, axis=1)
    c = p_true.mean(0)
    A = np.hstack([np.cross(p_true - c, normals), normals])
    sub = slice(None, None, max(1, len(q) // 100000))
    x = np.linalg.lstsq(A[sub], dn[sub], rcond=None)[0]
    return {"rms_3d_um": float(np.sqrt(np.mean(np.sum(d * d, 1)))) * 1e3,
            "rms_normal_um": float(np.sqrt(np.mean(dn**2))) * 1e3,
            "rms_normal_rigid_removed_um": float(np.sqrt(np.mean((dn - A @ x) ** 2))) * 1e3}


def refined_from_stats(df: pd.DataFrame, stats: dict) -> np.ndarray:
    """The points file's points moved by the per-frame corrections in a fuse stats JSON."""
    p = df[["x", "y", "z"]].to_numpy()
    r = (stats or {}).get("refine")
    if not r:
        return p
    pf = r["per_frame"]
    C = correction_transforms(np.array(pf["rotation_rad"]), np.array(pf["translation_mm"]),
                              np.array(pf["origin_mm"]))
    pos = np.searchsorted(np.array(pf["frame"]), df["frame"].to_numpy())
    return transform_points(C[pos], p)


_MESH: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def artefact_figures(artefact: str, nominal: dict, P: np.ndarray, labels: np.ndarray,
                     frames: np.ndarray | None, up: np.ndarray | None, capture: Path,
                     truth: dict, scan: str) -> dict[str, Any]:
    """The report's figures of one artefact (crossline.report.metrics, the report's settings)."""
    out: dict[str, Any] = {}
    try:
        if artefact == "gauge_block":
            g = mt.measure_gauge_block(P, float(nominal["height"]), edge_margin_mm=1.0, band_mm=0.2,
                                       up=up, seed=0, frame=frames)
            f = g.figures()
            out.update(height_mean_mm=f["mean_mm"], height_std_mm=f["std_mm"],
                       plane_ref_mean_mm=f.get("plane_reference_mean_mm"),
                       plane_ref_std_mm=f.get("plane_reference_std_mm"))
            ab = mt.compare_lasers("gauge_block", P, labels, gauge=g)
            if ab is not None:
                out["ab_height_mm"] = ab.difference["height_mm"]
        elif artefact == "plane":
            r = mt.measure_plane(P, band_mm=0.05, up=up)
            f = r.figures()
            out.update(share_within_band=f["share_within_band"], flatness_mm=f["flatness_mm"],
                       flatness_95_mm=f["flatness_95_mm"], rms_mm=f["rms_mm"])
            ab = mt.compare_lasers("plane", P, labels, plane=r)
            if ab is not None:
                out["ab_offset_mm"] = ab.difference["plane_offset_mm"]
        elif artefact == "sphere":
            s = mt.measure_sphere(P, float(nominal["diameter"]), ransac_threshold_mm=0.2,
                                  trim_sigma=5.0, seed=0)
            f = s.figures()
            out.update(size_error_mm=f["size_error_mm"], form_error_mm=f["form_error_mm"],
                       form_error_d95_mm=f["form_error_d95_mm"], rms_mm=f["rms_mm"])
            ab = mt.compare_lasers("sphere", P, labels, sphere=s)
            if ab is not None:
                out["ab_diameter_mm"] = ab.difference["diameter_mm"]
        elif artefact == "freeform":
            from crossline.report.accuracy import read_mesh

            mesh = capture / truth["scans"][scan]["mesh"]
            if str(mesh) not in _MESH:
                _MESH[str(mesh)] = read_mesh(mesh)
            V, F = _MESH[str(mesh)]
            dev = mt.mesh_signed_distance(P, V, F)
            if up is not None:
                a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
                if float(np.cross(b - a, c - a).sum(0) @ up) < 0:
                    dev = -dev
            on = np.abs(dev) <= 1.0
            if isinstance(truth.get("table_z_base"), int | float):
                on &= ~(np.abs(P[:, 2] - float(truth["table_z_base"])) < np.abs(dev))
            st = mt.deviation_stats(dev[on], 0.05)
            out.update(freeform_rms_mm=st["rms_mm"], freeform_mean_mm=st["mean_mm"],
                       freeform_std_mm=st["std_mm"])
    except ValueError as exc:
        out["error"] = str(exc)
    return out


def up_of(normals: np.ndarray | None) -> np.ndarray | None:
    if normals is None or len(normals) == 0:
        return None
    m = normals.mean(0)
    return m / np.linalg.norm(m) if np.linalg.norm(m) > 0.1 else None


# ----------------------------------------------------------------------------- one capture


def run_capture(name: str, capture: Path, draws: int) -> dict[str, Any]:
    """Workflow off/on, figures from the clouds, and the Monte-Carlo over arm draws."""
    truth = json.loads((capture / "truth.json").read_text())
    rig = open_capture(capture).rig
    scans = sorted(rig.scans)
    wd = workdir(name, capture)
    res: dict[str, Any] = {"capture": str(capture), "preset": truth.get("preset"),
                           "arm_noise": truth.get("arm_noise"), "scans": {}}
    t0 = time.perf_counter()
    set_config(wd, name, False)
    snakemake(wd, *[f"data/interim/{name}/points/{s}.parquet" for s in scans])
    say(f"[{name}] stages up to the points: {time.perf_counter() - t0:.0f} s (cached when unchanged)")
    interim = wd / "data" / "interim" / name
    X = np.array(json.loads((interim / "calibration" / "handeye.json").read_text())["T_tool_cam"])
    runs: dict[str, dict[str, Any]] = {}
    for tag, refine in (("reported", False), ("refined", True)):
        cfg = set_config(wd, name, refine)
        t = time.perf_counter()
        snakemake(wd, *[f"data/processed/{name}/{s}.ply" for s in scans], f"reports/{name}/metrics.json")
        say(f"[{name}] workflow with refine_poses={refine}: {time.perf_counter() - t:.0f} s")
        runs[tag] = {}
        for s in scans:
            ply = read_ply(wd / "data" / "processed" / name / f"{s}.ply")
            stats = json.loads((wd / "data" / "processed" / name / f"{s}.fuse.json").read_text())
            bench = wd / "logs" / name / "benchmarks" / "fuse_points" / f"{s}.tsv"
            wall = float(pd.read_csv(bench, sep="\t")["s"].iloc[-1]) if bench.is_file() else None
            runs[tag][s] = {"ply": ply, "stats": stats, "fuse_wall_s": wall}
        metrics = wd / "reports" / name / "metrics.json"
        runs[tag]["_metrics"] = json.loads(metrics.read_text()) if metrics.is_file() else None
        rb = wd / "logs" / name / "benchmarks" / "render_report.tsv"
        runs[tag]["_report_s"] = float(pd.read_csv(rb, sep="\t")["s"].iloc[-1]) if rb.is_file() else None
    fuse_cfg = cfg["fuse"]
    rad = fuse_cfg.get("arm_precision_rad", "auto")
    prior, _ = arm_prior(
        fuse_cfg.get("arm_precision_mm", "auto"), None if rad in (None, "auto") else float(rad),
        wd / "data" / "interim" / name / "calibration" / "handeye.json",
        smooth_fraction=float(fuse_cfg.get("arm_smooth_fraction", 0.9)),
        corr_time_s=float(fuse_cfg.get("arm_corr_time_s", 0.3)))
    res["prior"] = dataclasses.asdict(prior)
    res["report_s"] = {k: runs[k]["_report_s"] for k in runs}

    for s in scans:
        spec = rig.scans[s]
        df = pd.read_parquet(interim / "points" / f"{s}.parquet")
        pt = true_points(capture, s, df, X)
        nrm, _ = estimate_normals(pt, 0.5)
        row: dict[str, Any] = {"artefact": spec.artefact, "capture_run": {}}
        for tag in ("reported", "refined"):
            r = runs[tag][s]
            q = refined_from_stats(df, r["stats"])
            ply = r["ply"]
            fig = artefact_figures(spec.artefact, spec.nominal, ply["points"], ply["laser"],
                                   ply["frame"], up_of(ply.get("normals")), capture, truth, s)
            ref = r["stats"].get("refine") or {}
            row["capture_run"][tag] = {
                "pose_error": pose_error(q, pt, nrm), **fig, "fuse_wall_s": r["fuse_wall_s"],
                "crossings": ref.get("crossings"),
                "gap_rms_before_mm": ref.get("gap_rms_before_mm"),
                "gap_rms_after_mm": ref.get("gap_rms_after_mm"),
                "crossing_ab_offset_mm": ref.get("ab_offset_mm"),
                "correction_rms_mm": ref.get("correction_rms_mm"), "iterations": ref.get("iterations")}
        if draws:
            row["draws"] = monte_carlo(capture, s, spec, df, X, pt, nrm, truth, prior, draws, fuse_cfg)
        res["scans"][s] = row
    return res


def arm_draws(capture: Path, truth: dict, scan: str, df: pd.DataFrame, X: np.ndarray,
              draws: int) -> tuple[pd.DataFrame, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """The scan's true poses (table and flange transforms, frame order) and ``draws`` fresh
    draws of the simulator's arm model (seeds 1000, 1001, ...): each the points carried to
    the base frame with the drawn reported poses, and those flange poses."""
    from crossline.sim.arm import noise_scan
    from crossline.sim.presets import PRESETS

    tp = pd.read_parquet(capture / truth["scans"][scan]["poses"]).sort_values("frame")
    Tt = transform_from_pose(tp[["x", "y", "z"]].to_numpy(), tp[["qw", "qx", "qy", "qz"]].to_numpy())
    dt = float(np.median(np.diff(tp["time_s"].to_numpy())))
    pos = np.searchsorted(tp["frame"].to_numpy(), df["frame"].to_numpy())
    pc = df[["x_cam", "y_cam", "z_cam"]].to_numpy()
    out = []
    for k in range(draws):
        Tr, _, _ = noise_scan(Tt, PRESETS[truth["preset"]].arm, dt, np.random.default_rng(1000 + k))
        out.append((transform_points((Tr @ X)[pos], pc), Tr))
    return tp, Tt, out


def refine_posed(df: pd.DataFrame, p: np.ndarray, T: np.ndarray, tp: pd.DataFrame,
                 prior: ArmPrior, **kw: Any):
    """The refinement of points ``p`` posed with flange poses ``T`` (rows of ``tp``), as the
    fuse stage runs it: camera centres from the points, times and flange origins per frame."""
    fr = df["frame"].to_numpy()
    lab = np.where(df["laser"].astype(str) == "A", 1, 2).astype(np.uint8)
    frames, views = camera_centres(fr, df[["x_cam", "y_cam", "z_cam"]].to_numpy(), p)
    k = np.searchsorted(tp["frame"].to_numpy(), frames)
    return refine_frames(fr, lab, p, views, prior, frames=frames, times=tp["time_s"].to_numpy()[k],
                         origins=T[k, :3, 3], threads=2, **kw)


def monte_carlo(capture: Path, scan: str, spec: Any, df: pd.DataFrame, X: np.ndarray,
                pt: np.ndarray, nrm: np.ndarray, truth: dict, prior: ArmPrior, draws: int,
                fuse_cfg: dict) -> dict:
    """Fresh arm-error draws on the same points: figures reported vs refined, and the floor.

    The refinement runs as the workflow's fuse stage runs it: ``fuse_cfg``'s crossing
    window, smallest crossing angle and longest column cut.
    """
    fr = df["frame"].to_numpy()
    lab = np.where(df["laser"].astype(str) == "A", 1, 2).astype(np.uint8)
    fr_u, views_true = camera_centres(fr, df[["x_cam", "y_cam", "z_cam"]].to_numpy(), pt)
    kw = {"half_mm": float(fuse_cfg.get("crossing_half_mm", HALF_MM)),
          "min_angle_deg": float(fuse_cfg.get("crossing_min_angle_deg", MIN_ANGLE_DEG)),
          "crossing_mask": None if "width" not in df else usable_centres(
              lab, df["width"].to_numpy(np.float64),
              float(fuse_cfg.get("crossing_max_width_ratio", MAX_WIDTH_RATIO)))}
    up = up_of(orient_normals(pt, nrm, views_true[np.searchsorted(fr_u, fr)]))
    floor = artefact_figures(spec.artefact, spec.nominal, pt, lab, fr, up, capture, truth, scan)
    tp, Tt, posed = arm_draws(capture, truth, scan, df, X, draws)
    # the refinement run on the TRUE poses: what it does where there is nothing to correct
    # (only the stripes' own inconsistencies between A and B, and their noise)
    on_true = refine_posed(df, pt, Tt, tp, prior, **kw)
    floor_refined = {**pose_error(on_true.points, pt, nrm),
                     **artefact_figures(spec.artefact, spec.nominal, on_true.points, lab, fr, up, capture,
                                        truth, scan)}
    rows: dict[str, dict[str, list[float]]] = {"reported": {}, "refined": {}}
    secs = []
    for p, Tr in posed:
        t = time.perf_counter()
        ref = refine_posed(df, p, Tr, tp, prior, **kw)
        secs.append(time.perf_counter() - t)
        for tag, q in (("reported", p), ("refined", ref.points)):
            figs = {**pose_error(q, pt, nrm),
                    **artefact_figures(spec.artefact, spec.nominal, q, lab, fr, up, capture, truth, scan)}
            for key, v in figs.items():
                if isinstance(v, int | float):
                    rows[tag].setdefault(key, []).append(float(v))
    return {"draws": draws, "true_poses": floor, "true_poses_refined": floor_refined,
            "refine_s_median": float(np.median(secs)), **rows}


def _rms(v: list[float] | None, off: float = 0.0) -> float | None:
    """RMS over draws of v + off (an error against nominal when off = -nominal)."""
    return float(np.sqrt(np.mean(np.square(np.asarray(v) + off)))) if v else None


# ----------------------------------------------------------------------------- printing

FIGS = {  # key, label, scale, unit, offset (minus the nominal for a mean)
    "gauge_block": [
        ("height_mean_mm", "height mean - 20", 1e3, "µm", -20.0),
        ("height_std_mm", "height std", 1e3, "µm", 0),
        ("plane_ref_mean_mm", "height (plate plane) - 20", 1e3, "µm", -20.0),
        ("plane_ref_std_mm", "height std (plate plane)", 1e3, "µm", 0),
        ("ab_height_mm", "A-B height", 1e3, "µm", 0)],
    "plane": [
        ("share_within_band", "share within ±0.05", 100, "%", 0),
        ("flatness_mm", "flatness", 1e3, "µm", 0),
        ("flatness_95_mm", "flatness 2.5-97.5 %", 1e3, "µm", 0),
        ("rms_mm", "RMS to plane", 1e3, "µm", 0),
        ("ab_offset_mm", "A-B offset", 1e3, "µm", 0)],
    "sphere": [
        ("size_error_mm", "size error", 1e3, "µm", 0),
        ("form_error_mm", "form error (all)", 1e3, "µm", 0),
        ("form_error_d95_mm", "form error D95", 1e3, "µm", 0),
        ("rms_mm", "RMS radial", 1e3, "µm", 0),
        ("ab_diameter_mm", "A-B diameter", 1e3, "µm", 0)],
    "freeform": [
        ("freeform_rms_mm", "RMS to true mesh", 1e3, "µm", 0),
        ("freeform_mean_mm", "mean to true mesh", 1e3, "µm", 0),
        ("freeform_std_mm", "std to true mesh", 1e3, "µm", 0)],
}
POSE = [("rms_3d_um", "pose error 3-D"), ("rms_normal_um", "pose error along normal"),
        ("rms_normal_rigid_removed_um", "  same, common rigid motion removed")]


def _v(x: Any, scale: float = 1.0, off: float = 0.0) -> str:
    return f"{(x + off) * scale:9.2f}" if isinstance(x, int | float) else f"{'-':>9s}"


def print_capture(name: str, res: dict) -> None:
    pr, arm = res["prior"], res["arm_noise"]
    say(f"\n=== {name}: {res['capture']} (preset {res['preset']})")
    say(f"prior: {pr['sigma_mm'] * 1e3:.2f} µm, {pr['sigma_rad'] * 1e6:.1f} µrad per axis, smooth share "
        f"{pr['smooth_fraction']}, tau {pr['corr_time_s']} s; the rig's arm: {arm['precision_mm']} mm, "
        f"{arm['rot_sigma_axis_rad'] * 1e6:.0f} µrad, tau {arm['corr_time_s']} s")
    rs = res["report_s"]
    say(f"report rule: {_v(rs['reported']).strip()} s without, {_v(rs['refined']).strip()} s with refinement")
    for s, row in res["scans"].items():
        a, b = row["capture_run"]["reported"], row["capture_run"]["refined"]
        say(f"\n--- {name}/{s} ({row['artefact']}): this capture, fused clouds (reported | refined)")
        for k, lab in POSE:
            say(f"  {lab:40s} {_v(a['pose_error'][k])} | {_v(b['pose_error'][k])}  µm")
        for k, lab, sc, unit, off in FIGS[row["artefact"]]:
            say(f"  {lab:40s} {_v(a.get(k), sc, off)} | {_v(b.get(k), sc, off)}  {unit}")
        say(f"  {'fuse rule wall time':40s} {_v(a['fuse_wall_s'])} | {_v(b['fuse_wall_s'])}  s")
        um = {k: 1e3 * (b[k] or 0) for k in ("gap_rms_before_mm", "gap_rms_after_mm",
                                              "crossing_ab_offset_mm", "correction_rms_mm")}
        say(f"  refinement: {b['crossings']} crossings, {b['iterations']} "
            f"iterations, gap RMS {um['gap_rms_before_mm']:.2f} -> {um['gap_rms_after_mm']:.2f} µm, "
            f"A-B offset at the crossings {um['crossing_ab_offset_mm']:+.2f} µm, correction RMS "
            f"{um['correction_rms_mm']:.2f} µm")
        if "draws" in row:
            d = row["draws"]
            say(f"  {d['draws']} fresh arm draws on these points, RMS over draws (reported | refined), "
                f"and with the true poses (as they are | refined); refinement median "
                f"{d['refine_s_median']:.2f} s")
            tr = d["true_poses_refined"]
            for k, lab in POSE:
                say(f"  {lab:40s} {_v(_rms(d['reported'].get(k)))} | {_v(_rms(d['refined'].get(k)))} || "
                    f"{_v(0.0)} | {_v(tr.get(k))}  µm")
            for k, lab, sc, unit, off in FIGS[row["artefact"]]:
                ra, rb = _rms(d["reported"].get(k), off), _rms(d["refined"].get(k), off)
                f0, f1 = _v(d["true_poses"].get(k), sc, off), _v(tr.get(k), sc, off)
                say(f"  {lab:40s} {_v(ra, sc)} | {_v(rb, sc)} || {f0} | {f1}  {unit}")
                if off or k in ("size_error_mm", "ab_diameter_mm", "ab_height_mm", "freeform_mean_mm"):
                    ma = float(np.mean(np.asarray(d["reported"].get(k) or [np.nan]) + off))
                    mb = float(np.mean(np.asarray(d["refined"].get(k) or [np.nan]) + off))
                    say(f"  {'  (mean over draws)':40s} {_v(ma, sc)} | {_v(mb, sc)}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", default="demo,compact,paper-1,compact-1",
                    help="demo, compact, <preset>-<seed> or capture folders (comma-separated)")
    ap.add_argument("--draws", type=int, default=8, help="fresh arm-error draws per scan (0: none)")
    a = ap.parse_args(argv)
    out: dict[str, Any] = {}
    for name in a.captures.split(","):
        cap = capture_path(name)
        if cap is None:
            say(f"[{name}] no capture with truth.json found: skipped")
            continue
        out[name] = run_capture(Path(name).name, cap, a.draws)
        print_capture(name, out[name])
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "refine.json").write_text(json.dumps(out, indent=1, default=float) + "\n")
    (RESULTS / "refine.txt").write_text("\n".join(LINES) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

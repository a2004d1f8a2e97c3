"""Why the pose refinement shrinks the compact rig's sphere: the refinement on perfect poses.

    python benchmarks/bench_refine_bias.py                    # compact ball (bench_refine's cache)
    python benchmarks/bench_refine_bias.py --capture demo --scan ball

Needs the points of ``bench_refine.py``'s private workflow run (its cache,
benchmarks/.cache/refine/wd-<capture>/); run that first. The scan's stripe centres (real
rendered pixels) are triangulated with the TRUE camera and laser planes and carried to the
base frame with the TRUE poses and hand-eye: nothing is left for the refinement to correct,
so whatever it does comes from the stripes. Printed (µm):

- the sphere's size and form error with these points, and after the refinement with the
  workflow's prior (``fuse`` section of config.yaml);
- the same refinement with the crossings' gaps replaced by white noise of the measured
  level (``--noise-draws`` draws): what noise alone does to the size;
- the gaps binned by the crossing's polar angle on the sphere and by the frame distance
  between its A and B stripes (structure a white-noise model does not have);
- each laser's radial error on the sphere by polar angle and azimuth quadrant, and the
  refinement's radial shift per frame along the sweep;
- for every capture of ``--variant-captures`` (bench_refine's names): each laser's points,
  and its raw stripe centres extracted again with the Gaussian fit along the column alone and
  with the fit across steep stripes (``stripes.fit_across``), against the true centre lines by
  the length of their column cut (over the laser's median: steep or merged stripes), and the
  refinement's crossing parameters
  (``fuse.crossing_half_mm``, ``fuse.crossing_min_angle_deg``,
  ``fuse.crossing_max_width_ratio``) varied:
  on the workflow's points (estimated calibration) the size shift the refinement makes with
  the TRUE poses, and over ``--draws`` fresh arm draws (bench_refine's draws) the size error's
  mean and RMS and the form error's mean (µm); and the same parameters on the analytic
  white-noise ball of tests/test_refine.py (what its bounds say about them).

Results: benchmarks/results/refine_bias.txt.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_refine import CACHE, arm_draws, capture_path, refine_posed, true_points  # noqa: E402

from crossline.camera import Camera  # noqa: E402
from crossline.fuse import arm_prior, camera_centres  # noqa: E402
from crossline.geometry import transform_from_pose, transform_points  # noqa: E402
from crossline.io.capture import open_capture  # noqa: E402
from crossline.laser import LaserPlanes  # noqa: E402
from crossline.report import metrics as mt  # noqa: E402
from crossline.scan.refine import (  # noqa: E402
    HALF_MM,
    MAX_WIDTH_RATIO,
    MIN_ANGLE_DEG,
    ArmPrior,
    correction_transforms,
    refine_frames,
    solve_errors,
    usable_centres,
)
from crossline.scan.stripes import run_extract_stripes  # noqa: E402
from crossline.scan.triangulate import triangulate  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
LINES: list[str] = []


def say(text: str = "") -> None:
    print(text, flush=True)
    LINES.append(text)


def binned(label: str, x: np.ndarray, y: np.ndarray, bins: int = 5) -> None:
    q = np.quantile(x, np.linspace(0, 1, bins + 1))
    b = np.clip(np.searchsorted(q, x, side="right") - 1, 0, bins - 1)
    say(f"  {label:28s} " + "  ".join(f"[{q[i]:.0f}, {q[i + 1]:.0f}] {y[b == i].mean():+.2f}"
                                       for i in range(bins)))


# (half_mm, min_angle_deg, max_width_ratio); 0 = every centre may make crossings
VARIANTS = ((0.6, 30.0, 0.0), (0.6, 30.0, 2.0), (0.4, 30.0, 0.0), (0.6, 60.0, 0.0), (0.4, 60.0, 0.0))


def centre_error_by_cut(cap: Path, scan: str, df: pd.DataFrame, what: str = "centres") -> None:
    """The centres' true error (px, along the column) by their cut's length over the laser's median.

    ``df``: frame, laser, u, v, width (a points table, or the A and B frames of a stripes table).
    """
    truth_file = cap / "truth" / f"{scan}_centrelines.parquet"
    if not truth_file.is_file() or "width" not in df:
        return
    t = pd.read_parquet(truth_file, columns=["frame", "laser", "u", "v", "visible"])
    t = t[t["visible"]].rename(columns={"v": "v_true"})
    d = df[["frame", "laser", "u", "v", "width"]].copy()
    d["laser"] = d["laser"].astype(str)
    t["laser"] = t["laser"].astype(str)
    d["u"] = np.round(d["u"]).astype(np.int64)
    d["pid"] = np.arange(len(d))
    m = d.merge(t[["frame", "laser", "u", "v_true"]], on=["frame", "laser", "u"])
    m["dv"] = m["v"] - m["v_true"]
    m = m.loc[m.assign(a=m["dv"].abs()).groupby("pid")["a"].idxmin()]  # nearest true line
    m = m[m["dv"].abs() < 2.0]
    for laser in ("A", "B"):
        x = m[m["laser"] == laser]
        if len(x) == 0:
            continue
        ratio = x["width"] / np.median(df.loc[df["laser"].astype(str) == laser, "width"])
        parts = []
        for lo, hi in ((0, 1.5), (1.5, 2.0), (2.0, np.inf)):
            sel = (ratio > lo) & (ratio <= hi)
            if sel.sum():
                parts.append(f"cut {lo:g}-{hi:g}x median: {sel.mean():5.1%} of centres, error mean "
                             f"{x['dv'][sel].mean():+.3f} RMS {np.sqrt(np.mean(x['dv'][sel] ** 2)):.3f} px")
        say(f"    laser {laser} {what} against the true centre line: " + "; ".join(parts))


def fit_across_comparison(name: str, cap: Path, scan: str) -> None:
    """The scan's stripe centres, Gaussian fit along the column alone and with the fit across
    steep stripes (``stripes.fit_across``), against the true centre lines by cut length: the
    A and B frames' raw centres, before labelling, trimming and smoothing."""
    st = yaml.safe_load((REPO / "config.yaml").read_text())["stripes"]
    rn = st["relative_noise"]
    for across in (False, True):
        out = CACHE / f"stripes-{name}-{scan}-across-{str(across).lower()}.parquet"
        run_extract_stripes(cap, scan, out, extractor="gaussian", threshold=float(st["threshold"]),
                            min_width=float(st["min_width"]), max_width=float(st["max_width"]),
                            fit_pad=int(st["fit_pad"]), relative_noise=None if rn == "auto" else float(rn),
                            fit_across=across, threads=2)
        s = pd.read_parquet(out, columns=["frame", "lasers", "u", "v", "width"])
        s = s[s["lasers"].isin(["A", "B"])].rename(columns={"lasers": "laser"})
        centre_error_by_cut(cap, scan, s, f"stripe centres, {'fit across' if across else 'column fit'}")


def crossing_variants(name: str, scan: str, prior: ArmPrior, draws: int) -> None:
    """Size shift on the true poses and figures over arm draws, per crossing-parameter set."""
    cap = capture_path(name)
    interim = CACHE / f"wd-{name}" / "data" / "interim" / name
    points_file = interim / "points" / f"{scan}.parquet"
    if cap is None or not points_file.is_file():
        say(f"  {name}: no points at {points_file} (run bench_refine.py --captures {name}): skipped")
        return
    truth = json.loads((cap / "truth.json").read_text())
    R = 0.5 * float(truth["scans"][scan]["diameter"])
    df = pd.read_parquet(points_file)
    X = np.array(json.loads((interim / "calibration" / "handeye.json").read_text())["T_tool_cam"])
    pt = true_points(cap, scan, df, X)
    lab = np.where(df["laser"].astype(str) == "A", 1, 2)
    width = df["width"].to_numpy(np.float64)

    def sphere(P: np.ndarray) -> tuple[float, float]:
        f = mt.measure_sphere(P, 2 * R, ransac_threshold_mm=0.2, trim_sigma=5.0, seed=0).figures()
        return 1e3 * f["size_error_mm"], 1e3 * f["form_error_mm"]

    def refined(p: np.ndarray, T: np.ndarray, half: float, angle: float, ratio: float) -> np.ndarray:
        return refine_posed(df, p, T, tp, prior, half_mm=half, min_angle_deg=angle,
                            crossing_mask=usable_centres(lab, width, ratio)).points

    tp, Tt, drawn = arm_draws(cap, truth, scan, df, X, draws)
    posed = [(pt, Tt), *drawn]
    base = sphere(pt)[0]
    raw = np.array([sphere(p) for p, _ in posed[1:]])
    say(f"  {name}/{scan} ({truth['preset']}), true poses size {base:+.2f}; {draws} draws unrefined: "
        f"size mean {raw[:, 0].mean():+.2f} RMS {np.sqrt(np.mean(raw[:, 0] ** 2)):.2f}, "
        f"form mean {raw[:, 1].mean():.1f}")
    centre_error_by_cut(cap, scan, df, "points (labelled, trimmed, smoothed)")
    fit_across_comparison(name, cap, scan)
    for half, angle, ratio in VARIANTS:
        shift = sphere(refined(pt, Tt, half, angle, ratio))[0] - base
        f = np.array([sphere(refined(p, T, half, angle, ratio)) for p, T in posed[1:]])
        cut = f"cut <= {ratio:g}x" if ratio else "any cut  "
        say(f"    half {half:.1f} mm, angle >= {angle:2.0f} deg, {cut}: true-pose size shift {shift:+6.2f};  "
            f"draws size mean {f[:, 0].mean():+6.2f} RMS {np.sqrt(np.mean(f[:, 0] ** 2)):5.2f}, "
            f"form mean {f[:, 1].mean():5.1f}")


def analytic_variants() -> None:
    """The same parameters on the analytic white-noise ball of tests/test_refine.py.

    Noise (2 µm along the rays) and no pose error: the corrections the refinement makes from
    noise alone, in units of the arm prior's sigma; then pose errors injected (seeds 3-10 of
    the test's arm model) and the residual scatter of the refined ball over the noise-only
    one. test_noisy_scan_no_pose_error_is_not_distorted bounds both at the defaults (seed 3):
    0.25 sigma and 1.15x.
    """
    from crossline.geometry import fit_sphere
    from tests.test_refine import PRIOR, Scan, arm_errors

    s = Scan("sphere", noise=0.002)
    c = np.array(s.truth["center_base"])
    for half, angle, _ in VARIANTS[:1] + VARIANTS[2:]:
        p, ref = s.refine(None, half_mm=half, min_angle_deg=angle)
        on = np.linalg.norm(p - c, axis=1) < 12.6
        std0 = np.std(fit_sphere(p[on])[2])
        ratios = [np.std(fit_sphere(s.refine(arm_errors(len(s.T), PRIOR, seed=seed), half_mm=half,
                                             min_angle_deg=angle)[1].points[on])[2]) / std0
                  for seed in range(3, 11)]
        say(f"  half {half:.1f} mm, angle >= {angle:2.0f} deg: noise-only corrections "
            f"{ref.diagnostics['correction_rms_mm'] / PRIOR.sigma_mm:.3f} sigma; residual scatter "
            f"with pose errors {ratios[0]:.3f}x the noise-only one (seed 3), mean of 8 seeds "
            f"{np.mean(ratios):.3f}x")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", default="compact", help="demo or compact (bench_refine's names)")
    ap.add_argument("--scan", default="ball")
    ap.add_argument("--noise-draws", type=int, default=6)
    ap.add_argument("--variant-captures", default="demo,compact,paper-1,compact-1",
                    help="captures for the crossing-parameter table ('' for none)")
    ap.add_argument("--draws", type=int, default=8, help="arm draws per capture for that table")
    a = ap.parse_args(argv)
    cap = capture_path(a.capture)
    interim = CACHE / f"wd-{a.capture}" / "data" / "interim" / a.capture
    points_file = interim / "points" / f"{a.scan}.parquet"
    if cap is None or not points_file.is_file():
        say(f"no points at {points_file}: run benchmarks/bench_refine.py --captures {a.capture} first")
        return 1
    truth = json.loads((cap / "truth.json").read_text())
    spec = truth["scans"][a.scan]
    if "diameter" not in spec:
        say(f"scan {a.scan} is not a sphere")
        return 1
    centre, R = np.array(spec["center_base"], dtype=float), 0.5 * float(spec["diameter"])
    rig = open_capture(cap).rig
    cam = Camera(np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"]),
                 (rig.sensor.width, rig.sensor.height))
    df = pd.read_parquet(points_file)
    laser = df["laser"].astype(str).to_numpy()
    df[["x_cam", "y_cam", "z_cam"]] = triangulate(cam, LaserPlanes.from_dict(truth["lasers"]),
                                                  df[["u", "v"]].to_numpy(), laser)
    X = np.array(truth["T_tool_cam"])
    pt = true_points(cap, a.scan, df, X)
    tp = pd.read_parquet(cap / spec["poses"]).sort_values("frame")
    Tt = transform_from_pose(tp[["x", "y", "z"]].to_numpy(), tp[["qw", "qx", "qy", "qz"]].to_numpy())
    fr = df["frame"].to_numpy()
    lab = np.where(laser == "A", 1, 2)
    frames, views = camera_centres(fr, df[["x_cam", "y_cam", "z_cam"]].to_numpy(), pt)
    pos = np.searchsorted(tp["frame"].to_numpy(), frames)
    times, origins = tp["time_s"].to_numpy()[pos], Tt[pos, :3, 3]
    fcfg = yaml.safe_load((REPO / "config.yaml").read_text())["fuse"]
    rad = fcfg.get("arm_precision_rad", "auto")
    prior, _ = arm_prior(fcfg["arm_precision_mm"], None if rad in (None, "auto") else float(rad),
                         interim / "calibration" / "handeye.json",
                         smooth_fraction=float(fcfg["arm_smooth_fraction"]),
                         corr_time_s=float(fcfg["arm_corr_time_s"]))

    def sphere(P: np.ndarray) -> tuple[float, float]:
        f = mt.measure_sphere(P, 2 * R, ransac_threshold_mm=0.2, trim_sigma=5.0, seed=0).figures()
        return 1e3 * f["size_error_mm"], 1e3 * f["form_error_mm"]

    mask = usable_centres(lab, df["width"].to_numpy(np.float64))  # as the workflow's fuse stage
    ref = refine_frames(fr, lab, pt, views, prior, frames=frames, times=times, origins=origins,
                        crossing_mask=mask, threads=2)
    cr = ref.crossings
    say(f"=== {a.capture}/{a.scan}: TRUE camera, laser planes, hand-eye and poses; {len(pt)} points, "
        f"{len(cr.gap)} crossings; prior {prior.sigma_mm * 1e3:.2f} µm, tau {prior.corr_time_s} s")
    s0, f0 = sphere(pt)
    s1, f1 = sphere(ref.points)
    say(f"  size error {s0:+.2f} µm, form {f0:.2f} µm; after the refinement: size {s1:+.2f}, form {f1:.2f}")
    scale = ref.diagnostics["noise_scale"]
    fpos = np.searchsorted(frames, fr)
    rng = np.random.default_rng(0)
    sizes = []
    for _ in range(a.noise_draws):
        white = dataclasses.replace(cr, gap=rng.standard_normal(len(cr.gap)) * cr.sigma * scale)
        e, _, _ = solve_errors(white, origins, prior, times)
        C = correction_transforms(e[:, :3], e[:, 3:], origins)
        sizes.append(sphere(transform_points(C, pt, fpos))[0])
    say(f"  white-noise gaps (sd {1e3 * np.median(cr.sigma) * scale:.2f} µm), {a.noise_draws} draws: size "
        f"{np.mean(sizes):+.2f} ± {np.std(sizes):.2f} µm (change {np.mean(sizes) - s0:+.2f})")
    r = np.linalg.norm(cr.x - centre, axis=1)
    on = np.abs(r - R) < 0.1
    polar = np.degrees(np.arccos(np.clip((cr.x[:, 2] - centre[2]) / r, -1, 1)))
    say(f"  gaps on the sphere (A minus B along the normal, µm; mean {1e3 * cr.gap[on].mean():+.2f}):")
    binned("by polar angle (deg)", polar[on], 1e3 * cr.gap[on])
    binned("by frame of A minus frame of B", (frames[cr.frame_a] - frames[cr.frame_b])[on].astype(float),
           1e3 * cr.gap[on])
    q = pt - centre
    rr = np.linalg.norm(q, axis=1)
    pol = np.degrees(np.arccos(np.clip(q[:, 2] / rr, -1, 1)))
    az = np.degrees(np.arctan2(q[:, 1], q[:, 0]))
    radial = 1e3 * (rr - R)
    near = np.abs(radial) < 50
    say("  radial error of each laser's points (µm), by polar angle, and per azimuth quadrant "
        "[-180, -90) [-90, 0) [0, 90) [90, 180):")
    for code, name in ((1, "A"), (2, "B")):
        m = near & (lab == code)
        for lo, hi in ((0, 15), (15, 30), (30, 45), (45, 60), (60, 80)):
            mm = m & (pol >= lo) & (pol < hi)
            quad = []
            for q0 in (-180, -90, 0, 90):
                sel = mm & (az >= q0) & (az < q0 + 90)
                quad.append(f"{radial[sel].mean():+6.2f}" if sel.sum() > 50 else f"{'-':>6s}")
            say(f"    {name} polar {lo:2d}-{hi:2d}: {radial[mm].mean():+6.2f} (n {mm.sum():5d})  "
                + " ".join(quad))
    shift = 1e3 * (np.linalg.norm(ref.points - centre, axis=1) - rr)
    F = len(frames)
    cnt = np.bincount(fpos[near], minlength=F)
    per = np.bincount(fpos[near], shift[near], F) / np.maximum(cnt, 1)
    k = np.flatnonzero(cnt > 50)
    say("  the refinement's mean radial shift per frame (µm), every 10th frame with points: "
        + " ".join(f"{frames[i]}:{per[i]:+.1f}" for i in k[::10]))
    if a.variant_captures:
        say(f"=== the refinement's crossing parameters (default: half {HALF_MM} mm, angle >= "
            f"{MIN_ANGLE_DEG:g} deg, column cut <= {MAX_WIDTH_RATIO:g}x the laser's median), µm")
        for name in a.variant_captures.split(","):
            crossing_variants(name, a.scan, prior, a.draws)
        say("=== the same parameters on the analytic white-noise ball of tests/test_refine.py "
            "(no column cuts there)")
        analytic_variants()
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "refine_bias.txt").write_text("\n".join(LINES) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

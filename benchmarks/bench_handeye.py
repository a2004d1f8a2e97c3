"""Hand-eye accuracy over several rendered captures (seeds): one realisation is not a figure.

For each preset and seed, renders only what the hand-eye stage needs (the hand-eye views,
by the simulator's own jobs and per-image seeds, as in a full capture of that seed; cached under
``benchmarks/.cache/handeye/``), detects the board, runs ``solve_handeye`` with the TRUE
camera from the simulator, and prints per seed and over seeds (median and RMS):

* the RMS displacement of points of the measured volume (the whole field of view over the
  rig's working depths: paper 115-185 mm, compact 80-125 mm) carried by each method's X
  against the true X: Chou-Kamel, OpenCV's five, the plain reprojection refinement and the
  refined (maximum-likelihood) X (issue 3's target: <= 0.01 mm for the refined X);
* the refined solution's predicted 1-sigma for the same figure (from its covariance), and the
  normalised error ``e' C^-1 e`` of X's 6 parameters (chi-square with 6 degrees of freedom if
  the covariance is right: mean 6 over seeds);
* the noise the stage estimated (image px, arm mm and rad) against the simulator's.

On one seed per preset (``--estimated-camera-seed``) it also renders the camera and laser
board views, calibrates the camera as ``crossline calibrate-camera`` does (all board views,
bias correction) and solves the hand-eye with that camera, to show what the estimated camera
adds. A protocol study (how many views the expected figure needs) runs on exact synthetic
correspondences with the simulator's noise model (``--protocol``), no rendering.

    python benchmarks/bench_handeye.py                                  # compact 12, paper 6 seeds
    python benchmarks/bench_handeye.py --preset compact --seeds 8 --threads 2
    python benchmarks/bench_handeye.py --preset compact --views 36 --seeds 6
    python benchmarks/bench_handeye.py --noise-sweep 1,3,10                # issue 18.6

The noise sweep (``--noise-sweep``) scales each rendered seed's own arm-error draws (position
and rotation of every reported flange pose) by each factor, solves with the true camera and
prints per method the board consistency on the views (mm, the truth-free score the stage
chooses by) and X's error against truth (volume RMS, mm), the chosen method, the pairs the
data-driven tolerance keeps against those a fixed 0.05 deg cut would keep, and the
least-scatter X (the X minimising the board consistency itself) as a reference.

Results: benchmarks/results/handeye_seeds.txt and .json, handeye_noise.txt and .json
(timings are wall-clock on a shared machine: noisy).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_calibration import DEPTHS, TARGETS, volume_points  # noqa: E402

from crossline.calibrate.bias import centroid_offsets  # noqa: E402
from crossline.calibrate.camera import detect_views, solve_views  # noqa: E402
from crossline.calibrate.handeye import (  # noqa: E402
    OPENCV_METHODS,
    consistency_mm,
    motion_pairs,
    point_uncertainty,
    solve_handeye,
)
from crossline.calibrate.lm import dense_normal, levenberg_marquardt  # noqa: E402
from crossline.camera import Camera  # noqa: E402
from crossline.geometry import (  # noqa: E402
    invert_transform,
    make_transform,
    matrix_to_rotvec,
    rotation_angle,
    rotvec_to_matrix,
    transform_points,
)
from crossline.io.atomic import write_json  # noqa: E402
from crossline.sim import arm as arm_mod  # noqa: E402
from crossline.sim import capture as capture_mod  # noqa: E402
from crossline.sim import views as views_mod  # noqa: E402
from crossline.sim.presets import PRESETS, CalibrationSpec, RigPreset  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
CACHE = ROOT / "benchmarks" / ".cache" / "handeye"
METHODS = ("chou_kamel", *OPENCV_METHODS, "reprojection", "refined")
DEFAULT_SEEDS = {"compact": 12, "paper": 6}


# ----------------------------------------------------------------------------- rendering


def _sim_hash(rig: RigPreset) -> str:
    """Key of a cached render: the preset's numbers and the simulator's source."""
    h = hashlib.sha256(repr(rig).encode())
    for p in sorted((ROOT / "crossline" / "sim").glob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _calibration(rig: RigPreset, views: int | None) -> CalibrationSpec:
    cal = rig.calibration
    if views is None:
        return cal
    from dataclasses import replace

    return replace(cal, handeye_views=views)


def render(rig: RigPreset, seed: int, views: int | None, part: str, threads: int) -> Path:
    """One seed's hand-eye views (``part="handeye"``) or its camera and laser board views ("boards").

    The jobs, seeds and noise draws are those of ``crossline.sim.capture`` (each image its own
    generator); cached by preset, part, view count, seed and the simulator's source.
    """
    cal = _calibration(rig, views)
    n = cal.handeye_views
    out = CACHE / (f"{rig.name}-handeye{n}-s{seed}" if part == "handeye" else f"{rig.name}-boards-s{seed}")
    key = {"preset": rig.name, "seed": seed, "part": part, "handeye_views": n, "sim_hash": _sim_hash(rig)}
    meta = out / "meta.json"
    if meta.is_file() and json.loads(meta.read_text()).get("key") == key:
        return out
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    cam = true_camera(rig)
    plan = capture_mod.Plan(rig, seed, int(rig.sensor.bit_depth), out)
    info: dict = {}
    if part == "boards":
        for i, T in enumerate(views_mod.camera_views(cam, rig.board, cal, cal.camera_views)):
            plan.jobs.append(("camera", i, T, f"calibration/camera/view_{i:02d}.png"))
        for li, laser in enumerate(("A", "B")):
            vs = views_mod.laser_views(cam, rig.board, rig.lasers[laser], cal.laser_depths_mm,
                                       cal.laser_poses, phase=0.7 * li)
            for i, T in enumerate(vs):
                plan.jobs.append(("laser", laser, i, T, f"calibration/laser_{laser}/pose_{i:02d}_board.png",
                                  f"calibration/laser_{laser}/pose_{i:02d}_laser.png"))
    else:
        he = views_mod.handeye_views(cam, rig, n, cal.handeye_distance_mm)
        X = rig.T_tool_cam
        T_tool_true = np.array([arm_mod.tool_from_cam(T, X) for T in he])
        T_tool_rep, dp, dth = arm_mod.noise_calibration(T_tool_true, rig.arm, capture_mod._rng(seed, 90))
        for i, T in enumerate(he):
            plan.jobs.append(("handeye", i, invert_transform(T), f"calibration/handeye/pose_{i:02d}.png"))
        info = {"T_tool_cam": X, "T_base_board": rig.T_base_board,
                "T_base_tool_true": T_tool_true, "T_base_tool_reported": T_tool_rep,
                "T_cam_board": [invert_transform(T) @ rig.T_base_board for T in he],
                "error_position_mm": dp, "error_rotation_rad": dth}
    t0 = time.perf_counter()
    if threads <= 1:
        for j in plan.jobs:
            capture_mod._run(plan, j)
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        light = capture_mod.Plan(plan.preset, plan.seed, plan.bits, plan.root)
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(["crossline.sim.capture"])
        with ProcessPoolExecutor(max_workers=threads, mp_context=ctx) as ex:
            for f in [ex.submit(capture_mod._run, light, j) for j in plan.jobs]:
                f.result()
    write_json(meta, {"key": key, "render_s": time.perf_counter() - t0, "jobs": len(plan.jobs), **info})
    return out


# ----------------------------------------------------------------------------- scoring


def true_camera(rig: RigPreset) -> Camera:
    """The simulator's camera."""
    s = rig.sensor
    return Camera(np.array(s.K), np.array(s.dist), (s.width, s.height))


def x_error(X: np.ndarray, X_true: np.ndarray) -> np.ndarray:
    """The perturbation e = (rotation, translation) with ``X_true = X exp(e)`` (first order)."""
    D = invert_transform(X) @ X_true
    return np.r_[matrix_to_rotvec(D[:3, :3]), D[:3, 3]]


def score(he, rig: RigPreset, cam: Camera) -> dict:
    """Per method: volume RMS displacement against the true X; refined: prediction and chi-square."""
    X_t = rig.T_tool_cam
    Pv = volume_points(cam, DEPTHS[rig.name], n=11, nz=8)
    out: dict = {"methods": {}}
    for name in METHODS:
        m = he.extra["methods"].get(name, {})
        if "T_tool_cam" not in m:
            out["methods"][name] = {"error": m.get("error", "missing")}
            continue
        X = np.array(m["T_tool_cam"])
        d = transform_points(X, Pv) - transform_points(X_t, Pv)
        out["methods"][name] = {
            "volume_rms_mm": float(np.sqrt(np.mean(np.sum(d**2, 1)))),
            "rotation_err_deg": float(np.degrees(rotation_angle(X[:3, :3].T @ X_t[:3, :3]))),
            "translation_err_mm": float(np.linalg.norm(X[:3, 3] - X_t[:3, 3])),
        }
    ref = he.extra["methods"]["refined"]
    C = np.array(ref["uncertainty"]["covariance_X"])
    sig = point_uncertainty(he.T_tool_cam, C, Pv)
    e = x_error(he.T_tool_cam, X_t)
    out["predicted_volume_rms_mm"] = float(np.sqrt(np.mean(sig**2)))
    out["chi2_6"] = float(e @ np.linalg.solve(C, e))
    out["noise_model"] = ref["noise_model"]
    out["pairs"] = {k: he.extra["pairs"][k] for k in ("used", "total", "rejected")}
    return out


def run_seed(rig: RigPreset, seed: int, views: int | None, threads: int, camera: str) -> dict:
    """Render (or reuse), detect and solve one seed; ``camera`` is "true" or "estimated"."""
    t0 = time.perf_counter()
    root = render(rig, seed, views, "handeye", threads)
    boards = render(rig, seed, views, "boards", threads) if camera == "estimated" else None
    t_render = time.perf_counter() - t0
    meta = json.loads((root / "meta.json").read_text())
    board = rig.board.board
    shape = (rig.sensor.height, rig.sensor.width)
    he_paths = sorted((root / "calibration" / "handeye").glob("pose_*.png"))
    t0 = time.perf_counter()
    dets = detect_views(he_paths, board, shape, threads)
    t_detect = time.perf_counter() - t0
    cam = true_camera(rig)
    cam_info = None
    if camera == "estimated":
        # as `crossline calibrate-camera` (views "all"): camera, laser board and hand-eye views
        cal = boards / "calibration"
        paths = (sorted((cal / "camera").glob("*.png"))
                 + [p for laser in "AB" for p in sorted((cal / f"laser_{laser}").glob("*_board.png"))]
                 + he_paths)
        names = [str(p.relative_to(p.parents[2])) for p in paths]
        cdets = detect_views(paths[: len(paths) - len(he_paths)], board, shape, threads) + dets
        fit, used, _ = solve_views(names, cdets, board, (rig.sensor.width, rig.sensor.height))
        est = fit.camera
        Pv = volume_points(cam, DEPTHS[rig.name])
        dproj = est.project(Pv) - cam.project(Pv)
        cam_info = {"views_used": len(used), "rms_px": fit.rms_px,
                    "projection_rms_px_vs_true": float(np.sqrt(np.mean(np.sum(dproj**2, 1))))}
        cam = est
    use = [k for k, d in enumerate(dets) if d.found]
    pts = np.array([dets[k].points for k in use])
    Tb = np.array(meta["T_base_tool_reported"])[use]
    t0 = time.perf_counter()
    he = solve_handeye(cam, board, pts, Tb, [he_paths[k].name for k in use])
    t_solve = time.perf_counter() - t0
    r = score(he, rig, true_camera(rig))
    r.update(seed=seed, camera=camera, views=len(he_paths), views_found=len(use),
             timings_s={"render_or_cache": t_render, "detect": t_detect, "solve": t_solve})
    if cam_info:
        r["estimated_camera"] = cam_info
    # the measured circle centres against the true imaged centroids: the image noise the
    # hand-eye stage really sees (true camera, true pose)
    Tc = np.array(meta["T_cam_board"])[use]
    P = board.object_points()
    e = np.concatenate([
        p - (true_camera(rig).project(P @ T[:3, :3].T + T[:3, 3])
             + centroid_offsets(true_camera(rig), board, matrix_to_rotvec(T[:3, :3]), T[:3, 3]))
        for p, T in zip(pts, Tc, strict=True)
    ])
    r["centre_error_px_per_axis"] = float(np.sqrt(np.mean(e**2)))
    # where the error comes from: the same solve with the true arm poses (image error only),
    # and with the exact imaged centroids and the reported arm poses (arm error only)
    exact = pts - e.reshape(pts.shape)
    names = [he_paths[k].name for k in use]
    r["decomposition"] = {}
    for label, (p_in, T_in) in {"true_arm_poses": (pts, np.array(meta["T_base_tool_true"])[use]),
                                "exact_centres": (exact, Tb)}.items():
        sub = score(solve_handeye(cam, board, p_in, T_in, names), rig, true_camera(rig))
        r["decomposition"][label] = {
            "refined_mm": sub["methods"]["refined"]["volume_rms_mm"],
            "chou_kamel_mm": sub["methods"]["chou_kamel"]["volume_rms_mm"],
            "predicted_mm": sub["predicted_volume_rms_mm"],
        }
    return r


# ----------------------------------------------------------------------------- protocol study


def synthetic_views(rig: RigPreset, n: int):
    """True flange poses, board poses and exact imaged centroids of ``n`` hand-eye views."""
    cam = true_camera(rig)
    cal = rig.calibration
    he = views_mod.handeye_views(cam, rig, n, cal.handeye_distance_mm)
    Tb = np.array([arm_mod.tool_from_cam(T, rig.T_tool_cam) for T in he])
    Tc = np.array([invert_transform(T) @ rig.T_base_board for T in he])
    board = rig.board.board
    P = board.object_points()
    pts = np.array([cam.project(P @ T[:3, :3].T + T[:3, 3])
                    + centroid_offsets(cam, board, matrix_to_rotvec(T[:3, :3]), T[:3, 3]) for T in Tc])
    return cam, board, Tb, pts


def protocol(rig: RigPreset, view_counts: list[int], trials: int, sigma_px: float) -> list[dict]:
    """Over ``trials`` synthetic noise draws per view count: measured and predicted volume RMS."""
    rows = []
    for n in view_counts:
        cam, board, Tb, pts = synthetic_views(rig, n)
        Pv = volume_points(cam, DEPTHS[rig.name], n=11, nz=8)
        errs, preds = [], []
        for t in range(trials):
            rng = np.random.default_rng([n, t, 7])
            Tn, _, _ = arm_mod.noise_calibration(Tb, rig.arm, rng)
            he = solve_handeye(cam, board, pts + rng.normal(0.0, sigma_px, pts.shape), Tn,
                               [str(k) for k in range(n)])
            d = transform_points(he.T_tool_cam, Pv) - transform_points(rig.T_tool_cam, Pv)
            errs.append(float(np.sqrt(np.mean(np.sum(d**2, 1)))))
            C = np.array(he.extra["methods"]["refined"]["uncertainty"]["covariance_X"])
            preds.append(float(np.sqrt(np.mean(point_uncertainty(he.T_tool_cam, C, Pv) ** 2))))
        rows.append({"views": n, "trials": trials, "sigma_px": sigma_px,
                     "median_mm": float(np.median(errs)), "rms_mm": float(np.sqrt(np.mean(np.square(errs)))),
                     "predicted_rms_mm": float(np.sqrt(np.mean(np.square(preds)))),
                     "p90_mm": float(np.quantile(errs, 0.9))})
    return rows


# ----------------------------------------------------------------------------- noise sweep

FIXED_CUT_DEG = 0.05  # the former fixed tolerance on |theta_A - theta_B|
SWEEP_METHODS = (*METHODS, "least_scatter")


def least_scatter(X0: np.ndarray, T_base_tool: np.ndarray, T_cam_board: np.ndarray, board) -> np.ndarray:
    """The X minimising the board consistency on the views itself (Gauss-Newton from ``X0``)."""
    P = board.object_points()

    def fun(x: np.ndarray) -> np.ndarray:
        T = T_base_tool @ X0 @ make_transform(rotvec_to_matrix(x[:3]), x[3:]) @ T_cam_board
        pts = np.einsum("vij,nj->vni", T[:, :3, :3], P) + T[:, None, :3, 3]
        return (pts - pts.mean(0)).ravel()

    def jac(x: np.ndarray) -> np.ndarray:
        f0 = fun(x)
        J = np.empty((f0.size, 6))
        for k in range(6):
            dx = np.zeros(6)
            dx[k] = 1e-7 if k < 3 else 1e-5
            J[:, k] = (fun(x + dx) - f0) / dx[k]
        return J

    x = levenberg_marquardt(fun, dense_normal(jac), np.zeros(6)).x
    return X0 @ make_transform(rotvec_to_matrix(x[:3]), x[3:])


def sweep_seed(rig: RigPreset, seed: int, views: int | None, threads: int, scales: list[float]) -> list[dict]:
    """One rendered seed's hand-eye views solved with its arm errors scaled by each factor."""
    root = render(rig, seed, views, "handeye", threads)
    meta = json.loads((root / "meta.json").read_text())
    board = rig.board.board
    paths = sorted((root / "calibration" / "handeye").glob("pose_*.png"))
    dets = detect_views(paths, board, (rig.sensor.height, rig.sensor.width), threads)
    use = [k for k, d in enumerate(dets) if d.found]
    pts = np.array([dets[k].points for k in use])
    T_true = np.array(meta["T_base_tool_true"])[use]
    dp = np.array(meta["error_position_mm"])[use]
    dth = np.array(meta["error_rotation_rad"])[use]
    cam = true_camera(rig)
    Pv = volume_points(cam, DEPTHS[rig.name], n=11, nz=8)
    X_t = rig.T_tool_cam
    rows = []
    for s in scales:
        T_rep = make_transform(T_true[:, :3, :3] @ rotvec_to_matrix(s * dth), T_true[:, :3, 3] + s * dp)
        t0 = time.perf_counter()
        he = solve_handeye(cam, board, pts, T_rep, [paths[k].name for k in use])
        t_solve = time.perf_counter() - t0
        m = he.extra["methods"]
        used = np.array([b["used"] for b in he.extra["board_poses"]])
        Tc = np.array([b["T_cam_board"] for b in he.extra["board_poses"]])
        Xs = {k: np.array(v["T_tool_cam"]) for k, v in m.items() if "T_tool_cam" in v}
        Xs["least_scatter"] = least_scatter(Xs["refined"], T_rep[used], Tc[used], board)
        per = {}
        for k, X in Xs.items():
            d = transform_points(X, Pv) - transform_points(X_t, Pv)
            per[k] = {"volume_rms_mm": float(np.sqrt(np.mean(np.sum(d**2, 1)))),
                      "board_consistency_mm": consistency_mm(X, T_rep[used], Tc[used], board)}
        # what the former fixed cut would have kept of the same pairs
        pairs = [(i, j) for i in range(len(use)) for j in range(i + 1, len(use))]
        A, B = motion_pairs(T_rep, Tc, pairs)
        mis = np.degrees(np.abs(rotation_angle(A[:, :3, :3]) - rotation_angle(B[:, :3, :3])))
        sel = he.extra["selection"]
        rows.append({
            "seed": seed, "scale": s, "views": len(use), "chosen": he.method, "methods": per,
            "selection": {k: v for k, v in sel.items() if k != "rule"},
            "pairs": {k: he.extra["pairs"][k] for k in ("used", "total", "mismatch_sigma_deg",
                                                        "mismatch_rms_deg", "angle_tolerance_deg")},
            "pairs_fixed_cut_kept": int(np.sum(mis <= FIXED_CUT_DEG)),
            "solve_s": t_solve,
        })
    return rows


def format_sweep(title: str, rows: list[dict], scales: list[float]) -> tuple[str, dict]:
    """Per scale: per method mean board consistency and median / RMS X error over seeds."""
    short = {"chou_kamel": "C-K", "tsai": "tsai", "park": "park", "horaud": "horaud", "andreff": "andreff",
             "daniilidis": "daniil", "reprojection": "reproj", "refined": "refined",
             "least_scatter": "l-scat", "chosen": "CHOSEN"}
    cols = [*SWEEP_METHODS, "chosen"]
    L = [title]
    summary: dict = {}
    for s in scales:
        rs = [r for r in rows if r["scale"] == s]

        def vals(key: str, col: str, rs=rs) -> np.ndarray:
            return np.array([r["methods"][r["chosen"] if col == "chosen" else col][key] for r in rs
                             if (r["chosen"] if col == "chosen" else col) in r["methods"]])

        L.append(f"  arm noise x{s:g} ({len(rs)} seeds; pairs kept: data-driven "
                 f"{sum(r['pairs']['used'] for r in rs)}, fixed {FIXED_CUT_DEG:g} deg "
                 f"{sum(r['pairs_fixed_cut_kept'] for r in rs)}, of {sum(r['pairs']['total'] for r in rs)}; "
                 f"mismatch RMS {np.median([r['pairs']['mismatch_rms_deg'] for r in rs]):.4f} deg, robust "
                 f"sigma {np.median([r['pairs']['mismatch_sigma_deg'] for r in rs]):.4f} deg, cut "
                 f"{np.median([r['pairs']['angle_tolerance_deg'] for r in rs]):.4f} deg (medians))")
        L.append("    " + f"{'':26}" + "".join(f"{short[c]:>9}" for c in cols))
        summ = {}
        for label, key, stat in (("board consistency mean", "board_consistency_mm", np.mean),
                                 ("X error median", "volume_rms_mm", np.median),
                                 ("X error RMS", "volume_rms_mm", lambda v: np.sqrt(np.mean(v**2)))):
            row = {c: float(stat(vals(key, c))) for c in cols}
            summ[label] = row
            L.append(f"    {label + ' (mm)':26}" + "".join(f"{row[c]:9.5f}" for c in cols))
        chosen = [r["chosen"] for r in rs]
        d = np.array([r["selection"]["vs_best_opencv_percent"] for r in rs])
        ref_wins = np.mean([r["methods"]["refined"]["volume_rms_mm"]
                            <= min(r["methods"][k]["volume_rms_mm"] for k in OPENCV_METHODS) for r in rs])
        counts = ", ".join(f"{c} x{chosen.count(c)}" for c in sorted(set(chosen)))
        L.append(f"    chosen: {counts}; chosen vs "
                 f"best OpenCV consistency: median {np.median(d):+.2f} %, worst {d.max():+.2f} % "
                 f"(selection margin median {np.median([r['selection']['margin_mm'] for r in rs]):.5f} mm); "
                 f"refined X closer to truth than every OpenCV method in {100 * ref_wins:.0f} % of seeds")
        summ.update(chosen=chosen, vs_best_opencv_percent=d.tolist(),
                    refined_beats_opencv_fraction=float(ref_wins))
        summary[f"x{s:g}"] = summ
    return "\n".join(L), summary


# ----------------------------------------------------------------------------- report


def _stats(vals: list[float]) -> tuple[float, float]:
    v = np.asarray(vals, dtype=float)
    return float(np.median(v)), float(np.sqrt(np.mean(v**2)))


def summarise(runs: list[dict]) -> dict:
    """Median and RMS over seeds of each method's volume RMS, the prediction and chi-square."""
    out: dict = {"seeds": [r["seed"] for r in runs], "methods": {}}
    for name in METHODS:
        vals = [r["methods"][name]["volume_rms_mm"] for r in runs if "volume_rms_mm" in r["methods"][name]]
        if vals:
            med, rms = _stats(vals)
            out["methods"][name] = {"median_mm": med, "rms_mm": rms}
    out["predicted_median_mm"], out["predicted_rms_mm"] = _stats([r["predicted_volume_rms_mm"] for r in runs])
    out["chi2_6_mean"] = float(np.mean([r["chi2_6"] for r in runs]))
    return out


def format_block(title: str, runs: list[dict], summ: dict) -> str:
    """Table: one row per seed, then median and RMS over seeds."""
    short = {"chou_kamel": "C-K", "tsai": "tsai", "park": "park", "horaud": "horaud",
             "andreff": "andreff", "daniilidis": "daniil", "reprojection": "reproj", "refined": "refined"}
    head = ("   seed " + "".join(f"{short[m]:>9}" for m in METHODS)
            + "   pred 1s   chi2_6  arm mm/rad est      img px")
    L = [title, "   volume RMS displacement vs true X (mm), per method", head]
    for r in runs:
        nm = r["noise_model"]
        L.append(f"   {r['seed']:>4} " + "".join(
            f"{r['methods'][m].get('volume_rms_mm', float('nan')):9.5f}" for m in METHODS)
            + f"   {r['predicted_volume_rms_mm']:.5f}  {r['chi2_6']:7.2f}  "
            f"{nm['arm_sigma_mm']:.5f}/{nm['arm_sigma_rad']:.2e}  {nm['image_sigma_px']:.4f}")
    for stat in ("median", "rms"):
        L.append(f"   {stat:>6}" + "".join(
            f"{summ['methods'][m][stat + '_mm']:9.5f}" if m in summ["methods"] else f"{'-':>9}"
            for m in METHODS)
            + f"   {summ['predicted_' + stat + '_mm']:.5f}"
            + (f"  {summ['chi2_6_mean']:7.2f} (mean; 6 if the covariance is right)" if stat == "rms" else ""))
    ref = summ["methods"]["refined"]
    ok = "ok" if ref["median_mm"] <= TARGETS["handeye_mm"] else "NOT MET"
    L.append(f"   refined: median {ref['median_mm']:.5f} mm, RMS {ref['rms_mm']:.5f} mm over {len(runs)} "
             f"seeds [{ok} <= {TARGETS['handeye_mm']} (median)]; predicted 1-sigma RMS "
             f"{summ['predicted_rms_mm']:.5f} mm")
    return "\n".join(L)


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", action="append", choices=sorted(PRESETS),
                    help="preset (repeatable); default: compact and paper")
    ap.add_argument("--seeds", type=int, help="seeds 0..N-1 per preset (default: compact 12, paper 6)")
    ap.add_argument("--views", type=int, help="override the preset's number of hand-eye views")
    ap.add_argument("--estimated-camera-seed", type=int, default=0,
                    help="seed also solved with a camera calibrated from its rendered views (-1: none)")
    ap.add_argument("--protocol", type=str, default="",
                    help="comma-separated view counts for the synthetic protocol study (e.g. 24,36,48)")
    ap.add_argument("--protocol-trials", type=int, default=40)
    ap.add_argument("--noise-sweep", type=str, default="",
                    help="comma-separated arm-noise factors (e.g. 1,3,10): the noise sweep only")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=str, help="results file stem (default handeye_seeds, "
                                            "handeye_noise with --noise-sweep)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s %(name)s: %(message)s")
    import cv2

    cv2.setNumThreads(1)
    presets = args.preset or ["compact", "paper"]
    blocks, results = [], {}
    if args.noise_sweep:
        args.out = args.out or "handeye_noise"
        scales = [float(x) for x in args.noise_sweep.split(",")]
        for name in presets:
            rig = PRESETS[name]
            n_seeds = args.seeds or DEFAULT_SEEDS.get(name, 3)
            rows = []
            for seed in range(n_seeds):
                rows += sweep_seed(rig, seed, args.views, args.threads, scales)
                print(f"{name} seed {seed}: " + ", ".join(
                    f"x{r['scale']:g} {r['chosen']} {r['methods'][r['chosen']]['volume_rms_mm']:.5f} mm"
                    for r in rows[-len(scales):]), flush=True)
            title = (f"== {name}: {rows[0]['views']} hand-eye views, true camera, seeds 0-{n_seeds - 1}; "
                     f"arm errors = each seed's draws x factor (x1: {rig.arm.sigma_axis_mm:.5f} mm / "
                     f"{rig.arm.rot_sigma_rad:.1e} rad per axis); X error = volume RMS vs true X, z = "
                     f"{DEPTHS[name][0]:g}-{DEPTHS[name][1]:g} mm")
            block, summ = format_sweep(title, rows, scales)
            print(block, flush=True)
            blocks.append(block)
            results[name] = {"rows": rows, "summary": summ}
        presets = []
    args.out = args.out or "handeye_seeds"
    for name in presets:
        rig = PRESETS[name]
        n_seeds = args.seeds or DEFAULT_SEEDS.get(name, 3)
        runs = []
        for seed in range(n_seeds):
            runs.append(run_seed(rig, seed, args.views, args.threads, "true"))
            print(f"{name} seed {seed}: refined {runs[-1]['methods']['refined']['volume_rms_mm']:.5f} mm, "
                  f"predicted {runs[-1]['predicted_volume_rms_mm']:.5f} mm "
                  f"({runs[-1]['timings_s']['render_or_cache']:.0f} s render/cache)", flush=True)
        summ = summarise(runs)
        views = runs[0]["views"]
        title = (f"== {name}: {views} hand-eye views, true camera, seeds 0-{n_seeds - 1}; volume = whole "
                 f"field of view, z = {DEPTHS[name][0]:g}-{DEPTHS[name][1]:g} mm; arm sigma "
                 f"{rig.arm.sigma_axis_mm:.5f} mm / {rig.arm.rot_sigma_rad:.1e} rad per axis (simulator)")
        block = format_block(title, runs, summ)
        entry: dict = {"views": views, "runs": runs, "summary": summ}
        if args.estimated_camera_seed >= 0:
            est = run_seed(rig, args.estimated_camera_seed, args.views, args.threads, "estimated")
            entry["estimated_camera"] = est
            tr = next(r for r in runs if r["seed"] == args.estimated_camera_seed) \
                if args.estimated_camera_seed < n_seeds else None
            ec = est["estimated_camera"]
            block += (f"\n   estimated camera (seed {est['seed']}; {ec['views_used']} board views, "
                      f"projection RMS vs true {ec['projection_rms_px_vs_true']:.4f} px): "
                      + ", ".join(f"{m} {est['methods'][m]['volume_rms_mm']:.5f}"
                                  for m in ("chou_kamel", "reprojection", "refined"))
                      + f" mm; predicted {est['predicted_volume_rms_mm']:.5f}")
            if tr:
                block += f" (true camera: refined {tr['methods']['refined']['volume_rms_mm']:.5f})"
        block += ("\n   circle centres vs true imaged centroids, per axis: "
                  + ", ".join(f"{r['centre_error_px_per_axis']:.4f}" for r in runs) + " px")
        for label in ("true_arm_poses", "exact_centres"):
            d = [r["decomposition"][label] for r in runs]
            block += (f"\n   {label.replace('_', ' ')} only (refined, per seed): "
                      + ", ".join(f"{x['refined_mm']:.5f}" for x in d)
                      + f"; RMS {_stats([x['refined_mm'] for x in d])[1]:.5f}, predicted RMS "
                      f"{_stats([x['predicted_mm'] for x in d])[1]:.5f} mm")
        if args.protocol:
            counts = [int(c) for c in args.protocol.split(",")]
            sigma = float(np.median([r["centre_error_px_per_axis"] for r in runs]))
            rows = protocol(rig, counts, args.protocol_trials, sigma)
            entry["protocol"] = rows
            block += (f"\n   protocol study (synthetic, simulator's arm noise, image noise {sigma:.4f} px, "
                      f"{args.protocol_trials} trials per row): views  median  RMS  predicted  p90 (mm)")
            for row in rows:
                block += (f"\n     {row['views']:>4}  {row['median_mm']:.5f}  {row['rms_mm']:.5f}  "
                          f"{row['predicted_rms_mm']:.5f}  {row['p90_mm']:.5f}")
        print(block, flush=True)
        blocks.append(block)
        results[name] = entry
    meta = {"load_average": os.getloadavg(), "cpus": os.cpu_count(), "target_mm": TARGETS["handeye_mm"],
            "command": " ".join(["python", "benchmarks/bench_handeye.py",
                                 *(argv if argv is not None else sys.argv[1:])])}
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / f"{args.out}.json", {"meta": meta, "results": results})
    (RESULTS / f"{args.out}.txt").write_text(f"# {meta['command']}\n" + "\n\n".join(blocks) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

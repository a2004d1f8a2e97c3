"""Calibration accuracy against the virtual rig's truth: camera, laser planes, hand-eye.

For each capture (by default a `--quick` capture of the `paper` preset, or `data/raw/demo` if
it exists, and a `--quick` capture of the second preset), runs the three calibration stages
exactly as the workflow does and prints, against ``truth.json``:

* camera, WITH and WITHOUT the perspective-bias correction: RMS difference (px) between
  projecting points of the working volume with the estimated and with the true model
  (target <= 0.05 px), reprojection RMS, fx fy cx cy errors, and the detected circle centres
  against the true imaged centroids (true camera, true board pose), and the noise floor: the
  same solver on exact projections of this capture's board poses plus noise of the measured
  centre error (what the views allow, whatever the method);
* laser planes (with the estimated camera, and with the true camera to isolate the stage):
  angle between estimated and true normal (target <= 0.005 deg) and the largest distance
  between estimated and true plane over the working volume (target <= 0.005 mm);
* hand-eye (estimated camera; and true camera): RMS distance between points of the working
  volume carried by the estimated and by the true X (target <= 0.01 mm for the refined X),
  rotation and translation errors, for Chou-Kamel, OpenCV's five methods, the plain
  reprojection refinement and the refined X, side by side.

The working volume is a grid over the whole field of view at depths across the rig's working
range (paper: 115-185 mm as the issue states; compact: 80-125 mm around its 100 mm working
distance). Results go to benchmarks/results/calibration.json and .txt.

    python benchmarks/bench_calibration.py                       # paper + compact, quick
    python benchmarks/bench_calibration.py --capture data/raw/demo --capture /tmp/compact
    python benchmarks/bench_calibration.py --board asymmetric:7x13:2.5:1.5:light --keep /tmp/b

The camera rows also give the difference over the part of the volume that the scan window
sees ("window"), the coefficients the stage's model selection fixed at 0, and what the fit
predicts for itself; the circle centres also the factor between the detected shifts and the
predicted perspective bias (1: the bias model describes what the detector measures).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from crossline.board import Board  # noqa: E402
from crossline.calibrate.bias import centroid_offsets  # noqa: E402
from crossline.calibrate.camera import calibrate_camera, grid_pixels, run_calibrate_camera  # noqa: E402
from crossline.calibrate.detect import detect_board  # noqa: E402
from crossline.calibrate.handeye import HandEye, point_uncertainty, run_calibrate_handeye  # noqa: E402
from crossline.calibrate.lasers import run_calibrate_lasers  # noqa: E402
from crossline.camera import Camera  # noqa: E402
from crossline.geometry import (  # noqa: E402
    angle_between,
    matrix_to_rotvec,
    rotation_angle,
    transform_points,
)
from crossline.io.atomic import write_json  # noqa: E402
from crossline.io.images import read_image  # noqa: E402
from crossline.laser import LaserPlanes  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
DEPTHS = {"paper": (115.0, 185.0), "compact": (80.0, 125.0)}
NOISE_TRIALS = 24  # noise-only camera calibrations per capture
TARGETS = {"camera_px": 0.05, "laser_angle_deg": 0.005, "laser_dist_mm": 0.005, "handeye_mm": 0.01}


# ----------------------------------------------------------------------------- metrics


def volume_points(cam: Camera, depths: tuple[float, float], n: int = 21, nz: int = 8,
                  window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Camera-frame points (M, 3) seen by the true camera in ``window`` (default: its whole
    field of view) at ``nz`` depths."""
    xy = cam.undistort(grid_pixels(window or (0, 0, *cam.image_size), n))
    z = np.linspace(depths[0], depths[1], nz)
    return np.concatenate([np.column_stack([xy * zz, np.full(len(xy), zz)]) for zz in z])


def camera_metrics(est: Camera, true: Camera, depths,
                   window: tuple[int, int, int, int] | None = None) -> dict:
    """Projection difference over the working volume (and over the part of it that the scan
    window sees) and intrinsic errors."""
    P = volume_points(true, depths)
    d = est.project(P) - true.project(P)
    Pw = volume_points(true, depths, window=window) if window is not None else P
    dw = est.project(Pw) - true.project(Pw)
    unc = (est.extra.get("uncertainty") or {}).get("projection_rms_px", {})
    return {
        "projection_rms_px": float(np.sqrt(np.mean(np.sum(d**2, 1)))),
        "projection_max_px": float(np.max(np.linalg.norm(d, axis=1))),
        "window_rms_px": float(np.sqrt(np.mean(np.sum(dw**2, 1)))),
        "predicted_window_rms_px": unc.get("scan_window"),
        "distortion_fixed": sorted((est.extra.get("distortion_model") or {}).get("fixed", {})),
        "reprojection_rms_px": float(est.extra.get("rms_px", np.nan)),
        "fx_err_px": est.fx - true.fx, "fy_err_px": est.fy - true.fy,
        "cx_err_px": est.cx - true.cx, "cy_err_px": est.cy - true.cy,
        "dist_err": (est.dist - true.dist).tolist(),
        "bias_mean_shift_px": est.extra.get("bias_correction", {}).get("mean_shift_px"),
        "bias_iterations": est.extra.get("bias_correction", {}).get("iterations"),
        "views_used": est.extra.get("n_views_used"),
        "predicted_projection_rms_px": (est.extra.get("uncertainty") or {}).get("projection_rms_px",
                                                                                 {}).get("sensor"),
    }


def centre_metrics(capture: Path, truth: dict, true_cam: Camera, board: Board) -> dict:
    """Detected circle centres against the true imaged centroids (true camera, true pose)."""
    errs, offs = [], []
    for name, v in sorted(truth["calibration"]["camera"].items()):
        img = read_image(capture / "calibration" / "camera" / name)
        det = detect_board(img, board)
        if not det.found:
            continue
        T = np.array(v["T_cam_board"])
        P = board.object_points()
        off = centroid_offsets(true_cam, board, matrix_to_rotvec(T[:3, :3]), T[:3, 3])
        proj = true_cam.project(P @ T[:3, :3].T + T[:3, 3]) + off
        from crossline.calibrate.detect import board_symmetries

        # the true board frame may differ from the detection's labelling by a symmetry
        best = min(board_symmetries(board), key=lambda p: float(np.abs(det.points[p] - proj).mean()))
        errs.append(det.points[best] - proj)
        offs.append(off)
    e = np.concatenate(errs)
    o = np.concatenate(offs)
    return {
        "views": len(errs),
        # least-squares factor of the detected shifts (detected minus projected centre) over the
        # predicted perspective bias: 1 where the bias model describes what the detector measures
        "bias_slope": float(np.sum((e + o) * o) / np.sum(o * o)) if np.any(o) else float("nan"),
        "rms_px": float(np.sqrt(np.mean(np.sum(e**2, 1)))),
        "mean_px": e.mean(0).tolist(),
        "max_px": float(np.max(np.linalg.norm(e, axis=1))),
    }


def laser_metrics(est: LaserPlanes, truth: dict, true_cam: Camera, depths) -> dict:
    """Normal angle and largest plane distance over the working volume, per laser."""
    out = {}
    w, h = true_cam.image_size
    u, v = np.meshgrid(np.linspace(0, w - 1, 61), np.linspace(0, h - 1, 41))
    rays = true_cam.rays(np.column_stack([u.ravel(), v.ravel()]))
    for laser in ("A", "B"):
        n_t = np.array(truth["lasers"][laser]["normal"])
        d_t = float(truth["lasers"][laser]["d"])
        p = est[laser]
        n_e, d_e = p.normal, p.d
        if n_e @ n_t < 0:
            n_e, d_e = -n_e, -d_e
        # points of the true plane seen by the camera inside the working depths
        lam = -d_t / (rays @ n_t)
        pts = rays * lam[:, None]
        ok = (lam > 0) & (pts[:, 2] >= depths[0]) & (pts[:, 2] <= depths[1])
        dist = pts[ok] @ n_e + d_e
        out[laser] = {
            "angle_deg": float(np.degrees(angle_between(n_e, n_t))),
            "max_distance_mm": float(np.max(np.abs(dist))),
            "d_err_mm": d_e - d_t,
            "rms_mm": p.extra.get("rms_mm"),
            "points": p.extra.get("n_used"),
        }
    return out


def handeye_metrics(he: HandEye, truth: dict, true_cam: Camera, depths) -> dict:
    """Per method: volume RMS distance, rotation and translation error of X."""
    X_t = np.array(truth["T_tool_cam"])
    P = volume_points(true_cam, depths, n=11, nz=8)
    out = {}
    for name, m in he.extra["methods"].items():
        if "T_tool_cam" not in m:
            out[name] = {"error": m.get("error")}
            continue
        X = np.array(m["T_tool_cam"])
        d = transform_points(X, P) - transform_points(X_t, P)
        out[name] = {
            "volume_rms_mm": float(np.sqrt(np.mean(np.sum(d**2, 1)))),
            "volume_max_mm": float(np.max(np.linalg.norm(d, axis=1))),
            "rotation_err_deg": float(np.degrees(rotation_angle(X[:3, :3].T @ X_t[:3, :3]))),
            "translation_err_mm": float(np.linalg.norm(X[:3, 3] - X_t[:3, 3])),
            "board_consistency_mm": m.get("board_consistency_mm"),
        }
    unc = he.extra["methods"].get("refined", {}).get("uncertainty")
    if unc is not None:
        # what the stage's own covariance predicts for the same volume (1 sigma, RMS)
        sig = point_uncertainty(np.array(he.T_tool_cam), np.array(unc["covariance_X"]), P)
        out["refined"]["predicted_volume_rms_mm"] = float(np.sqrt(np.mean(sig**2)))
    out["pairs"] = {k: he.extra["pairs"][k] for k in ("total", "used", "rejected")}
    return out


# ----------------------------------------------------------------------------- runs


def board_poses(truth: dict) -> list[np.ndarray]:
    """True T_cam_board of every lasers-off board view the camera stage calibrates on."""
    cal = truth["calibration"]
    return [np.array(v["T_cam_board"]) for k in ("camera", "laser_A", "laser_B", "handeye")
            for _, v in sorted(cal.get(k, {}).items())]


def camera_noise_floor(truth: dict, true_cam: Camera, board: Board, centre_rms_px: float,
                       depths, trials: int = NOISE_TRIALS, seed: int = 0,
                       window: tuple[int, int, int, int] | None = None) -> dict:
    """The camera figure that the capture's own board poses allow, noise alone.

    The stage's solver (Zhang + bundle adjustment) on exact projections of every board view
    of this capture plus Gaussian noise of the measured centre error (per axis: RMS / sqrt 2):
    no bias, no detection, no model error. A measured figure near this one is limited by the
    views (their number and tilts), not by the method.
    """
    rng = np.random.default_rng(seed)
    P = board.object_points()
    exact = np.array([true_cam.project(P @ T[:3, :3].T + T[:3, 3]) for T in board_poses(truth)])
    sigma = centre_rms_px / np.sqrt(2.0)
    proj, win = [], []
    for _ in range(trials):
        fit = calibrate_camera(exact + rng.normal(0.0, sigma, exact.shape), board, true_cam.image_size,
                               bias_correction=False)
        m = camera_metrics(fit.camera, true_cam, depths, window)
        proj.append(m["projection_rms_px"])
        win.append(m["window_rms_px"])
    proj, win = np.array(proj), np.array(win)
    return {"views": len(exact), "sigma_px_per_axis": sigma, "trials": trials,
            "projection_rms_px": proj.tolist(), "median_px": float(np.median(proj)),
            "p90_px": float(np.percentile(proj, 90)),
            "window_median_px": float(np.median(win)), "window_p90_px": float(np.percentile(win, 90))}


def evaluate(capture: Path, work: Path, threads: int, camera_only: bool = False) -> dict:
    """Run the stages on one capture and score them against its truth."""
    from crossline.io.capture import open_capture

    truth = json.loads((capture / "truth.json").read_text())
    sw = open_capture(capture).rig.scan_window
    window = (sw.x, sw.y, sw.width, sw.height)
    preset = truth.get("preset", capture.name)
    depths = DEPTHS.get(preset, DEPTHS["paper"])
    true_cam = Camera(np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"]),
                      tuple(truth["camera"]["image_size"]))
    tb = truth["board"]
    board = Board(tb["pattern"], tb["cols"], tb["rows"], tb["spacing"], tb.get("diameter"),
                  tb.get("circles", "dark"))
    work.mkdir(parents=True, exist_ok=True)
    res: dict = {"capture": str(capture), "preset": preset, "quick": truth.get("quick"),
                 "working_depths_mm": depths, "scan_window": window, "board": board.to_dict(),
                 "timings_s": {}}
    t = time.perf_counter()
    res["centres"] = centre_metrics(capture, truth, true_cam, board)
    res["timings_s"]["centres"] = time.perf_counter() - t
    cams = {}
    for key, bc, model in (("with_bias_correction", True, "select"),
                           ("without_bias_correction", False, "select"),
                           ("all_coefficients_free", True, "full")):
        if model == "full" and not cams["with_bias_correction"].extra["distortion_model"]["fixed"]:
            continue  # the selection kept every coefficient: the same fit
        t = time.perf_counter()
        path = work / f"camera_{key}.json"
        cams[key] = run_calibrate_camera(capture, path, bias_correction=bc, threads=threads, distortion=model)
        res["timings_s"][f"camera_{key}"] = time.perf_counter() - t
        res.setdefault("camera", {})[key] = camera_metrics(cams[key], true_cam, depths, window)
    t = time.perf_counter()
    res["camera_noise_floor"] = camera_noise_floor(truth, true_cam, board, res["centres"]["rms_px"], depths,
                                                   window=window)
    res["timings_s"]["camera_noise_floor"] = time.perf_counter() - t
    if camera_only:
        return res
    true_json = work / "camera_true.json"
    true_cam.save(true_json)
    for label, cj in (("estimated_camera", work / "camera_with_bias_correction.json"),
                      ("true_camera", true_json)):
        t = time.perf_counter()
        lp = run_calibrate_lasers(capture, cj, work / f"lasers_{label}.json", threads=threads)
        res["timings_s"][f"lasers_{label}"] = time.perf_counter() - t
        res.setdefault("lasers", {})[label] = laser_metrics(lp, truth, true_cam, depths)
        t = time.perf_counter()
        he = run_calibrate_handeye(capture, cj, work / f"handeye_{label}.json", threads=threads)
        res["timings_s"][f"handeye_{label}"] = time.perf_counter() - t
        res.setdefault("handeye", {})[label] = handeye_metrics(he, truth, true_cam, depths)
    return res


def format_result(r: dict) -> str:
    """Human-readable table of one capture's figures."""
    ok = lambda v, lim: "ok" if v <= lim else "NOT MET"  # noqa: E731
    b = r.get("board") or {}
    sw = r.get("scan_window")
    L = [f"== {r['preset']} ({'quick' if r['quick'] else 'full'}) {r['capture']}",
         "   board: " + ":".join(str(b.get(k)) for k in ("pattern", "cols", "rows", "spacing", "diameter",
                                                         "circles")),
         f"   working volume: whole field of view, z = {r['working_depths_mm'][0]:g}-"
         f"{r['working_depths_mm'][1]:g} mm" + (f"; window: the part the scan window {sw[2]}x{sw[3]} at "
                                                 f"({sw[0]}, {sw[1]}) sees" if sw else ""),
         f"   circle centres vs true imaged centroids: RMS {r['centres']['rms_px']:.4f} px, "
         f"max {r['centres']['max_px']:.4f} px over {r['centres']['views']} views; detected shift / "
         f"predicted perspective bias {r['centres'].get('bias_slope', float('nan')):.4f}"]
    L.append("   camera                      proj RMS px  (max)     window px  reproj px  "
             "fx err   fy err   cx err   cy err   fixed")
    for key, c in r["camera"].items():
        L.append(f"   {key:<27} {c['projection_rms_px']:.4f} ({c['projection_max_px']:.4f})  "
                 f"{c.get('window_rms_px', float('nan')):.4f}     "
                 f"{c['reprojection_rms_px']:.4f}   {c['fx_err_px']:+.4f}  {c['fy_err_px']:+.4f}  "
                 f"{c['cx_err_px']:+.4f}  {c['cy_err_px']:+.4f}   "
                 f"{','.join(c.get('distortion_fixed', [])) or '-'}"
                 f"   [{ok(c['projection_rms_px'], TARGETS['camera_px'])} <= {TARGETS['camera_px']}]")
    for key, c in r["camera"].items():
        if c.get("predicted_projection_rms_px") is not None:
            L.append(f"   {key}: predicted by the fit itself (1 sigma RMS): "
                     f"{c['predicted_projection_rms_px']:.4f} px over the sensor, "
                     f"{c.get('predicted_window_rms_px') or float('nan'):.4f} px over "
                     "the scan window")
    nf = r["camera_noise_floor"]
    L.append(f"   noise floor: the stage's solver on exact projections of this capture's {nf['views']} "
             f"board poses + {nf['sigma_px_per_axis']:.4f} px noise per axis, {nf['trials']} trials: "
             f"proj RMS median {nf['median_px']:.4f} px, p90 {nf['p90_px']:.4f} px; window median "
             f"{nf.get('window_median_px', float('nan')):.4f} px, "
             f"p90 {nf.get('window_p90_px', float('nan')):.4f} px")
    if "lasers" not in r:
        L.append("   timings s: " + ", ".join(f"{k} {v:.1f}" for k, v in r["timings_s"].items()))
        return "\n".join(L)
    L.append("   laser planes                angle deg   max dist mm   d err mm    fit RMS mm  points")
    for label, lp in r["lasers"].items():
        for laser, m in lp.items():
            L.append(f"   {laser} ({label:<16})      {m['angle_deg']:.5f}     {m['max_distance_mm']:.5f}"
                     f"      {m['d_err_mm']:+.5f}   {m['rms_mm']:.5f}     {m['points']}   "
                     f"[{ok(m['angle_deg'], TARGETS['laser_angle_deg'])}, "
                     f"{ok(m['max_distance_mm'], TARGETS['laser_dist_mm'])}]")
    for label, he in r["handeye"].items():
        p = he["pairs"]
        L.append(f"   hand-eye ({label}; pairs used {p['used']}/{p['total']}, rejected {p['rejected']})")
        L.append("     method         volume RMS mm  max mm   rot err deg  trans err mm  "
                 "board consistency mm")
        for name, m in he.items():
            if name == "pairs":
                continue
            if "error" in m:
                L.append(f"     {name:<14} failed: {m['error']}")
                continue
            flag = (f"  [{ok(m['volume_rms_mm'], TARGETS['handeye_mm'])} <= {TARGETS['handeye_mm']}; "
                    f"1-sigma predicted by the noise: {m.get('predicted_volume_rms_mm', float('nan')):.5f}]"
                    if name == "refined" else "")
            L.append(f"     {name:<14} {m['volume_rms_mm']:.5f}        {m['volume_max_mm']:.5f}  "
                     f"{m['rotation_err_deg']:.5f}      {m['translation_err_mm']:.5f}       "
                     f"{m['board_consistency_mm']:.5f}{flag}")
    L.append("   timings s: " + ", ".join(f"{k} {v:.1f}" for k, v in r["timings_s"].items()))
    return "\n".join(L)


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, action="append",
                    help="capture folder with truth.json (repeatable); default: see above")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", type=Path, help="keep rendered captures and artefacts here")
    ap.add_argument("--board", action="append", metavar="SPEC",
                    help="instead: quick captures of the paper rig with this board (repeatable, "
                         "crossline simulate's --board), camera only")
    ap.add_argument("--camera-only", action="store_true",
                    help="score the camera stage only (results to calibration_boards.*)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    base = args.keep or Path(tempfile.mkdtemp(prefix="bench-calibration-"))
    captures = args.capture
    stem = "calibration"
    if args.board:
        from crossline.board import Board as _Board
        from crossline.sim import simulate

        stem, args.camera_only, captures = "calibration_boards", True, []
        for spec in args.board:
            out = base / f"paper-quick-{args.seed}-{spec.replace(':', '_')}"
            if not (out / "rig.yaml").is_file():
                simulate(out, preset="paper", seed=args.seed, quick=True, threads=args.threads,
                         progress=False, board=_Board.parse(spec))
            captures.append(out)
    if args.camera_only:
        stem = "calibration_boards"
    if not captures:
        from crossline.sim import simulate

        demo = ROOT / "data" / "raw" / "demo"
        captures = []
        for preset in ("paper", "compact"):
            if preset == "paper" and (demo / "truth.json").is_file():
                captures.append(demo)
                continue
            out = base / f"{preset}-quick-{args.seed}"
            if not (out / "rig.yaml").is_file():
                simulate(out, preset=preset, seed=args.seed, quick=True, threads=args.threads, progress=False)
            captures.append(out)
    results = []
    for cap in captures:
        r = evaluate(cap, base / f"artefacts-{cap.name}", args.threads, args.camera_only)
        results.append(r)
        print(format_result(r), flush=True)
    meta = {"load_average": os.getloadavg(), "cpus": os.cpu_count(), "targets": TARGETS}
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / f"{stem}.json", {"meta": meta, "results": results})
    (RESULTS / f"{stem}.txt").write_text("\n\n".join(format_result(r) for r in results) + "\n")
    if not args.keep:
        shutil.rmtree(base, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

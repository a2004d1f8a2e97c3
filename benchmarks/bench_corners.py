"""Chessboard corners against the virtual rig's truth: OpenCV's refiners and crossline's X-junction fit.

Renders a `--quick` capture of each rig with a chessboard instead of its circle grid
(``crossline simulate --board``; calibration views and one plate frame), then, for every
board view whose true pose truth.json holds (camera, laser-board and hand-eye views), compares
with the projected true corners (true camera, true pose):

* ``opencv_sb``: ``cv2.findChessboardCornersSB`` on the full image (EXHAUSTIVE | ACCURACY);
* ``opencv_subpix``: what crossline did before the X-junction fit: the corners found on the
  reduced image, then ``cv2.cornerSubPix`` at full size;
* ``xfit``: ``crossline.calibrate.corners`` (what ``detect_board`` returns now).

It prints RMS, mean, p99 and max of the 2-D error, split into the views whose edges run along
the pixel grid (fronto-parallel, not turned: camera views 0 and 1) and all others, the time
per view of each refiner, and then the camera calibrated (the stage's solver, every view) from
each set of corners: its projection error over the working volume against the true camera,
beside the error the fit predicts for itself. Results go to benchmarks/results/corners.json
and .txt.

    python benchmarks/bench_corners.py                    # paper and compact rigs
    python benchmarks/bench_corners.py --presets paper --keep /tmp/corners
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

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench_calibration import DEPTHS, volume_points  # noqa: E402

from crossline.board import Board  # noqa: E402
from crossline.calibrate.camera import solve_views, uncertainty_summary  # noqa: E402
from crossline.calibrate.detect import (  # noqa: E402
    Detection,
    board_symmetries,
    detect_board,
    subpix_corners,
    to_uint8,
)
from crossline.camera import Camera  # noqa: E402
from crossline.io.atomic import write_json  # noqa: E402
from crossline.io.images import read_image  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
BOARDS = {"paper": "chessboard:12x9:4", "compact": "chessboard:11x10:2.5"}
ALIGNED = {"calibration/camera/view_00.png", "calibration/camera/view_01.png"}
METHODS = ("opencv_sb", "opencv_subpix", "xfit")


def _views(truth: dict) -> list[tuple[str, np.ndarray]]:
    """(image path in the capture, true T_cam_board) of every board view with a true pose."""
    out = []
    cal = truth["calibration"]
    for name, v in sorted(cal["camera"].items()):
        out.append((f"calibration/camera/{name}", np.array(v["T_cam_board"])))
    for laser in ("laser_A", "laser_B"):
        for pose, v in sorted(cal.get(laser, {}).items()):
            out.append((f"calibration/{laser}/{pose}_board.png", np.array(v["T_cam_board"])))
    for name, v in sorted(cal.get("handeye", {}).items()):
        if "T_cam_board" in v:
            out.append((f"calibration/handeye/{name}", np.array(v["T_cam_board"])))
    return out


def _stats(e: np.ndarray) -> dict:
    n = np.linalg.norm(e, axis=1)
    return {"n": len(e), "rms_px": float(np.sqrt(np.mean(n**2))), "mean_px": e.mean(0).tolist(),
            "p99_px": float(np.percentile(n, 99)), "max_px": float(n.max())}


def evaluate(capture: Path, preset: str) -> dict:
    """Corner errors of the three refiners on every view, and the cameras they calibrate."""
    truth = json.loads((capture / "truth.json").read_text())
    c = truth["camera"]
    true_cam = Camera(np.array(c["K"]), np.array(c["dist"]), tuple(c["image_size"]))
    board = Board.parse(BOARDS[preset])
    P = board.object_points()
    errs = {m: {"aligned": [], "other": []} for m in METHODS}
    times = {m: [] for m in METHODS}
    names, dets = [], {m: [] for m in METHODS}
    for rel, T in _views(truth):
        img = read_image(capture / rel)
        proj = true_cam.project(P @ T[:3, :3].T + T[:3, 3])
        img8 = to_uint8(img)
        t0 = time.perf_counter()
        ok, sb = cv2.findChessboardCornersSB(img8, board.pattern_size,
                                             flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        t1 = time.perf_counter()
        crude = detect_board(img, board, refine=False)
        sub = subpix_corners(img8, crude.points, board)  # what crossline did before the fit
        t3 = time.perf_counter()
        ours = detect_board(img, board)
        t4 = time.perf_counter()
        if not (ok and crude.found and ours.found):
            continue
        pts = {"opencv_sb": sb.reshape(-1, 2).astype(np.float64), "opencv_subpix": sub, "xfit": ours.points}
        times["opencv_sb"].append(t1 - t0)
        times["opencv_subpix"].append(t3 - t1)  # detection on the reduced image + cornerSubPix
        times["xfit"].append(t4 - t3)  # the same detection + cornerSubPix + the X-junction fit
        names.append(rel)
        group = "aligned" if rel in ALIGNED else "other"
        for m, p in pts.items():
            best = min(board_symmetries(board), key=lambda perm: float(np.abs(p[perm] - proj).mean()))
            errs[m][group].append(p[best] - proj)
            dets[m].append(Detection(p))
    result: dict = {"capture": str(capture), "preset": preset, "board": BOARDS[preset], "views": len(names),
                    "corners": {}, "time_per_view_s": {}, "camera": {}}
    for m in METHODS:
        result["corners"][m] = {g: _stats(np.concatenate(v)) for g, v in errs[m].items() if v}
        result["corners"][m]["all"] = _stats(np.concatenate(errs[m]["aligned"] + errs[m]["other"]))
        result["time_per_view_s"][m] = float(np.median(times[m]))
    # the camera from each set of corners: the stage's solver, every view, no bias correction
    w, h = true_cam.image_size
    Q = volume_points(true_cam, DEPTHS[preset])
    for m in METHODS:
        fit, used, _ = solve_views(names, dets[m], board, (w, h))
        d = fit.camera.project(Q) - true_cam.project(Q)
        unc = uncertainty_summary(fit, {"sensor": (0, 0, w, h)})
        result["camera"][m] = {"projection_rms_px": float(np.sqrt(np.mean(np.sum(d**2, 1)))),
                               "predicted_rms_px": unc["projection_rms_px"]["sensor"],
                               "reprojection_rms_px": fit.rms_px, "views_used": len(used)}
    return result


def format_result(r: dict) -> str:
    """The printed table of one capture."""
    L = [f"== {r['preset']} rig, {r['board']} ({r['capture']}), {r['views']} views with a true pose"]
    L.append("   corners vs true projected corners   RMS px   mean (u, v) px        p99 px   max px   "
             "[aligned views | other views]")
    for m in METHODS:
        c = r["corners"][m]
        a, o = c.get("aligned"), c.get("other")
        L.append(f"   {m:<14} all {c['all']['rms_px']:.4f}   ({c['all']['mean_px'][0]:+.4f}, "
                 f"{c['all']['mean_px'][1]:+.4f})   {c['all']['p99_px']:.4f}   {c['all']['max_px']:.4f}   "
                 f"[{a['rms_px'] if a else float('nan'):.4f} | {o['rms_px'] if o else float('nan'):.4f}]")
    L.append("   time per view s: " + ", ".join(f"{m} {t:.2f}" for m, t in r["time_per_view_s"].items())
             + "  (opencv_subpix: detection + cornerSubPix; xfit: the same + the fit)")
    L.append("   camera from these corners (every view)   projection RMS px vs truth   predicted 1 sigma   "
             "reprojection px")
    for m in METHODS:
        c = r["camera"][m]
        L.append(f"   {m:<14} {c['projection_rms_px']:.4f}                        {c['predicted_rms_px']:.4f}"
                 f"              {c['reprojection_rms_px']:.4f}   ({c['views_used']} views)")
    return "\n".join(L)


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["paper", "compact"], choices=sorted(BOARDS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--keep", type=Path, help="keep the rendered captures here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    cv2.setNumThreads(1)
    from crossline.sim import simulate

    base = args.keep or Path(tempfile.mkdtemp(prefix="bench-corners-"))
    results = []
    for preset in args.presets:
        out = base / f"{preset}-chessboard-{args.seed}"
        if not (out / "rig.yaml").is_file():
            simulate(out, preset=preset, seed=args.seed, quick=True, scans=["plate"], frames=1,
                     board=Board.parse(BOARDS[preset]), threads=args.threads, progress=False, force=True)
        r = evaluate(out, preset)
        results.append(r)
        print(format_result(r), flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"load_average": os.getloadavg(), "cpus": os.cpu_count()}
    write_json(RESULTS / "corners.json", {"meta": meta, "results": results})
    (RESULTS / "corners.txt").write_text("\n\n".join(format_result(r) for r in results) + "\n")
    if not args.keep:
        shutil.rmtree(base, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

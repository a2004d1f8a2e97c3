"""What JPEG frames cost: plane angle and point sigma on the virtual rig, PNG against JPEG 90 and 75.

Renders the same rig and seed once per image format (``crossline simulate --image-format``):
PNG (lossless, 8-bit: the reference), JPEG quality 90 and JPEG quality 75. The simulator
draws the same scene, noise and quantisation for every format, so the captures differ only
by the compression. Captures (``--quick``, the plate scan only, no hand-eye views):

* ``paper``: the paper rig, grey sensor, seed 0;
* ``paper-colour-red``: the same rig with a colour (Bayer) sensor and red lasers (the
  pipeline reads the red channel; JPEG also subsamples the chroma), seed 0;
* ``random-small-1``: a drawn rig (``--preset random-small --seed 1``, 8-bit).

For each capture, through the CLI as the workflow runs it (one process at a time, 1 thread):

* ``calibrate-camera``; against truth.json: RMS difference between projecting points of the
  working volume with the estimated and with the true model (whole sensor and scan window),
  and the reprojection RMS;
* ``calibrate-lasers`` with that camera (the chain) and with the TRUE camera (the laser stage
  alone); against truth: each plane's angle to the true plane (deg), its offset d - d_true and
  the largest distance between the planes over the working volume (µm), and the fit's RMS
  (scatter of the stripe points about the fitted plane, µm);
* ``extract-stripes`` + ``triangulate`` of the plate scan with the TRUE calibration
  (``crossline.sim.write_true_calibration``), points carried to the base frame with the TRUE
  arm poses: mean and sigma (standard deviation; and robust, 1.4826 MAD) of the points'
  distances to the true plate, with the workflow's 7-column smoothing and without it. So the
  point figures hold JPEG's cost on the stripe centres alone, not on the calibration.

Printed: one table per capture, the PNG figures and the ratios q90/PNG and q75/PNG (of
absolute values; signed figures that sit near zero, d - d_true and the plate's mean, as
differences JPEG minus PNG). A single seed's calibration errors are of the size of its noise:
their ratios move by chance; the scatter figures (reprojection RMS, fit RMS, sigma) are the
stable ones. A stage that refuses a capture is a result: the table says FAILED and why.
Results: benchmarks/results/jpeg.txt and .json.

By default the code measured is the repository's HEAD commit (exported with ``git archive``
under benchmarks/.cache/jpeg/, so uncommitted edits do not leak into the figures); ``--code
worktree`` measures the working tree.

    python benchmarks/bench_jpeg.py                          # ~10 min on 1 core
    python benchmarks/bench_jpeg.py --captures paper --code worktree
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
CACHE = HERE / ".cache" / "jpeg"
RESULTS = HERE / "results"
SCAN = "plate"

CAPTURES: dict[str, list[str]] = {
    "paper": ["--preset", "paper", "--seed", "0"],
    "paper-colour-red": ["--preset", "paper", "--seed", "0", "--colour", "red"],
    "random-small-1": ["--preset", "random-small", "--seed", "1"],
}
FORMATS: dict[str, list[str]] = {
    "png": ["--image-format", "png", "--bit-depth", "8"],
    "q90": ["--image-format", "jpeg", "--jpeg-quality", "90"],
    "q75": ["--image-format", "jpeg", "--jpeg-quality", "75"],
}


def _git(*args: str) -> str:
    out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 else "?"


def code_dir(which: str) -> tuple[Path, str]:
    """The folder holding the ``crossline`` package to measure, and its version label."""
    if which == "worktree":
        return ROOT, _git("describe", "--always", "--dirty")
    commit = _git("rev-parse", "--short", which)
    if commit == "?":
        raise SystemExit(f"--code {which}: not a commit of {ROOT}")
    dest = CACHE / f"code-{commit}"
    if not (dest / "crossline" / "__init__.py").is_file():
        tmp = dest.with_name(dest.name + f".partial-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        tar = subprocess.run(["git", "archive", commit, "crossline"], cwd=ROOT, capture_output=True,
                             check=True).stdout
        tar_path = tmp / "code.tar"
        tar_path.write_bytes(tar)
        with tarfile.open(tar_path) as tf:
            tf.extractall(tmp, filter="data")
        tar_path.unlink()
        shutil.rmtree(dest, ignore_errors=True)
        os.rename(tmp, dest)
    return dest, commit


def _error_message(stderr: str) -> str:
    """The CLI's named error in one line: its first line (less the capture's folder), the
    lines under it, and the first of their itemised reasons."""
    lines = stderr.splitlines()
    at = [i for i, x in enumerate(lines) if ": error:" in x]
    if not at:
        return lines[-1].strip() if lines else ""
    first = lines[at[-1]].split(": error:", 1)[1].strip()
    first = first.replace(str(CACHE / "captures") + "/", "")
    rest = [x.strip() for x in lines[at[-1] + 1:] if x.strip()]
    items = [x for x in rest if x.startswith("- ")]
    return " ".join([first, *[x for x in rest if not x.startswith("- ")], *items[:1]])


class StageError(RuntimeError):
    """A stage refused the capture: its error message is a result, not a crash."""


class Cli:
    """``crossline <command>`` of the measured code, in a child process, timed."""

    def __init__(self, code: Path):
        self.env = dict(os.environ, PYTHONPATH=str(code) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        self.times: dict[str, float] = {}

    def __call__(self, tag: str, *args: str) -> None:
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "crossline.cli", *map(str, args)], env=self.env,
                           capture_output=True, text=True)
        self.times[tag] = self.times.get(tag, 0.0) + time.perf_counter() - t
        if r.returncode:
            raise StageError(_error_message(r.stderr) or f"exit {r.returncode}", r.stderr[-3000:])


def render(cli: Cli, name: str, fmt: str) -> Path:
    """The quick capture of ``name`` in format ``fmt``: camera and laser views, the plate scan."""
    out = CACHE / "captures" / f"{name}-{fmt}"
    if (out / "truth.json").is_file():
        return out
    shutil.rmtree(out, ignore_errors=True)
    cli("render", "simulate", out, *CAPTURES[name], *FORMATS[fmt], "--quick", "--parts",
        "camera,lasers,scans", "--scans", SCAN, "--threads", "1", "--force")
    return out


def plate_figures(capture: Path, points_path: Path, T_tool_cam: np.ndarray) -> dict:
    """Distances of the points (TRUE calibration) to the true plate, with the TRUE arm poses."""
    import pandas as pd

    from crossline.geometry import transform_from_pose
    from crossline.robust import robust_sigma
    from crossline.scan.triangulate import to_base

    truth = json.loads((capture / "truth.json").read_text())
    plane = np.array(truth["scans"][SCAN]["plane_base"])
    n, d = plane[:3] / np.linalg.norm(plane[:3]), plane[3] / np.linalg.norm(plane[:3])
    p = pd.read_parquet(points_path)
    tp = pd.read_parquet(capture / truth["scans"][SCAN]["poses"]).set_index("frame")
    sel = tp.loc[p["frame"].to_numpy()]
    T = transform_from_pose(sel[["x", "y", "z"]].to_numpy(), sel[["qw", "qx", "qy", "qz"]].to_numpy())
    r = to_base(p[["x_cam", "y_cam", "z_cam"]].to_numpy(), T, T_tool_cam) @ n + d
    rep = p[["x", "y", "z"]].to_numpy() @ n + d  # with the reported (noisy) arm poses

    def stats(x: np.ndarray) -> dict:
        return {"n": len(x), "mean_um": 1e3 * float(np.mean(x)), "sigma_um": 1e3 * float(np.std(x)),
                "robust_sigma_um": 1e3 * robust_sigma(x)}

    lasers = p["laser"].to_numpy()
    return {"true_poses": stats(r), "reported_poses": stats(rep),
            "per_laser": {k: stats(r[lasers == k]) for k in sorted(set(lasers))}}


def measure(cli: Cli, name: str, fmt: str, work: Path) -> dict:
    """Every figure of one capture in one format."""
    from bench_calibration import DEPTHS, camera_metrics, laser_metrics

    from crossline.camera import Camera
    from crossline.io.capture import open_capture
    from crossline.laser import LaserPlanes
    from crossline.report.metrics import plane_depth_range
    from crossline.sim import write_true_calibration

    cap = render(cli, name, fmt)
    shutil.rmtree(work, ignore_errors=True)  # every stage runs afresh
    work.mkdir(parents=True)
    truth = json.loads((cap / "truth.json").read_text())
    rig = open_capture(cap).rig
    sw = rig.scan_window
    window = (sw.x, sw.y, sw.width, sw.height)
    true_cam = Camera(np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"]),
                      (rig.sensor.width, rig.sensor.height))
    planes = [(np.array(v["normal"]), float(v["d"])) for v in truth["lasers"].values()]
    depths = DEPTHS.get(truth.get("preset")) or plane_depth_range(true_cam, planes, region=window)
    tcam, tlas, the = write_true_calibration(cap, work / "true")
    frames = sorted((cap / "scans" / SCAN / "frames").iterdir())
    res: dict = {"capture": name, "frames": len(frames), "format": fmt, "folder": str(cap.relative_to(ROOT)),
                 "depths_mm": list(depths), "scan_window": list(window),
                 "frame_kb": float(np.mean([f.stat().st_size for f in frames]) / 1024),
                 "channel": rig.sensor.channel}

    res["failed"] = {}  # stage -> its error message (a result: what JPEG did to the stage)
    res["lasers"] = {}
    try:
        cli("calibrate-camera", "calibrate-camera", cap, "--out", work / "camera.json", "--threads", "1")
        res["camera"] = camera_metrics(Camera.load(work / "camera.json"), true_cam, depths, window)
        cams = (("estimated_camera", work / "camera.json"), ("true_camera", tcam))
    except StageError as exc:
        res["failed"]["calibrate-camera"] = exc.args[0]
        cams = (("true_camera", tcam),)
    for label, cj in cams:
        out = work / f"lasers_{label}.json"
        try:
            cli("calibrate-lasers", "calibrate-lasers", cap, "--camera", cj, "--out", out, "--threads", "1")
        except StageError as exc:
            res["failed"][f"calibrate-lasers ({label.replace('_', ' ')})"] = exc.args[0]
            continue
        lp = LaserPlanes.load(out)
        res["lasers"][label] = laser_metrics(lp, truth, true_cam, depths)
        for k, m in res["lasers"][label].items():
            m["poses_used"] = len(lp[k].extra.get("poses") or [])
            m["poses_skipped"] = len(lp[k].extra.get("skipped_poses") or [])

    stripes = work / "stripes.parquet"
    cli("extract-stripes", "extract-stripes", cap, SCAN, "--out", stripes, "--threads", "1")
    res["plate"] = {}
    for label, smooth in (("smoothed", "7"), ("unsmoothed", "1")):
        pts = work / f"points_{label}.parquet"
        cli("triangulate", "triangulate", cap, SCAN, "--stripes", stripes, "--camera", tcam, "--lasers",
            tlas, "--handeye", the, "--out", pts, "--smooth-px", smooth)
        res["plate"][label] = plate_figures(cap, pts, np.array(truth["T_tool_cam"]))
    return res


# one row of a capture's table: label, getter, number format, and whether the JPEG columns
# compare by ratio (magnitudes) or by difference (signed figures that may sit near zero)
RATIO, DIFF = "ratio", "diff"


def _rows(lasers: list[str]) -> list[tuple[str, object, str, str]]:
    rows: list[tuple[str, object, str, str]] = [
        ("frame file size, KB (mean of scan frames)", lambda r: r["frame_kb"], "{:.0f}", RATIO),
        ("camera: projection vs true, sensor RMS px", lambda r: r["camera"]["projection_rms_px"], "{:.4f}",
         RATIO),
        ("camera: projection vs true, window RMS px", lambda r: r["camera"]["window_rms_px"], "{:.4f}",
         RATIO),
        ("camera: reprojection RMS px", lambda r: r["camera"]["reprojection_rms_px"], "{:.4f}", RATIO),
    ]
    for label, tag in (("estimated_camera", "est. camera"), ("true_camera", "true camera")):
        for k in lasers:
            g = lambda r, k=k, label=label: r["lasers"][label][k]  # noqa: E731
            rows += [
                (f"laser {k} ({tag}): angle to true, deg", lambda r, g=g: g(r)["angle_deg"], "{:.5f}", RATIO),
                (f"laser {k} ({tag}): d - d_true, um", lambda r, g=g: 1e3 * g(r)["d_err_mm"], "{:+.2f}",
                 DIFF),
                (f"laser {k} ({tag}): max dist over volume, um",
                 lambda r, g=g: 1e3 * g(r)["max_distance_mm"], "{:.2f}", RATIO),
                (f"laser {k} ({tag}): fit RMS, um", lambda r, g=g: 1e3 * g(r)["rms_mm"], "{:.2f}", RATIO),
                (f"laser {k} ({tag}): points used", lambda r, g=g: g(r)["points"], "{:.0f}", RATIO),
            ]
    for label, tag in (("smoothed", "smoothed 7 px"), ("unsmoothed", "unsmoothed")):
        g = lambda r, label=label: r["plate"][label]["true_poses"]  # noqa: E731
        rows += [
            (f"plate ({tag}): points", lambda r, g=g: g(r)["n"], "{:.0f}", RATIO),
            (f"plate ({tag}): mean distance, um", lambda r, g=g: g(r)["mean_um"], "{:+.2f}", DIFF),
            (f"plate ({tag}): sigma, um", lambda r, g=g: g(r)["sigma_um"], "{:.2f}", RATIO),
            (f"plate ({tag}): robust sigma, um", lambda r, g=g: g(r)["robust_sigma_um"], "{:.2f}", RATIO),
        ]
    return rows


def _get(get, r: dict | None) -> float | None:
    try:
        return None if r is None else float(get(r))
    except (KeyError, TypeError):
        return None  # the stage failed on this capture (said below the table)


def table(name: str, by_fmt: dict[str, dict]) -> list[str]:
    png = by_fmt["png"]
    lasers = sorted({k for r in by_fmt.values() for lab in r["lasers"].values() for k in lab})
    w = 46
    head = f"  {'figure':<{w}} {'PNG':>9} {'JPEG 90':>9} {'JPEG 75':>9} {'q90/PNG':>8} {'q75/PNG':>8}"
    chan = png["channel"] or "grey"
    L = [f"== {name} (simulate {' '.join(CAPTURES[name])} --quick): plate scan of {png['frames']} "
         f"frames, channel {chan}; working volume z = {png['depths_mm'][0]:.0f}-{png['depths_mm'][1]:.0f} mm",
         head]
    for label, get, fmt, kind in _rows(lasers):
        vals = [_get(get, by_fmt.get(f)) for f in FORMATS]
        cells = [fmt.format(v) if v is not None else "failed" for v in vals]
        cmp = []
        for v in vals[1:]:
            if v is None or vals[0] is None:
                cmp.append("-")
            elif kind == DIFF:
                cmp.append(f"d{v - vals[0]:+.2f}")
            else:
                cmp.append(f"{abs(v) / abs(vals[0]):.2f}" if vals[0] else "-")
        L.append(f"  {label:<{w}} {cells[0]:>9} {cells[1]:>9} {cells[2]:>9} {cmp[0]:>8} {cmp[1]:>8}")
    for f, r in by_fmt.items():
        for stage, msg in r.get("failed", {}).items():
            L.append(f"  {f}: {stage} FAILED: {msg}")
    return L



def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--captures", default=",".join(CAPTURES), help="among " + ", ".join(CAPTURES))
    ap.add_argument("--code", default="HEAD", help="commit whose crossline/ to measure (default HEAD), "
                    "or 'worktree'")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    code, version = code_dir(a.code)
    # the measured package first, then this folder for bench_calibration's metrics
    sys.path[:0] = [str(code), str(HERE)]
    import crossline

    assert Path(crossline.__file__).resolve().is_relative_to(code.resolve()), crossline.__file__
    from run_all import machine

    cli = Cli(code)
    names = [n for n in a.captures.split(",") if n]
    results: dict[str, dict[str, dict]] = {}
    lines = [
        "JPEG's cost against lossless PNG on the virtual rig: the same rig, seed, scene and sensor",
        "noise rendered as 8-bit PNG, JPEG quality 90 and JPEG quality 75 (crossline simulate",
        "--quick --image-format ...; camera and laser-plane views, the plate scan).",
        "Camera and laser planes: calibrate-camera, then calibrate-lasers with that camera (est.) and",
        "with the true camera (the laser stage alone), against truth.json. Plate: extract-stripes",
        "(gaussian) + triangulate with the TRUE calibration and TRUE arm poses, distances of the",
        "points to the true plate (JPEG's cost on the stripe centres alone). q90/PNG, q75/PNG: ratios",
        "of absolute values; dX: JPEG minus PNG (signed figures near zero). One seed's calibration",
        "errors are noise-sized and their ratios move by chance; the scatter rows (reprojection RMS,",
        "fit RMS, sigma) are the stable ones. A stage that refuses a capture is a result: FAILED.",
    ]
    for line in lines:
        print(line, flush=True)
    for name in names:
        results[name] = {}
        for fmt in FORMATS:
            t = time.perf_counter()
            results[name][fmt] = measure(cli, name, fmt, CACHE / "work" / f"{name}-{fmt}")
            print(f"  [{name} {fmt}: {time.perf_counter() - t:.0f} s]", flush=True)
        block = table(name, results[name])
        print("\n".join(block), flush=True)
        lines += ["", *block]
    wall = time.perf_counter() - t0
    tail = ["", f"code: crossline/ of {version}; wall {wall:.0f} s, 1 process at a time, 1 thread; "
            "stage times (s): " + ", ".join(f"{k} {v:.0f}" for k, v in cli.times.items()),
            f"machine: {machine()} (shared with other jobs)"]
    print("\n".join(tail))
    lines += tail
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "jpeg.txt").write_text("\n".join(lines) + "\n")
    (RESULTS / "jpeg.json").write_text(json.dumps(
        {"code": version, "machine": machine(), "wall_s": wall, "stage_s": cli.times,
         "formats": {k: " ".join(v) for k, v in FORMATS.items()},
         "captures": {k: " ".join(v) for k, v in CAPTURES.items() if k in names}, "results": results},
        indent=1, default=float) + "\n")
    print(f"wrote {RESULTS / 'jpeg.txt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

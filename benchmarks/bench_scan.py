"""Scan stages: accuracy against the simulator's truth, speed, and memory.

    python benchmarks/bench_scan.py                 # paper + compact presets, 300-frame plate scans
    python benchmarks/bench_scan.py --frames 120 --presets paper --mem-frames 300,1000

Prints the figures and writes benchmarks/results/scan.json and scan.txt. For each preset it
renders (once, cached under benchmarks/.cache/) a capture with the plate scan, then

- centre error of each extractor against the true centreline (truth/<scan>_centrelines.parquet),
  RMS and 99th percentile, away from the crossing and in the crossing band (a centre whose
  column has the other laser's true stripe within CROSSING_PX px in that frame);
- labels: AB-frame centres given the wrong laser, dropped centres by reason, as counts and
  rates; points per frame against a single-line rig on the same scan (the paper: 1.33x);
- with the TRUE calibration (truth.json), RMS distance of the triangulated points to the true
  plate, with the reported arm poses and with the true ones (the latter isolates extraction);
- speeds (medians of several runs): PNG decoding alone (OpenCV, the fast decoder), the
  grey-centre kernel (numba, numpy), Steger, a naive per-column Python loop, and the scan
  stages end to end (PNG on disk -> points) with 2 threads;
- peak memory (RSS) of the scan stages on long scans made by cycling the frames, to show it
  does not grow with the number of frames.

If the simulator cannot render (it is being written), synthetic 2658x800 frames of two crossed
Gaussian stripes stand in for speed and memory, and accuracy is skipped (said in the output).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from crossline.camera import Camera  # noqa: E402
from crossline.io.capture import open_capture  # noqa: E402
from crossline.laser import LaserPlanes  # noqa: E402
from crossline.report.scan_truth import stripe_spacing_mm  # noqa: E402
from crossline.scan.centreline import half_amplitude_columns  # noqa: E402
from crossline.scan.frames import decode_png, fast_decoder_available  # noqa: E402
from crossline.scan.stripes import EXTRACTORS, gaussian, grey_centre, run_extract_stripes, steger  # noqa: E402
from crossline.scan.triangulate import run_triangulate, to_base  # noqa: E402

CACHE = REPO / "benchmarks" / ".cache"
RESULTS = REPO / "benchmarks" / "results"
CROSSING_PX = 15.0
SCAN = "plate"
SMOOTH_WINDOWS = (5, 7, 9)
# the workflow's default smoothing window along the stripe (config.yaml points.smooth_px)
SMOOTH_DEFAULT = int(yaml.safe_load((REPO / "config.yaml").read_text())["points"]["smooth_px"])
BUDGET_FRAMES = 6  # per laser, for the error budget
PATTERNS = (("A", "B", "AB"), ("A", "B", "AB", "AB"), ("A", "B", "AB", "AB", "AB", "AB"))


# ----------------------------------------------------------------------------- data


def render(preset: str, frames: int, pattern: list[str] | None = None) -> Path | None:
    """A capture of ``preset`` with its plate scan of ``frames`` frames (cached), or None."""
    tag = "" if pattern is None else "-" + "-".join(pattern)
    out = CACHE / f"{preset}-{SCAN}-{frames}{tag}"
    if (out / "rig.yaml").is_file() and (out / "truth.json").is_file():
        return out
    try:
        from crossline.sim import simulate

        shutil.rmtree(out, ignore_errors=True)
        simulate(out, preset=preset, frames=frames, scans=[SCAN], force=True, threads=2,
                 progress=False, pattern=pattern)
        return out
    except Exception as exc:  # the simulator is optional here: say why and go on
        print(f"  [{preset}] simulator unavailable: {type(exc).__name__}: {exc}")
        shutil.rmtree(out, ignore_errors=True)
        return None


def synthetic_capture(frames: int, seed: int = 0) -> Path:
    """A 2658x800 capture of two crossed Gaussian stripes moving frame to frame (no truth)."""
    from crossline.io.atomic import write_json
    from crossline.io.images import write_png

    out = CACHE / f"synthetic-{frames}"
    if (out / "rig.yaml").is_file():
        return out
    shutil.rmtree(out, ignore_errors=True)
    rng = np.random.default_rng(seed)
    W, H = 2658, 800
    rig = {"format": "crossline-capture/1", "sensor": {"width": 3072, "height": 2048, "bit_depth": 8},
           "scan_window": {"x": 207, "y": 624, "width": W, "height": H}, "frame_rate": 80,
           "board": {"pattern": "symmetric", "cols": 15, "rows": 11, "spacing": 3.75,
                     "diameter": 1.875, "circles": "dark"},
           "scans": {SCAN: {"artefact": "plane"}}}
    out.mkdir(parents=True)
    (out / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    z = np.zeros((4, 4), np.uint8)
    for sub, names in (("camera", ["v.png"]), ("laser_A", ["a_board.png", "a_laser.png", "b_board.png",
                                                          "b_laser.png"]),
                       ("laser_B", ["a_board.png", "a_laser.png", "b_board.png", "b_laser.png"]),
                       ("handeye", ["p.png"])):
        for n in names:
            write_png(out / "calibration" / sub / n, z)
    (out / "calibration" / "handeye" / "poses.csv").write_text(
        "image,x,y,z,qw,qx,qy,qz\np.png,0,0,0,1,0,0,0\n")
    fdir = out / "scans" / SCAN / "frames"
    fdir.mkdir(parents=True)
    u = np.arange(W, dtype=float)[None, :]
    v = np.arange(H, dtype=float)[:, None]
    rows = ["frame,time_s,lasers,x,y,z,qw,qx,qy,qz"]
    for k in range(frames):
        st = ("A", "B", "AB")[k % 3]
        img = np.full((H, W), 6.0)
        for laser, slope in (("A", 0.28), ("B", -0.26)):
            if laser in st:
                c = 400 + 0.5 * k + slope * (u - W / 2) + 3 * np.sin(u / 300 + k / 20)
                img += 170 * np.exp(-0.5 * ((v - c) / (1.6 * np.sqrt(1 + slope**2))) ** 2)
        img += rng.normal(0, 1, img.shape) * np.sqrt(img * 0.3 + 1)
        write_png(fdir / f"{k:06d}.png", np.clip(np.round(img), 0, 255).astype(np.uint8))
        rows.append(f"{k},{k / 80:.6f},{st},0,{0.1 * k:.4f},150,1,0,0,0")
    (out / "scans" / SCAN / "frames.csv").write_text("\n".join(rows) + "\n")
    cam = Camera(np.array([[5000.0, 0, 1536], [0, 5000.0, 1024], [0, 0, 1]]),
                 np.array([-0.05, 0.1, 0, 0, 0]), (3072, 2048))
    cal = out / "cal"
    cam.save(cal / "camera.json")
    LaserPlanes.from_dict({"A": {"normal": [0, 0.8, -0.6], "d": 90.0},
                           "B": {"normal": [0.8, 0, -0.6], "d": 90.0}}).save(cal / "lasers.json")
    write_json(cal / "handeye.json", {"T_tool_cam": np.eye(4).tolist()})
    return out


def true_calibration(capture: Path, dest: Path) -> tuple[Path, Path, Path]:
    """camera.json, lasers.json, handeye.json written from truth.json (benchmarks only)."""
    if (capture / "cal" / "camera.json").is_file():  # synthetic stand-in
        c = capture / "cal"
        return c / "camera.json", c / "lasers.json", c / "handeye.json"
    from crossline.sim import write_true_calibration

    return write_true_calibration(capture, dest)


# ----------------------------------------------------------------------------- accuracy


def truth_table(capture: Path) -> tuple[dict, pd.DataFrame]:
    truth = json.loads((capture / "truth.json").read_text())
    t = pd.read_parquet(capture / truth["scans"][SCAN]["centrelines"])
    t = t[t["visible"]] if "visible" in t else t
    return truth, t[["frame", "laser", "u", "v"]]


def score_centres(stripes: pd.DataFrame, tl: pd.DataFrame) -> dict:
    """Centre error vs the true centreline, away from and in the crossing band."""
    # the true row of each lit laser at the centre's column
    s = stripes[["frame", "lasers", "u", "v", "flags"]].copy()
    # the truth is sampled at integer columns; Steger's centres sit at fractional columns, so
    # the true row is interpolated linearly between the two columns around each centre
    s["u0"] = np.floor(s["u"]).astype(np.int64)
    s["u1"] = s["u0"] + 1
    frac = (s["u"] - s["u0"]).to_numpy()
    piv = tl.groupby(["frame", "u", "laser"])["v"].first().unstack("laser")
    piv = piv.reindex(columns=["A", "B"])
    slopes = true_slopes(tl)
    m0 = s.join(piv, on=["frame", "u0"])
    m1 = s.join(piv, on=["frame", "u1"])
    m = m0
    lit_a = m["lasers"].str.contains("A").to_numpy()
    lit_b = m["lasers"].str.contains("B").to_numpy()
    va = np.where(frac > 0, (1 - frac) * m0["A"].to_numpy() + frac * m1["A"].to_numpy(),
                  m0["A"].to_numpy())
    vb = np.where(frac > 0, (1 - frac) * m0["B"].to_numpy() + frac * m1["B"].to_numpy(),
                  m0["B"].to_numpy())
    v = m["v"].to_numpy()
    da = np.where(lit_a, np.abs(v - va), np.inf)
    db = np.where(lit_b, np.abs(v - vb), np.inf)
    e = np.minimum(da, db)
    e = np.where(np.isfinite(e), e, np.nan)
    # the distance to the true centre line itself (normal to it) is the error a centre makes;
    # the row error at a fixed column is that divided by cos(slope), 1.4-1.7x on these stripes
    sl = s[["frame", "u0"]].join(slopes, on=["frame", "u0"])
    slope = np.where(da <= db, sl["A"].to_numpy(), sl["B"].to_numpy())
    e_normal = e / np.sqrt(1.0 + np.nan_to_num(slope) ** 2)
    near = np.abs(va - vb) < CROSSING_PX  # both true stripes close in this column
    flagged = (m["flags"].to_numpy() & 1) != 0  # merged
    has = np.isfinite(e) & (e < 5.0)  # centres on a true stripe (not reflections or noise)
    out = {"centres": len(s), "scored": int(has.sum()), "off_truth": int((~has).sum())}
    for name, sel in (("away", has & ~near & ~flagged), ("crossing", has & near & ~flagged)):
        x, xn = e[sel], e_normal[sel]
        out[name] = {"n": int(x.size),
                     "rms_px": float(np.sqrt(np.mean(x**2))) if x.size else None,
                     "p99_px": float(np.percentile(x, 99)) if x.size else None,
                     "mean_abs_px": float(np.mean(x)) if x.size else None,
                     "normal_rms_px": float(np.sqrt(np.mean(xn**2))) if x.size else None,
                     "normal_p99_px": float(np.percentile(xn, 99)) if x.size else None}
    return out


def true_slopes(tl: pd.DataFrame) -> pd.DataFrame:
    """dv/du of the true centre line at each (frame, column), one column per laser."""
    t = tl.sort_values(["frame", "laser", "u"])
    du = t.groupby(["frame", "laser"])["u"].diff()
    dv = t.groupby(["frame", "laser"])["v"].diff()
    fwd = (dv / du).where(du == 1)
    back = fwd.groupby([t["frame"], t["laser"]]).shift(-1)
    slope = pd.concat([fwd, back], axis=1).mean(axis=1)
    out = pd.DataFrame({"frame": t["frame"], "u": t["u"], "laser": t["laser"], "slope": slope})
    return out.groupby(["frame", "u", "laser"])["slope"].first().unstack("laser").reindex(
        columns=["A", "B"])


def score_labels(points: pd.DataFrame, tl: pd.DataFrame, meta: dict) -> dict:
    """Wrong labels among AB-frame points; dropped counts; points per frame vs a single line."""
    p = points[points["lasers"] == "AB"][["frame", "laser", "u", "v"]].copy()
    p["ui"] = np.round(p["u"]).astype(np.int64)
    piv = tl.groupby(["frame", "u", "laser"])["v"].first().unstack("laser").reindex(columns=["A", "B"])
    m = p.join(piv, on=["frame", "ui"])
    da = np.abs(m["v"] - m["A"]).to_numpy()
    db = np.abs(m["v"] - m["B"]).to_numpy()
    true = np.where(np.nan_to_num(da, nan=np.inf) < np.nan_to_num(db, nan=np.inf), "A", "B")
    known = np.isfinite(np.fmin(da, db)) & (np.fmin(da, db) < 3.0)
    near = np.abs(m["A"] - m["B"]).to_numpy() < CROSSING_PX
    wrong = known & (m["laser"].to_numpy() != true)
    c = meta["counts"]
    ab_in = c["centres_by_state"]["AB"]
    single = (c["centres_by_state"]["A"] + c["centres_by_state"]["B"]) / max(
        c["frames"]["A"] + c["frames"]["B"], 1)
    # a single-line rig runs the same pipeline (its trace ends are trimmed too): its points per
    # frame are those of our A and B frames
    single_points = int(points["lasers"].isin(["A", "B"]).sum()) / max(c["frames"]["A"] + c["frames"]["B"], 1)
    return {
        "ab_points": len(p), "ab_points_known": int(known.sum()),
        "wrong_labels": int(wrong.sum()), "wrong_labels_away": int((wrong & ~near).sum()),
        "wrong_labels_crossing": int((wrong & near).sum()),
        "wrong_rate": float(wrong.sum() / max(known.sum(), 1)),
        "dropped": c["dropped"], "dropped_total": int(sum(c["dropped"].values())),
        "dropped_rate_of_ab_centres": float(sum(c["dropped"].values()) / max(ab_in, 1)),
        "AB_frames_without_reference": c["AB_frames_without_reference"],
        "points_per_frame": meta["points_per_frame"],
        "single_line_centres_per_frame": single,
        "ratio_vs_single_line_centres": meta["points_per_frame"] / max(single, 1e-9),
        "single_line_points_per_frame": single_points,
        "ratio_vs_single_line": meta["points_per_frame"] / max(single_points, 1e-9),
        "ab_points_per_ab_frame": len(p) / max(c["frames"]["AB"], 1),
    }


def score_surface(capture: Path, points: pd.DataFrame, T_tool_cam: np.ndarray) -> dict:
    truth = json.loads((capture / "truth.json").read_text())
    plane = np.array(truth["scans"][SCAN]["plane_base"])
    n, d = plane[:3] / np.linalg.norm(plane[:3]), plane[3] / np.linalg.norm(plane[:3])
    out = {}
    rep = points[["x", "y", "z"]].to_numpy() @ n + d
    out["reported_poses"] = {"rms_mm": float(np.sqrt(np.mean(rep**2))),
                             "p99_mm": float(np.percentile(np.abs(rep), 99))}
    poses_file = truth["scans"][SCAN].get("poses")
    if poses_file:
        from crossline.geometry import transform_from_pose

        tp = pd.read_parquet(capture / poses_file).set_index("frame")
        sel = tp.loc[points["frame"].to_numpy()]
        T = transform_from_pose(sel[["x", "y", "z"]].to_numpy(), sel[["qw", "qx", "qy", "qz"]].to_numpy())
        pb = to_base(points[["x_cam", "y_cam", "z_cam"]].to_numpy(), T, T_tool_cam)
        tru = pb @ n + d
        out["true_poses"] = {"rms_mm": float(np.sqrt(np.mean(tru**2))),
                             "p99_mm": float(np.percentile(np.abs(tru), 99))}
    return out


def error_budget(preset: str) -> dict:
    """Centre error of each extractor on plate frames rendered with and without speckle and noise.

    The same frames (A-only and B-only, spread over the sweep) are rendered four times with the
    simulator's own renderer, so the share of each error source is seen directly.
    """
    from crossline.geometry import invert_transform
    from crossline.sim import arm as arm_mod
    from crossline.sim.capture import KIND_SCAN, Plan, _light_base, _model, _rng
    from crossline.sim.presets import PRESETS
    from crossline.sim.render import render_image
    from crossline.sim.scenes import scan_scene

    rig = PRESETS[preset]
    model = _model(Plan(rig, 0, rig.sensor.bit_depth, None))
    spec = next(x for x in rig.scans if x.name == SCAN)
    scene0, _, aim = scan_scene(rig, spec)
    _, T_base_cam = arm_mod.scan_trajectory(rig, spec, aim, spec.frames)
    T_cam_base = invert_transform(T_base_cam)
    x0, y0 = model.scan_window[:2]
    ks = np.linspace(0.1, 0.9, BUDGET_FRAMES) * (spec.frames - 1)
    cases = {"sensor noise and speckle": (True, True), "speckle only": (False, True),
             "sensor noise only": (True, False), "neither (optics, sampling)": (False, False)}
    out = {}
    for name, (noise, speckle) in cases.items():
        rows = {ex: [] for ex in EXTRACTORS}
        truth = []
        for j, k in enumerate(ks.astype(int)):
            for laser in ("A", "B"):
                fid = 2 * j + (laser == "B")
                scene = scene0.transformed(T_cam_base[k])
                light = _light_base(T_cam_base[k], rig.ambient_scan_e, aim)
                dn, tr, _ = render_image(model, scene, light, model.scan_window, (laser,),
                                         _rng(0, KIND_SCAN, 0, k), noise=noise, speckle=speckle)
                t = pd.DataFrame({"frame": fid, "laser": laser, "u": tr[laser]["u"], "v": tr[laser]["v"],
                                  "visible": tr[laser]["visible"]})
                truth.append(t[t["visible"]])
                for ex in EXTRACTORS:
                    c = {"grey_centre": grey_centre, "gaussian": gaussian, "steger": steger}[ex](dn)
                    rows[ex].append(pd.DataFrame({"frame": fid, "lasers": laser, "u": c["u"] + x0,
                                                  "v": c["v"] + y0, "flags": c["flags"]}))
        tl = pd.concat(truth, ignore_index=True)[["frame", "laser", "u", "v"]]
        # the trace ends (cut cross-sections) are left out, as the pipeline trims them
        lo = tl.groupby(["frame", "laser"])["u"].transform("min") + 8
        hi = tl.groupby(["frame", "laser"])["u"].transform("max") - 8
        tl_in = tl[(tl["u"] >= lo) & (tl["u"] <= hi)]
        out[name] = {}
        for ex in EXTRACTORS:
            st = pd.concat(rows[ex], ignore_index=True)
            st = st[st.set_index(["frame", "u"]).index.isin(tl_in.set_index(["frame", "u"]).index)]
            out[name][ex] = score_centres(st, tl_in)["away"]
    return out


def pattern_study(preset: str, frames: int, cal_dir: Path, work: Path) -> dict:
    """Points per frame and labelling with patterns that have more AB frames per period."""
    out = {}
    for pat in PATTERNS:
        cap = render(preset, frames, None if pat == PATTERNS[0] else list(pat))
        if cap is None:
            continue
        cal = true_calibration(cap, cal_dir)
        _, tl = truth_table(cap)
        name = ",".join(pat)
        st, pt = work / f"pattern-{len(pat)}.parquet", work / f"pattern-{len(pat)}-points.parquet"
        run_extract_stripes(cap, SCAN, st, extractor="gaussian", threads=2)
        meta = run_triangulate(cap, SCAN, st, *cal, pt)
        out[name] = score_labels(pd.read_parquet(pt), tl, meta)
    return out


# ----------------------------------------------------------------------------- speed


def median_time(fn, repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def naive_grey_centre(img: np.ndarray, threshold: float = 0.15, pad: int = 2) -> list:
    """The grey-centre as a per-column, per-pixel Python loop (for the speed ratio only)."""
    thr = threshold * 255.0
    H, W = img.shape
    out = []
    for c in range(W):
        col = img[:, c].tolist()
        r = 0
        while r < H:
            if col[r] > thr:
                s = r
                while r < H and col[r] > thr:
                    r += 1
                e = r - 1
                if e - s + 1 >= 2:
                    lo, hi = max(s - pad, 0), min(e + pad, H - 1)
                    bl = (col[max(lo - 1, 0)] + col[max(lo - 2, 0)]) / 2
                    bh = (col[min(hi + 1, H - 1)] + col[min(hi + 2, H - 1)]) / 2
                    bg = min(bl, bh)
                    sw = swr = 0.0
                    for rr in range(lo, hi + 1):
                        w = col[rr] - bg
                        if w > 0:
                            sw += w
                            swr += w * rr
                    if sw > 0:
                        out.append((c, swr / sw))
            else:
                r += 1
    return out


def speeds(capture: Path, cal: tuple[Path, Path, Path], repeat: int, work: Path) -> dict:
    sc = open_capture(capture).scans[SCAN]
    paths = sc.frame_paths[:60]
    blobs = [p.read_bytes() for p in paths]
    imgs = [decode_png(b, p, "opencv") for b, p in zip(blobs, paths, strict=True)]
    for b, p, im in zip(blobs[:5], paths[:5], imgs[:5], strict=True):
        assert np.array_equal(decode_png(b, p, "auto"), im)
    n = len(blobs)
    res: dict = {"frames_timed": n, "frame_shape": list(imgs[0].shape),
                 "fast_decoder": fast_decoder_available()}

    def per_frame_ms(fn, items, rep=repeat):
        fn(items[0])
        return 1e3 * median_time(lambda: [fn(x) for x in items], rep) / len(items)

    res["decode_opencv_ms"] = per_frame_ms(lambda b: decode_png(b, "x", "opencv"), blobs)
    if fast_decoder_available():
        res["decode_fast_ms"] = per_frame_ms(lambda b: decode_png(b, "x", "fast"), blobs)
    res["grey_centre_numba_ms"] = per_frame_ms(lambda im: grey_centre(im, backend="numba"), imgs)
    res["grey_centre_numpy_ms"] = per_frame_ms(lambda im: grey_centre(im, backend="numpy"), imgs)
    res["gaussian_ms"] = per_frame_ms(gaussian, imgs)
    res["steger_ms"] = per_frame_ms(lambda im: steger(im, sigma=2.0), imgs)
    res["naive_python_ms"] = 1e3 * median_time(lambda: naive_grey_centre(imgs[0]), 1)
    res["naive_over_numba"] = res["naive_python_ms"] / res["grey_centre_numba_ms"]
    res["naive_over_numpy"] = res["naive_python_ms"] / res["grey_centre_numpy_ms"]
    for k in ("grey_centre_numba", "grey_centre_numpy", "gaussian", "steger"):
        res[k + "_fps_per_core"] = 1e3 / res[k + "_ms"]
    # end to end with 2 threads: extraction (streamed, 2 threads) then triangulation with the
    # workflow's smoothing along the stripe
    nfr = len(sc.frames)
    for ex in EXTRACTORS:
        ext, tri = [], []
        for _ in range(max(2, repeat // 2)):
            st, pt = work / f"e2e-{ex}.parquet", work / f"e2e-{ex}-points.parquet"
            t0 = time.perf_counter()
            run_extract_stripes(capture, SCAN, st, extractor=ex, threads=2)
            t1 = time.perf_counter()
            run_triangulate(capture, SCAN, st, *cal, pt, smooth_px=SMOOTH_DEFAULT)
            t2 = time.perf_counter()
            ext.append(t1 - t0)
            tri.append(t2 - t1)
        e, t = float(np.median(ext)), float(np.median(tri))
        res[f"end_to_end_{ex}"] = {"frames": nfr, "extract_s": e, "triangulate_s": t,
                                   "frames_per_s": nfr / (e + t), "extract_frames_per_s": nfr / e}
    return res


# ----------------------------------------------------------------------------- throughput


def _scan_of(capture: Path) -> str:
    """The scan the throughput is measured on: the plate scan if there is one, else the first."""
    scans = sorted(open_capture(capture).scans)
    if not scans:
        raise SystemExit(f"{capture}: no scans")
    return SCAN if SCAN in scans else scans[0]


def _timed_pool(items, fn, threads: int) -> float:
    """Wall time of ``fn`` over ``items`` on a pool of ``threads`` threads, in order, bounded."""
    from concurrent.futures import ThreadPoolExecutor

    t0 = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        for _ in pool.map(fn, items):
            pass
    return time.perf_counter() - t0


def workflow_run(capture: Path, cal: tuple[Path, Path, Path], root: Path, scan: str, chunks: int,
                 one_core: bool) -> dict:
    """extract-stripes (``chunks`` jobs), gather-stripes and triangulate as the workflow runs
    them, each a fresh process; on 1 core (``taskset -c 0``, jobs one after another, 1 thread)
    or on both (jobs side by side; 1 thread each when chunked, else 2). Wall and CPU s."""
    from bench_scale import run_parallel, stage_commands

    n = len(open_capture(capture).scans[scan].frames)
    shutil.rmtree(root, ignore_errors=True)
    interim, processed = root / "interim", root / "processed"
    (interim / "stripes" / scan).mkdir(parents=True)
    (interim / "points").mkdir(parents=True)
    (interim / "calibration").mkdir(parents=True)
    for f in cal:
        shutil.copy(f, interim / "calibration" / f.name)
    cmds = stage_commands(capture, interim, processed, chunks, scan)
    pre = ["taskset", "-c", "0"] if one_core else []
    ext = cmds["extract"]
    if chunks > 1 or one_core:
        ext = [[*c[:-1], "1"] for c in ext]  # 1 thread per job
    out: dict = {}
    if one_core:  # the jobs one after the other on one core
        rs = [run_parallel([c], [root / f"extract{i}.log"], pre)[0] for i, c in enumerate(ext)]
        out["extract"] = {"wall_s": sum(r["wall_s"] for r in rs), "cpu_s": sum(r["cpu_s"] for r in rs)}
    else:
        rs = run_parallel(ext, [root / f"extract{i}.log" for i in range(len(ext))], pre)
        out["extract"] = {"wall_s": max(r["wall_s"] for r in rs), "cpu_s": sum(r["cpu_s"] for r in rs)}
    for st in ("gather", "triangulate"):
        if not cmds[st]:  # gather, with one chunk: the workflow has no such job
            out[st] = {"wall_s": 0.0, "cpu_s": 0.0}
            continue
        r = run_parallel(cmds[st], [root / f"{st}.log"], pre)[0]
        out[st] = {"wall_s": r["wall_s"], "cpu_s": r["cpu_s"]}
    out["wall_s"] = sum(v["wall_s"] for v in out.values())
    out["frames_per_s"] = n / out["wall_s"]
    return out


def speedup(capture: Path, cal: tuple[Path, Path, Path], work: Path, rounds: int, say) -> dict:
    """Scatter/gather on a long scan: 1 core against 2 chunk jobs side by side (and 1 job of 2
    threads), interleaved rounds; wall and CPU time."""
    scan = _scan_of(capture)
    n = len(open_capture(capture).scans[scan].frames)
    runs: dict = {"one_core": [], "two_chunks": [], "one_job_two_threads": []}
    for r in range(rounds):
        runs["one_core"].append(workflow_run(capture, cal, work / "su-1core", scan, 1, True))
        runs["two_chunks"].append(workflow_run(capture, cal, work / "su-2chunks", scan, 2, False))
        runs["one_job_two_threads"].append(workflow_run(capture, cal, work / "su-2threads", scan, 1, False))
        say(f"  round {r + 1}: " + ", ".join(
            f"{k} {v[-1]['frames_per_s']:.1f} frames/s (extract {v[-1]['extract']['wall_s']:.0f} s wall "
            f"{v[-1]['extract']['cpu_s']:.0f} s CPU)" for k, v in runs.items()))
    med = {k: float(np.median([x["frames_per_s"] for x in v])) for k, v in runs.items()}
    ratios = [b["frames_per_s"] / a["frames_per_s"] for a, b in zip(runs["one_core"], runs["two_chunks"],
                                                                      strict=True)]
    out = {"capture": str(capture), "frames": n, "runs": runs, "frames_per_s": med,
           "speedup_1_to_2_cores": float(np.median(ratios)), "ratios": ratios}
    say(f"  scatter/gather on {n} frames: 1 core {med['one_core']:.1f} frames/s, 2 chunk jobs "
        f"{med['two_chunks']:.1f}, 1 job of 2 threads {med['one_job_two_threads']:.1f}: speed-up 1 -> 2 "
        f"cores {out['speedup_1_to_2_cores']:.2f}x (rounds {', '.join(f'{x:.2f}' for x in ratios)})")
    return out


def throughput(capture: Path, cal: tuple[Path, Path, Path], work: Path, rounds: int,
               say) -> dict:
    """Decode-only against the scan stages as the workflow runs them, on the same frames, in
    one run; rounds interleave the measurements, so a load from others hits all alike.

    - decode only: every frame read from disk and decoded (the stage's decoder, transposed as
      the extractor takes it) on 2 threads, in this process (no process start);
    - end to end: ``crossline extract-stripes`` (2 threads, 1 chunk: it writes the scan's table,
      no gather job) and ``triangulate``, each a fresh process with config.yaml's options
      (bench_scale's commands);
    - scatter/gather: the same on 1 core (``taskset -c 0``, 1 thread) and with 2 chunk jobs of
      1 thread side by side (2 cores), as Snakemake runs ``stripes.chunks: 2``;
    - the split: decode-only and extraction in this process on 1 thread, so extraction's share
      (what the decoder leaves for it) is seen, and a zstd-compressed raw copy of the frames
      decoded from memory against the PNG bytes (what a faster lossless storage buys).
    """
    import imagecodecs

    from crossline.scan.frames import keep_freed_memory, map_frames, read_frame

    keep_freed_memory()  # the stages' heap, so that decode only runs as they decode
    scan = _scan_of(capture)
    cap = open_capture(capture)
    sc = cap.scans[scan]
    paths = sc.frame_paths
    win = cap.rig.scan_window
    shape = (win.height, win.width)
    n = len(paths)
    rate = float(cap.rig.frame_rate)
    png_mb = float(np.mean([p.stat().st_size for p in paths]) / 1e6)
    res: dict = {"capture": str(capture), "scan": scan, "frames": n, "frame_shape": list(shape),
                 "png_mb_mean": png_mb, "frame_rate": rate, "rounds": rounds,
                 "fast_decoder": fast_decoder_available(), "load_before": os.getloadavg()[0]}
    say(f"== throughput on {capture.name} scan {scan}: {n} frames {shape[1]}x{shape[0]}, PNG "
        f"{png_mb:.3f} MB each (mean), rig {rate:g} frames/s; {os.cpu_count()} cores, load average "
        f"(1 min) {res['load_before']:.2f} before")
    read_frame(paths[0], shape, transposed=True)  # compile / load the cached kernels

    decode_cpu: list[float] = []

    def decode_only(threads: int) -> float:
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in map_frames(paths, lambda i, im: None, shape=shape, threads=threads, transposed=True):
            pass
        decode_cpu.append(time.process_time() - c0)
        return time.perf_counter() - t0

    def workflow(tag: str, chunks: int, one_core: bool) -> dict:
        return workflow_run(capture, cal, work / f"tp-{tag}", scan, chunks, one_core)

    keys = ("decode_only_s", "decode_only_1thread_s", "e2e", "one_core", "two_chunks")
    runs: dict = {k: [] for k in keys}
    for r in range(rounds):
        runs["decode_only_s"].append(decode_only(2))
        runs["e2e"].append(workflow("e2e", 1, False))
        runs["decode_only_s"].append(decode_only(2))
        runs["one_core"].append(workflow("1core", 1, True))
        runs["two_chunks"].append(workflow("2chunks", 2, False))
        runs["decode_only_1thread_s"].append(decode_only(1))
        e = runs["e2e"][-1]
        say(f"  round {r + 1}: decode only {n / runs['decode_only_s'][-2]:.0f} / "
            f"{n / runs['decode_only_s'][-1]:.0f} frames/s (2 threads, before / after), end to end "
            f"{e['frames_per_s']:.0f} frames/s (extract {e['extract']['wall_s']:.1f} s wall, "
            f"{e['extract']['cpu_s']:.1f} s CPU; gather {e['gather']['wall_s']:.1f} s; triangulate "
            f"{e['triangulate']['wall_s']:.1f} s); 1 core {runs['one_core'][-1]['frames_per_s']:.0f}, "
            f"2 chunk jobs {runs['two_chunks'][-1]['frames_per_s']:.0f} frames/s")
    res["runs"] = runs
    dec = float(np.median(runs["decode_only_s"]))
    e2e = runs["e2e"]
    e_fps = float(np.median([x["frames_per_s"] for x in e2e]))
    # each round's end to end over the mean of the decode-only runs either side of it
    dec_either_side = [0.5 * (runs["decode_only_s"][2 * i] + runs["decode_only_s"][2 * i + 1])
                       for i in range(len(e2e))]
    ratios = [x["frames_per_s"] * d / n for x, d in zip(e2e, dec_either_side, strict=True)]
    ext_wall = float(np.median([x["extract"]["wall_s"] for x in e2e]))
    ext_cpu = float(np.median([x["extract"]["cpu_s"] for x in e2e]))
    tri = float(np.median([x["triangulate"]["wall_s"] + x["gather"]["wall_s"] for x in e2e]))
    one = float(np.median([x["frames_per_s"] for x in runs["one_core"]]))
    two = float(np.median([x["frames_per_s"] for x in runs["two_chunks"]]))
    # CPU time, which a load from others does not inflate as it does wall time: the work per
    # frame, and the throughput 2 cores give when the stages keep both busy
    e2e_cpu = float(np.median([sum(x[k]["cpu_s"] for k in ("extract", "gather", "triangulate"))
                               for x in e2e]))
    dcpu = float(np.median(decode_cpu))
    res["cpu"] = {"decode_only_ms_per_frame": 1e3 * dcpu / n, "end_to_end_ms_per_frame": 1e3 * e2e_cpu / n,
                  "extract_ms_per_frame": 1e3 * ext_cpu / n,
                  "ratio_decode_over_e2e": dcpu / e2e_cpu, "two_core_e2e_frames_per_s": 2 * n / e2e_cpu,
                  "two_core_decode_frames_per_s": 2 * n / dcpu}
    res.update({"decode_only_frames_per_s": n / dec,
                "decode_only_1thread_frames_per_s": n / float(np.median(runs["decode_only_1thread_s"])),
                "end_to_end_frames_per_s": e_fps, "ratio_e2e_over_decode": float(np.median(ratios)),
                "ratios": ratios, "extract_cpu_cores_used": ext_cpu / ext_wall,
                "serial_tail_share": tri / float(np.median([x["wall_s"] for x in e2e])),
                "one_core_frames_per_s": one, "two_chunks_frames_per_s": two,
                "speedup_1_to_2_cores": two / one, "e2e_over_rig_rate": e_fps / rate})
    # the split on one thread, in this process: decoding against extracting (+ table, write)
    # one frame first: the compiled kernels load from numba's cache on their first call
    run_extract_stripes(capture, scan, work / "tp-1thread.parquet", extractor="gaussian", threads=1,
                        chunk=(0, n))
    t0 = time.perf_counter()
    run_extract_stripes(capture, scan, work / "tp-1thread.parquet", extractor="gaussian", threads=1)
    ext1 = time.perf_counter() - t0
    d1 = float(np.median(runs["decode_only_1thread_s"]))
    res["one_thread_ms_per_frame"] = {"decode": 1e3 * d1 / n, "extract_stage": 1e3 * ext1 / n,
                                      "extraction_beyond_decode": 1e3 * (ext1 - d1) / n}
    res["ratio_ceiling_from_cpu_split"] = d1 / ext1
    # a faster lossless storage: the same pixels as zstd (level 1) of the raw array, from memory
    sample = paths[: min(n, 120)]
    blobs = [p.read_bytes() for p in sample]
    raws = [read_frame(p, shape) for p in sample]
    zs = [imagecodecs.zstd_encode(np.ascontiguousarray(a).tobytes(), level=1) for a in raws]
    png_t = _timed_pool(blobs, lambda b: decode_png(b, transposed=True), 2)
    zst_t = _timed_pool(
        zs, lambda z: np.frombuffer(imagecodecs.zstd_decode(z), np.uint8).reshape(shape).T.copy(), 2)
    res["storage"] = {"frames": len(sample), "png_mb": float(np.mean([len(b) for b in blobs]) / 1e6),
                      "zstd1_raw_mb": float(np.mean([len(z) for z in zs]) / 1e6),
                      "png_decode_frames_per_s": len(sample) / png_t,
                      "zstd1_decode_frames_per_s": len(sample) / zst_t}
    st = res["storage"]
    res["load_after"] = os.getloadavg()[0]  # about 2 after this run's own jobs; more: others ran too
    say(f"  load average (1 min) after the runs: {res['load_after']:.2f}")
    say(f"  decode only (read + fast PNG decode, transposed, 2 threads): "
        f"{res['decode_only_frames_per_s']:.0f} frames/s "
        f"({res['decode_only_1thread_frames_per_s']:.0f} on 1 thread)")
    say(f"  end to end (extract-stripes 2 threads + gather + triangulate, processes started): {e_fps:.0f} "
        f"frames/s = {res['ratio_e2e_over_decode']:.2f}x decode only (rounds: "
        f"{', '.join(f'{x:.2f}' for x in ratios)}), {res['e2e_over_rig_rate']:.2f}x the rig's "
        f"{rate:g} frames/s")
    c = res["cpu"]
    say(f"  CPU time per frame: decode only {c['decode_only_ms_per_frame']:.1f} ms, end to end "
        f"{c['end_to_end_ms_per_frame']:.1f} ms (extract-stripes {c['extract_ms_per_frame']:.1f} ms, "
        f"process start included): {c['ratio_decode_over_e2e']:.2f}x; on 2 free cores kept busy "
        f"{c['two_core_decode_frames_per_s']:.0f} vs {c['two_core_e2e_frames_per_s']:.0f} frames/s "
        f"= {c['two_core_e2e_frames_per_s'] / rate:.2f}x the rig's rate")
    say(f"  extract-stripes used {res['extract_cpu_cores_used']:.2f} cores on average; gather + triangulate "
        f"(one process, one core) are {100 * res['serial_tail_share']:.0f} % of the end-to-end wall time")
    o = res["one_thread_ms_per_frame"]
    say(f"  one thread, in process: decode {o['decode']:.1f} ms/frame, the extraction stage "
        f"{o['extract_stage']:.1f} ms/frame (extraction, tables, writing beyond decoding: "
        f"{o['extraction_beyond_decode']:.1f} ms): end to end can reach at most "
        f"{res['ratio_ceiling_from_cpu_split']:.2f}x decode only with this extractor")
    say(f"  scatter/gather: 1 core (taskset, 1 thread) {one:.0f} frames/s, 2 chunk jobs side by side "
        f"{two:.0f} frames/s: {res['speedup_1_to_2_cores']:.2f}x")
    say(f"  storage: PNG {st['png_mb']:.3f} MB decodes at {st['png_decode_frames_per_s']:.0f} frames/s, "
        f"zstd-1 of the raw pixels {st['zstd1_raw_mb']:.3f} MB at {st['zstd1_decode_frames_per_s']:.0f} "
        f"frames/s (2 threads, from memory, {st['frames']} frames)")
    return res


# ----------------------------------------------------------------------------- memory


def cycled_capture(capture: Path, n: int) -> Path:
    """A capture whose plate scan has ``n`` frames, hard links cycling the original frames."""
    out = CACHE / f"{capture.name}-cycled-{n}"
    if (out / "scans" / SCAN / "frames.csv").is_file():
        return out
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    rig = yaml.safe_load((capture / "rig.yaml").read_text())
    rig["scans"] = {SCAN: rig["scans"][SCAN]}
    (out / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    os.symlink(capture / "calibration", out / "calibration")
    src = pd.read_csv(capture / "scans" / SCAN / "frames.csv", dtype=str)
    period = len(src) - len(src) % 3 or len(src)  # keep the A, B, AB phase across the seam
    fdir = out / "scans" / SCAN / "frames"
    fdir.mkdir(parents=True)
    rows = []
    for k in range(n):
        r = src.iloc[k % period].copy()
        os.link(capture / "scans" / SCAN / "frames" / f"{int(r['frame']):06d}.png", fdir / f"{k:06d}.png")
        r["frame"] = str(k)
        r["time_s"] = f"{k / 80:.6f}"
        rows.append(r)
    pd.DataFrame(rows).to_csv(out / "scans" / SCAN / "frames.csv", index=False)
    return out


def peak_rss(capture: Path, cal: tuple[Path, Path, Path], work: Path) -> dict:
    """Peak resident memory (MB) of each scan job (extraction, then triangulation), each run
    in its own fresh interpreter as Snakemake runs it, with the workflow's default extractor.

    Read from /proc/self/status (VmHWM, the high-water mark of the process's own memory),
    not from getrusage: ru_maxrss survives exec, so a child started from this benchmark
    (which holds its frames and tables, ~1 GB) would report the parent's peak.
    """
    head = f"""
import sys, time
sys.path.insert(0, {str(REPO)!r})
def hwm():
    for line in open('/proc/self/status'):
        if line.startswith('VmHWM:'):
            return int(line.split()[1]) / 1024
t0 = time.perf_counter()
"""
    jobs = {
        "extract": f"""
from crossline.scan.stripes import run_extract_stripes
run_extract_stripes({str(capture)!r}, {SCAN!r}, {str(work / 'm.parquet')!r}, threads=2, extractor='gaussian')
""",
        "triangulate": f"""
from crossline.scan.triangulate import run_triangulate
run_triangulate({str(capture)!r}, {SCAN!r}, {str(work / 'm.parquet')!r}, {str(cal[0])!r}, {str(cal[1])!r},
                {str(cal[2])!r}, {str(work / 'mp.parquet')!r}, smooth_px={SMOOTH_DEFAULT})
""",
    }
    res = {}
    for job, body in jobs.items():
        code = head + body + "print(hwm(), time.perf_counter() - t0)\n"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        mb, sec = out.stdout.split()
        res[f"peak_rss_{job}_mb"] = float(mb)
        res[f"{job}_s"] = float(sec)
    return res


# ----------------------------------------------------------------------------- main


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", default="paper,compact",
                    help="simulator presets to score ('' = none: speed and memory on synthetic frames)")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--mem-frames", default="500,2000")
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--no-budget", dest="budget", action="store_false",
                    help="skip the error budget (frames rendered with speckle and noise switched off)")
    ap.add_argument("--capture", type=Path,
                    help="measure the throughput on this capture (default: the noisy-sensor render "
                         "of benchmarks/scan_data.py)")
    ap.add_argument("--throughput-only", action="store_true",
                    help="only the throughput section (no accuracy, kernels or memory)")
    ap.add_argument("--rounds", type=int, default=3, help="throughput: interleaved rounds")
    ap.add_argument("--speedup-frames", type=int, default=0,
                    help="only the scatter/gather speed-up, on a long scan of this many frames "
                         "(scan_data.long_capture of the noisy-sensor render)")
    ap.add_argument("--sensor-frames", type=int, default=480,
                    help="throughput: frames of the noisy-sensor render (default 480)")
    ap.add_argument("--no-patterns", dest="patterns", action="store_false",
                    help="skip the laser-pattern study (renders the plate scan with more AB frames)")
    a = ap.parse_args(argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    work = CACHE / "work"
    work.mkdir(parents=True, exist_ok=True)
    report: dict = {"crossing_band_px": CROSSING_PX, "presets": {}, "machine": {
        "cpus": os.cpu_count(), "python": sys.version.split()[0]}}
    lines: list[str] = []

    def say(s: str = "") -> None:
        print(s, flush=True)
        lines.append(s)

    from crossline.io.atomic import write_json

    if a.speedup_frames:
        from scan_data import long_capture, sensor_capture

        src = sensor_capture(a.sensor_frames)
        say(f"== scatter/gather speed-up: {a.speedup_frames} frames of {src.name} reused along a long "
            f"arm path; load average (1 min) {os.getloadavg()[0]:.2f} before")
        su = speedup(long_capture(src, a.speedup_frames), true_calibration(src, work / f"cal-{src.name}"),
                     work, a.rounds, say)
        write_json(RESULTS / "scan_speedup.json", su)
        (RESULTS / "scan_speedup.txt").write_text("\n".join(lines) + "\n")
        return 0
    if a.capture is not None:
        tcap = a.capture.resolve()
        tcal = (tcap / "cal" / "camera.json", tcap / "cal" / "lasers.json", tcap / "cal" / "handeye.json") \
            if (tcap / "cal" / "camera.json").is_file() else None
        if tcal is None and (tcap / "truth.json").is_file():
            tcal = true_calibration(tcap, work / f"cal-{tcap.name}")
        if tcal is None:
            raise SystemExit(f"{tcap}: needs cal/camera.json, lasers.json, handeye.json or a truth.json")
    else:
        from scan_data import sensor_capture

        tcap = sensor_capture(a.sensor_frames)
        tcal = true_calibration(tcap, work / f"cal-{tcap.name}")
    report["throughput"] = throughput(tcap, tcal, work, a.rounds, say)
    write_json(RESULTS / "scan_throughput.json", report["throughput"])
    (RESULTS / "scan_throughput.txt").write_text("\n".join(lines) + "\n")
    if a.throughput_only:
        return 0
    speed_capture, speed_cal = None, None
    for preset in [x for x in a.presets.split(",") if x]:
        say(f"== preset {preset}")
        cap = render(preset, a.frames)
        if cap is None:
            report["presets"][preset] = {"rendered": False}
            continue
        cal = true_calibration(cap, work / f"cal-{preset}")
        truth, tl = truth_table(cap)
        T_tool_cam = np.array(truth["T_tool_cam"])
        entry: dict = {"rendered": True, "frames": a.frames, "extractors": {}}
        for ex in EXTRACTORS:
            st, pt = work / f"{preset}-{ex}.parquet", work / f"{preset}-{ex}-points.parquet"
            smeta = run_extract_stripes(cap, SCAN, st, extractor=ex, threads=2)
            meta = run_triangulate(cap, SCAN, st, *cal, pt)
            s, p = pd.read_parquet(st), pd.read_parquet(pt)
            r = {"centres": score_centres(s, tl), "centres_used": score_centres(p, tl),
                 "labels": score_labels(p, tl, meta),
                 "surface": score_surface(cap, p, T_tool_cam)}
            if "noise" in smeta:
                r["noise_found"] = {k: float(np.median(v)) for k, v in smeta["noise"].items() if k != "frame"}
            # the same with the centre line smoothed along the stripe (local quadratic)
            for win in SMOOTH_WINDOWS:
                ps = work / f"{preset}-{ex}-smooth{win}.parquet"
                run_triangulate(cap, SCAN, st, *cal, ps, smooth_px=win)
                pts = pd.read_parquet(ps)
                r[f"centres_smooth{win}"] = score_centres(pts, tl)
                r[f"surface_smooth{win}"] = score_surface(cap, pts, T_tool_cam)
            # the lateral resolution the smoothing leaves, in mm on this plate
            # (the lasers' median spacings, crossline.report.scan_truth.stripe_spacing_mm, averaged)
            r["column_spacing_mm"] = float(np.mean(list(stripe_spacing_mm(ps).values())))
            # the paper's rule (latest frame, nearest wins) on the same centres, for comparison
            meta0 = run_triangulate(cap, SCAN, st, *cal, work / f"{preset}-{ex}-paper.parquet",
                                    ambiguity_px=0.0, predict=False)
            r["labels_paper_rule"] = score_labels(
                pd.read_parquet(work / f"{preset}-{ex}-paper.parquet"), tl, meta0)
            entry["extractors"][ex] = r
            c, lb, sf = r["centres"], r["labels"], r["surface"]
            say(f"  {ex:12s} centre error away (row at the column / normal to the line): RMS "
                f"{c['away']['rms_px']:.4f} / {c['away']['normal_rms_px']:.4f} px, p99 "
                f"{c['away']['p99_px']:.4f} / {c['away']['normal_p99_px']:.4f} px (n={c['away']['n']}); "
                f"crossing band: RMS "
                f"{c['crossing']['rms_px'] or float('nan'):.4f} px, p99 "
                f"{c['crossing']['p99_px'] or float('nan'):.4f} px (n={c['crossing']['n']})")
            if "noise_found" in r:
                say(f"  {'':12s} noise found in the frames (median): background "
                    f"{r['noise_found']['background_noise_dn']:.2f} DN, relative (speckle) "
                    f"{r['noise_found']['relative_noise']:.3f}")
            tags = [("centres_used", "after end trimming", "surface")] + [
                (f"centres_smooth{w}", f"trimmed + smoothed over {w} columns"
                 + (" (workflow default)" if w == SMOOTH_DEFAULT else ""), f"surface_smooth{w}")
                for w in SMOOTH_WINDOWS]
            for tag, what, stag in tags:
                c = r[stag.replace("surface", "centres")] if stag != "surface" else r[tag]
                ssf = r[stag]
                say(f"  {'':12s} {what}: away RMS {c['away']['rms_px']:.4f} / "
                    f"{c['away']['normal_rms_px']:.4f} px, p99 {c['away']['p99_px']:.4f} / "
                    f"{c['away']['normal_p99_px']:.4f} px (n={c['away']['n']}); plate RMS (TRUE "
                    f"calibration and poses) "
                    f"{ssf.get('true_poses', ssf['reported_poses'])['rms_mm']:.4f} mm")
            ripple = half_amplitude_columns(SMOOTH_DEFAULT)
            say(f"  {'':12s} points {r['column_spacing_mm']:.4f} mm apart along the stripe (median): "
                f"the {SMOOTH_DEFAULT}-column smoothing passes half the amplitude of a "
                f"{ripple:.2f}-column ripple = {ripple * r['column_spacing_mm']:.3f} mm")
            for tag, L in (("ours", lb), ("paper rule", r["labels_paper_rule"])):
                say(f"  {'':12s} labels ({tag}): wrong {L['wrong_labels']} of {L['ab_points_known']} "
                    f"AB points "
                    f"({100 * L['wrong_rate']:.3f} %), away from crossing {L['wrong_labels_away']}; "
                    f"dropped {L['dropped_total']} ({100 * L['dropped_rate_of_ab_centres']:.2f} % of AB "
                    f"centres) {L['dropped']}; points/frame {L['points_per_frame']:.1f} = "
                    f"{L['ratio_vs_single_line']:.3f}x a single line through the same pipeline "
                    f"({L['ratio_vs_single_line_centres']:.3f}x its untrimmed centres)")
            sp = sf.get("true_poses", sf["reported_poses"])
            say(f"  {'':12s} distance to true plate (TRUE calibration): RMS "
                f"{sf['reported_poses']['rms_mm']:.4f} mm with reported poses, "
                f"{sp['rms_mm']:.4f} mm with true poses")
        if a.budget:
            entry["error_budget"] = error_budget(preset)
            say(f"  error budget (A and B frames of the plate rendered again, {BUDGET_FRAMES} each; "
                f"centre error RMS, row at the column / normal to the line, px):")
            for name, row in entry["error_budget"].items():
                say(f"    {name:28s} " + "  ".join(
                    f"{ex} {v['rms_px']:.4f} / {v['normal_rms_px']:.4f}" for ex, v in row.items()))
        if a.patterns and preset == "paper":
            entry["patterns"] = pattern_study(preset, a.frames, work / f"cal-{preset}", work)
            say("  laser patterns (gaussian extractor; points per frame vs a single line through the "
                "same pipeline):")
            for name, L in entry["patterns"].items():
                say(f"    {name:20s} {L['points_per_frame']:7.1f} points/frame = "
                    f"{L['ratio_vs_single_line']:.3f}x (all lines kept: "
                    f"{(len(name.split(',')) + name.count('AB')) / len(name.split(',')):.3f}x); wrong labels "
                    f"{L['wrong_labels']} of {L['ab_points_known']}, dropped "
                    f"{100 * L['dropped_rate_of_ab_centres']:.2f} % of AB centres")
        report["presets"][preset] = entry
        if speed_capture is None:
            speed_capture, speed_cal = cap, cal
    if speed_capture is None:
        say("== no simulator capture: speed and memory on synthetic 2658x800 frames (no truth)")
        speed_capture = synthetic_capture(a.frames)
        speed_cal = true_calibration(speed_capture, work / "cal-synthetic")
        report["speed_data"] = "synthetic"
    else:
        report["speed_data"] = speed_capture.name
    say(f"== speed on {speed_capture.name} (medians of {a.repeat} runs)")
    sp = speeds(speed_capture, speed_cal, a.repeat, work)
    report["speed"] = sp
    say(f"  decode alone: OpenCV {sp['decode_opencv_ms']:.2f} ms/frame"
        + (f", fast (libdeflate + numba) {sp['decode_fast_ms']:.2f} ms/frame"
           if "decode_fast_ms" in sp else ""))
    say(f"  grey-centre kernel: numba {sp['grey_centre_numba_ms']:.3f} ms "
        f"({sp['grey_centre_numba_fps_per_core']:.0f} frames/s/core), numpy "
        f"{sp['grey_centre_numpy_ms']:.3f} ms ({sp['grey_centre_numpy_fps_per_core']:.0f})")
    say(f"  Gaussian-fit kernel: {sp['gaussian_ms']:.3f} ms "
        f"({sp['gaussian_fps_per_core']:.0f} frames/s/core)")
    say(f"  Steger kernel: {sp['steger_ms']:.3f} ms ({sp['steger_fps_per_core']:.0f} frames/s/core)")
    say(f"  naive per-column Python loop: {sp['naive_python_ms']:.0f} ms/frame = "
        f"{sp['naive_over_numba']:.0f}x numba, {sp['naive_over_numpy']:.0f}x numpy")
    for ex in EXTRACTORS:
        e = sp[f"end_to_end_{ex}"]
        say(f"  end to end {ex} (2 threads, {e['frames']} frames): {e['frames_per_s']:.0f} frames/s "
            f"(extract {e['extract_s']:.2f} s = {e['extract_frames_per_s']:.0f} frames/s, triangulate "
            f"{e['triangulate_s']:.2f} s)")
    if not a.skip_memory:
        say("== peak memory (RSS, VmHWM) of each scan job in its own process, frames cycled")
        report["memory"] = {}
        for n in (int(x) for x in a.mem_frames.split(",")):
            cc = cycled_capture(speed_capture, n)
            m = peak_rss(cc, speed_cal, work)
            report["memory"][str(n)] = m
            say(f"  {n:5d} frames: extract (gaussian, 2 threads) {m['peak_rss_extract_mb']:.0f} MB in "
                f"{m['extract_s']:.1f} s, triangulate {m['peak_rss_triangulate_mb']:.0f} MB in "
                f"{m['triangulate_s']:.1f} s")
    write_json(RESULTS / "scan.json", report)
    (RESULTS / "scan.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Scale curve: wall time and peak memory of every scan stage against the length of the scan.

    python benchmarks/bench_scale.py                      # 1000,5000,20000,50000 frames
    python benchmarks/bench_scale.py --sizes 1000,5000 --chunks 2
    python benchmarks/bench_scale.py --sizes 50000 --stages fuse,report --reuse   # again, from its points

Long scans are made by :func:`scan_data.long_capture`: frames of a rendered noisy-sensor plate
scan (:func:`scan_data.sensor_capture`) reused in a fixed-seed order along a long, varied arm
path (their images are reused, stated as such: the clouds are for time and memory, not
accuracy). Each size runs the workflow's commands for one scan, each in its own process as
Snakemake runs it (process start included), with the options of config.yaml: ``crossline
check``, ``extract-stripes`` (``stripes.chunks`` jobs, run side by side), ``gather-stripes``
(with 2 or more chunks), ``triangulate``, ``fuse`` and ``report``, with the TRUE calibration
(written from truth.json: the calibration stages do not depend on the scan's length). Per
stage: wall time, CPU time, and peak resident memory (VmHWM of the stage's own process, read
by a wrapper that calls ``crossline.cli.main`` as the console script does). Results go to
benchmarks/results/scale.json, scale.txt and scale.png; a size is skipped when the time left
(``--budget-s``) is less than the previous size's time scaled by frames.
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

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))

from scan_data import CACHE, SCAN, long_capture, sensor_capture  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
CONFIG = yaml.safe_load((REPO / "config.yaml").read_text())

# runs the console script's entry point, then writes this process's peak RSS (kB) to a file
_WRAP = """
import os, sys
from crossline.cli import main
try:
    rc = main(sys.argv[2:])
finally:
    with open(sys.argv[1], "w") as f:
        f.write(next(l.split()[1] for l in open("/proc/self/status") if l.startswith("VmHWM:")))
sys.exit(rc)
"""


def run_stage(args: list[str], log: Path) -> dict:
    """Run ``crossline <args>`` in a fresh interpreter; wall s, CPU s, peak RSS MB."""
    return run_parallel([args], [log])[0]


def run_parallel(jobs: list[list[str]], logs: list[Path], prefix: list[str] | None = None) -> list[dict]:
    """Several stage commands side by side (as Snakemake runs independent jobs); per job
    wall s (from the start of all), CPU s and peak RSS MB. ``prefix``: e.g. ``taskset -c 0``."""
    t0 = time.perf_counter()
    procs = []
    for args, log in zip(jobs, logs, strict=True):
        hwm = log.with_suffix(".hwm")
        hwm.unlink(missing_ok=True)
        f = log.open("w")
        cmd = [*(prefix or []), sys.executable, "-c", _WRAP, str(hwm), *args]
        procs.append((subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT), f, hwm, log))
    out = []
    for p, f, hwm, log in procs:
        _, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        f.close()
        if p.returncode != 0:
            raise RuntimeError(f"crossline {' '.join(jobs[procs.index((p, f, hwm, log))][:1])} failed "
                               f"(exit {p.returncode}); see {log}:\n{log.read_text()[-3000:]}")
        out.append({"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime,
                    "peak_rss_mb": int(hwm.read_text()) / 1024})
    return out


def stage_commands(capture: Path, interim: Path, processed: Path, chunks: int,
                   scan: str = SCAN) -> dict[str, list]:
    """The workflow's commands for one scan (workflow/rules/*.smk with config.yaml's values)."""
    s, p, fu = CONFIG["stripes"], CONFIG["points"], CONFIG["fuse"]
    st = interim / "stripes" / scan
    stripes = interim / "stripes" / f"{scan}.parquet"
    # one chunk writes the scan's table itself, as the workflow's extract_stripes does
    parts = [st / f"part{i}-of-{chunks}.parquet" for i in range(chunks)] if chunks > 1 else [stripes]
    extract = [["extract-stripes", str(capture), scan, "--out", str(parts[i]), "--extractor",
                s["extractor"], "--threshold", str(s["threshold"]), "--min-width", str(s["min_width"]),
                "--max-width", str(s["max_width"]), "--sigma", str(s["sigma"]), "--pad", str(s["pad"]),
                "--fit-pad", str(s["fit_pad"]), "--relative-noise", str(s["relative_noise"]),
                "--fit-across", str(s["fit_across"]).lower(), "--min-peak", str(s["min_peak"]),
                "--off-frames", s["off_frames"], "--chunk", f"{i}/{chunks}",
                "--threads", "2"] for i in range(chunks)]
    points = interim / "points" / f"{scan}.parquet"
    cal = interim / "calibration"
    frames = capture / "scans" / scan / "frames.csv"
    return {
        "check": [["check", str(capture), "--json", str(interim / "check.json")]],
        "extract": extract,
        "gather": [["gather-stripes", *map(str, parts), "--out", str(stripes)]] if chunks > 1 else [],
        "triangulate": [[
            "triangulate", str(capture), scan, "--stripes", str(stripes), "--camera",
            str(cal / "camera.json"), "--lasers", str(cal / "lasers.json"), "--handeye",
            str(cal / "handeye.json"), "--out", str(points), "--threshold-px", str(p["threshold_px"]),
            "--max-frame-gap", str(p["max_frame_gap"]), "--ambiguity-px", str(p["ambiguity_px"]),
            "--predict", str(p["predict"]).lower(), "--end-trim-px", str(p["end_trim_px"]),
            "--smooth-px", str(p["smooth_px"]), "--bridge-columns", str(p["bridge_columns"]),
            "--track-references", str(p["track_references"]).lower(),
            "--stats", str(interim / "points" / f"{scan}.json")]],
        "fuse": [[
            "fuse", str(points), "--out", str(processed / f"{scan}.ply"), "--stats",
            str(processed / f"{scan}.fuse.json"), "--neighbours", str(fu["neighbours"]),
            "--std-ratio", str(fu["std_ratio"]), "--voxel-mm", str(fu["voxel_mm"]),
            "--normal-radius-mm", str(fu["normal_radius_mm"]), "--mesh", fu["mesh"],
            "--refine-poses", str(fu["refine_poses"]).lower(), "--frames", str(frames),
            "--handeye", str(cal / "handeye.json"), "--arm-precision-mm", str(fu["arm_precision_mm"]),
            "--arm-precision-rad", str(fu["arm_precision_rad"]),
            "--arm-smooth-fraction", str(fu["arm_smooth_fraction"]),
            "--arm-corr-time-s", str(fu["arm_corr_time_s"]),
            "--crossing-half-mm", str(fu["crossing_half_mm"]),
            "--crossing-min-angle-deg", str(fu["crossing_min_angle_deg"]),
            "--crossing-max-width-ratio", str(fu["crossing_max_width_ratio"]),
            "--arm-draws", str(fu["arm_draws"]), "--arm-draws-out", str(processed / f"{scan}.arm.npz"),
            "--threads", "2"]],
        "report": [[
            "report", str(capture), "--interim", str(interim), "--processed", str(processed),
            "--config-json", json.dumps({k: CONFIG[k] for k in ("camera", "lasers", "handeye", "stripes",
                                                                  "points", "fuse", "report")},
                                        sort_keys=True),
            "--pdf", str(processed / "accuracy.pdf"), "--metrics", str(processed / "metrics.json")]],
    }


STAGES = ("check", "extract", "gather", "triangulate", "fuse", "report")


def run_size(src: Path, n: int, chunks: int, stages: tuple[str, ...], reuse: bool = False) -> dict:
    """All stages on an ``n``-frame long scan; per stage wall, CPU and peak RSS.

    ``reuse`` keeps what an earlier run of this size left (its points file, fused cloud) and
    runs only ``stages`` on it: the later stages of a long scan measured again without its
    extraction."""
    from crossline.sim import write_true_calibration

    cap = long_capture(src, n)
    work = CACHE / "scale" / f"{n}"
    if reuse:
        need = {"triangulate": work / "interim" / "stripes" / f"{SCAN}.parquet",
                "fuse": work / "interim" / "points" / f"{SCAN}.parquet",
                "report": work / "processed" / f"{SCAN}.ply"}
        missing = [str(need[s]) for s in stages[:1] if s in need and not need[s].is_file()]
        if missing:
            raise SystemExit(f"--reuse: {missing[0]} is missing; run the earlier stages of "
                             f"{n} frames first")
    else:
        shutil.rmtree(work, ignore_errors=True)
    interim, processed = work / "interim", work / "processed"
    for d in (interim / "stripes" / SCAN, interim / "points", processed, work / "logs"):
        d.mkdir(parents=True, exist_ok=True)
    write_true_calibration(src, interim / "calibration")
    cmds = stage_commands(cap, interim, processed, chunks)
    res: dict = {"frames": n, "chunks": chunks, "stages": {}}
    for stage in stages:
        jobs = cmds[stage]
        if not jobs:  # gather, with one chunk: the workflow has no such job
            continue
        logs = [work / "logs" / f"{stage}{i}.log" for i in range(len(jobs))]
        r = run_parallel(jobs, logs)
        res["stages"][stage] = {"wall_s": max(x["wall_s"] for x in r),
                                "cpu_s": sum(x["cpu_s"] for x in r),
                                "peak_rss_mb": max(x["peak_rss_mb"] for x in r), "jobs": len(r)}
        print(f"  {n:6d} frames {stage:12s} {res['stages'][stage]['wall_s']:8.1f} s wall "
              f"{res['stages'][stage]['cpu_s']:8.1f} s CPU  peak RSS "
              f"{res['stages'][stage]['peak_rss_mb']:7.0f} MB", flush=True)
    meta = json.loads((interim / "points" / f"{SCAN}.json").read_text()) \
        if (interim / "points" / f"{SCAN}.json").is_file() else {}
    res["points"] = meta.get("points") or meta.get("counts", {}).get("points")
    fj = processed / f"{SCAN}.fuse.json"
    if fj.is_file():
        res["fuse_stats"] = {k: v for k, v in json.loads(fj.read_text()).items()
                             if isinstance(v, (int, float, str))}
    files = [interim / "stripes" / f"{SCAN}.parquet", interim / "points" / f"{SCAN}.parquet",
             processed / f"{SCAN}.ply"]
    res["sizes_mb"] = {str(p.relative_to(work)): round(p.stat().st_size / 1e6, 1)
                       for p in files if p.is_file()}
    shutil.rmtree(work / "interim" / "stripes", ignore_errors=True)  # GBs at 50 k frames
    return res


def plot(results: list[dict], path: Path, extrapolate_to: int = 50000) -> None:
    """Wall time, CPU time and peak RSS per stage against frames; the peak RSS also drawn as
    the straight line through the measured sizes, out to ``extrapolate_to`` frames (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, (a, c, b) = plt.subplots(1, 3, figsize=(15, 4.4))
    ns = np.array([r["frames"] for r in results], float)
    for k, stage in enumerate(STAGES):
        if not all(stage in r["stages"] for r in results):
            continue
        col = f"C{k}"
        a.plot(ns, [r["stages"][stage]["wall_s"] for r in results], "o-", color=col, label=stage)
        c.plot(ns, [r["stages"][stage]["cpu_s"] for r in results], "o-", color=col, label=stage)
        gb = np.array([r["stages"][stage]["peak_rss_mb"] / 1024 for r in results])
        b.plot(ns, gb, "o-", color=col, label=stage)
        if len(ns) >= 2 and extrapolate_to > ns[-1]:
            slope, icpt = np.polyfit(ns, gb, 1)
            xs = np.array([ns[-1], extrapolate_to])
            b.plot(xs, icpt + slope * xs, "--", color=col, lw=1)
    a.set(xscale="log", yscale="log", xlabel="frames in the scan", ylabel="wall time, s",
          title="wall time per stage (2 cores shared with others)")
    c.set(xscale="log", yscale="log", xlabel="frames in the scan", ylabel="CPU time, s",
          title="CPU time per stage (user + sys)")
    b.set(xscale="log", yscale="log", xlabel="frames in the scan", ylabel="peak RSS, GB",
          title="peak memory per stage (dashed: linear extrapolation)")
    b.axhline(4.0, color="k", ls=":", lw=1, label="4 GB target")
    for ax in (a, c, b):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="1000,5000,20000,50000")
    ap.add_argument("--chunks", type=int, default=int(CONFIG["stripes"]["chunks"]),
                    help="extraction jobs per scan (default: config.yaml stripes.chunks)")
    ap.add_argument("--source-frames", type=int, default=480, help="rendered frames to reuse")
    ap.add_argument("--pattern", default=None,
                    help="laser pattern of the rendered frames (e.g. AB: both lines in every "
                         "frame, about twice the points; default the rig's)")
    ap.add_argument("--stages", default=",".join(STAGES))
    ap.add_argument("--budget-s", type=float, default=float("inf"),
                    help="skip a size whose predicted time exceeds the time left")
    ap.add_argument("--tag", default="", help="suffix of the result files")
    ap.add_argument("--reuse", action="store_true",
                    help="run --stages on what an earlier run of each size left (e.g. --stages "
                         "fuse,report after a run that made the points), instead of from scratch")
    ap.add_argument("--replot", action="store_true", help="only redraw the plot from scale<tag>.json")
    a = ap.parse_args(argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    if a.replot:
        saved = json.loads((RESULTS / f"scale{a.tag}.json").read_text())
        plot(saved["results"], RESULTS / f"scale{a.tag}.png")
        return 0
    t_start = time.perf_counter()
    src = sensor_capture(a.source_frames, pattern=a.pattern)
    stages = tuple(x for x in a.stages.split(",") if x)
    results: list[dict] = []
    skipped: list[int] = []
    lines = [f"== scale curve: {src.name} frames reused along a long arm path, "
             f"{a.chunks} extraction job(s), machine shared (2 cores, {os.cpu_count()} CPUs seen)"]
    print(lines[0], flush=True)
    for n in (int(x) for x in a.sizes.split(",")):
        if results:
            last = results[-1]
            predicted = sum(s["wall_s"] for s in last["stages"].values()) * n / last["frames"]
            left = a.budget_s - (time.perf_counter() - t_start)
            if predicted > left:
                skipped.append(n)
                msg = f"  {n:6d} frames skipped: predicted {predicted:.0f} s, {left:.0f} s left"
                print(msg, flush=True)
                lines.append(msg)
                continue
        r = run_size(src, n, a.chunks, stages, a.reuse)
        results.append(r)
        for stage, s in r["stages"].items():
            lines.append(f"  {n:6d} frames {stage:12s} {s['wall_s']:8.1f} s wall {s['cpu_s']:8.1f} s CPU  "
                         f"peak RSS {s['peak_rss_mb']:7.0f} MB")
        lines.append(f"  {n:6d} frames: {r.get('points')} points; files {r['sizes_mb']} MB")
        out = {"source": src.name, "chunks": a.chunks, "results": results, "skipped": skipped}
        (RESULTS / f"scale{a.tag}.json").write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
        (RESULTS / f"scale{a.tag}.txt").write_text("\n".join(lines) + "\n")
        plot(results, RESULTS / f"scale{a.tag}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())

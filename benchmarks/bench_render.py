"""Render-speed figures of the virtual rig: the --quick capture and the full paper demo.

Prints wall time, CPU time (this process and its workers) and the load average beside each
run, and writes them to benchmarks/results/render.json and render.txt. The figures to meet
(issue 2): --quick within 20 s and the full paper demo (all calibration images, 4 scans of
>= 300 frames) within 3 minutes on a 2-core machine. On a shared machine the wall time
depends on what else runs: compare CPU time / cores, and re-run on a quiet machine.

    python benchmarks/bench_render.py                 # quick x3 (median) + full paper once
    python benchmarks/bench_render.py --quick-only
    python benchmarks/bench_render.py --presets paper compact --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from crossline.capture import check_capture  # noqa: E402
from crossline.sim import simulate  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


def _cpu() -> float:
    """CPU seconds of the whole machine (user + system, all cores) from /proc/stat.

    The renderer's workers are children of a forkserver, whose usage never reaches this
    process's RUSAGE_CHILDREN: on a quiet machine the machine's CPU time is the render's.
    """
    try:
        ticks = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
        busy = sum(int(t) for i, t in enumerate(ticks) if i not in (3, 4))  # not idle, iowait
        return busy / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        me = resource.getrusage(resource.RUSAGE_SELF)
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def run_once(preset: str, quick: bool, threads: int, work: Path) -> dict:
    """Render one capture; return its timings and size."""
    out = work / f"{preset}-{'quick' if quick else 'full'}"
    shutil.rmtree(out, ignore_errors=True)
    load0 = os.getloadavg()[0]
    c0, t0 = _cpu(), time.perf_counter()
    simulate(out, preset=preset, quick=quick, threads=threads, progress=False)
    wall = time.perf_counter() - t0
    cpu = _cpu() - c0
    summary = check_capture(out, images=False)
    n_images = (sum(summary["views"].values()) + sum(summary["views"][k] for k in ("laser_A", "laser_B"))
                + sum(s["frames"] for s in summary["scans"].values()))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    shutil.rmtree(out, ignore_errors=True)
    return {"wall_s": wall, "cpu_s": cpu, "images": n_images, "frames_per_scan":
            {k: s["frames"] for k, s in summary["scans"].items()}, "bytes": size,
            "load_before": load0, "load_after": os.getloadavg()[0]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["paper"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3, help="repeats of --quick (median reported)")
    ap.add_argument("--quick-only", action="store_true")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temp dir)")
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="crossline-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    results: dict = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                 "platform": platform.platform()},
                     "threads": a.threads, "runs": {}}
    lines = []
    for preset in a.presets:
        quick = [run_once(preset, True, a.threads, work) for _ in range(a.repeat)]
        med = statistics.median(r["wall_s"] for r in quick)
        results["runs"][f"{preset}/quick"] = {"median_wall_s": med, "target_s": 20.0, "runs": quick}
        lines.append(f"{preset:8s} --quick  median wall {med:6.1f} s over {a.repeat} "
                     f"(cpu {statistics.median(r['cpu_s'] for r in quick):6.1f} s, "
                     f"{quick[0]['images']} images, load {quick[0]['load_before']:.1f}) target 20 s")
        print(lines[-1], flush=True)
        if not a.quick_only:
            full = run_once(preset, False, a.threads, work)
            results["runs"][f"{preset}/full"] = {"wall_s": full["wall_s"], "target_s": 180.0,
                                                 "runs": [full]}
            lines.append(f"{preset:8s} full     wall {full['wall_s']:6.1f} s "
                         f"(cpu {full['cpu_s']:6.1f} s, {full['images']} images, "
                         f"{full['bytes'] / 1e6:.0f} MB, load {full['load_before']:.1f}) target 180 s")
            print(lines[-1], flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    # keep the figures of runs not repeated this time (e.g. the full demo after --quick-only)
    old = RESULTS / "render.json"
    if old.is_file():
        try:
            prev = json.loads(old.read_text()).get("runs", {})
        except json.JSONDecodeError:
            prev = {}
        results["runs"] = {**prev, **results["runs"]}
    (RESULTS / "render.json").write_text(json.dumps(results, indent=2) + "\n")
    txt = []
    for key, r in sorted(results["runs"].items()):
        runs = r["runs"]
        wall = r.get("median_wall_s", r.get("wall_s"))
        cpu = statistics.median(x["cpu_s"] for x in runs)
        txt.append(f"{key:16s} wall {wall:6.1f} s (median of {len(runs)}), cpu {cpu:6.1f} s, "
                   f"{runs[0]['images']} images, load avg {runs[0]['load_before']:.1f}, "
                   f"target {r['target_s']:.0f} s")
    (RESULTS / "render.txt").write_text("\n".join(txt) + "\n")
    if a.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

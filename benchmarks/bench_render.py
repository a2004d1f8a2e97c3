"""Render-speed figures of the virtual rig: the --quick capture and the full paper demo.

Every render runs in a child process of this script, which is made a *child subreaper*
(Linux ``prctl(PR_SET_CHILD_SUBREAPER)``): the renderer's forkserver and its workers, orphaned
when the render's process ends, are re-parented to this script and reaped here, so
``RUSAGE_CHILDREN`` holds the user + system CPU seconds of the whole process tree of that
render and of nothing else. That figure does not depend on what else runs on the machine;
the wall time does, so the load average is printed beside it (and the machine-wide busy
CPU seconds from /proc/stat, for comparison with older figures). The figures to meet
(issue 2): --quick within 20 s and the full paper demo (all calibration images, 4 scans of
>= 300 frames) within 3 minutes on a 2-core machine.

Prints medians (wall, tree CPU, images/s) and writes benchmarks/results/render.json and
render.txt (figures of runs not repeated this time are kept).

    python benchmarks/bench_render.py                 # quick x3 (median) + full paper once
    python benchmarks/bench_render.py --quick-only
    python benchmarks/bench_render.py --presets paper compact --threads 2
    python benchmarks/bench_render.py --quick-only --threads 1 --repeat 1 --tag t1
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from crossline.io.capture import check_capture  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
PR_SET_CHILD_SUBREAPER = 36

RENDER = """
import sys
from crossline.sim import simulate
simulate(sys.argv[1], preset=sys.argv[2], quick=sys.argv[3] == "quick", threads=int(sys.argv[4]),
         progress=False)
"""


def _subreaper() -> bool:
    """Make this process the reaper of its orphaned descendants (Linux); True on success."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _machine_cpu() -> float:
    """Busy CPU seconds of the whole machine (user + system, all cores) from /proc/stat."""
    try:
        ticks = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
        busy = sum(int(t) for i, t in enumerate(ticks) if i not in (3, 4))  # not idle, iowait
        return busy / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return float("nan")


def _children_cpu() -> tuple[float, float]:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime, r.ru_stime


def _reap_all() -> None:
    """Wait for every remaining descendant (the orphaned forkserver and its children)."""
    while True:
        try:
            os.waitpid(-1, 0)
        except ChildProcessError:
            return


def run_once(preset: str, quick: bool, threads: int, work: Path, src: Path = ROOT) -> dict:
    """Render one capture in a child process (the crossline package of ``src``); its figures."""
    out = work / f"{preset}-{'quick' if quick else 'full'}"
    shutil.rmtree(out, ignore_errors=True)
    load0 = os.getloadavg()[0]
    _reap_all()
    c0, m0, t0 = _children_cpu(), _machine_cpu(), time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", RENDER, str(out), preset,
                           "quick" if quick else "full", str(threads)], cwd=src)
    wall = time.perf_counter() - t0
    _reap_all()
    c1 = _children_cpu()
    user, system = c1[0] - c0[0], c1[1] - c0[1]
    cpu = user + system
    machine = _machine_cpu() - m0
    if proc.returncode:
        raise SystemExit(f"render failed with exit code {proc.returncode}")
    summary = check_capture(out, images=False)
    n_images = (sum(summary["views"].values()) + sum(summary["views"][k] for k in ("laser_A", "laser_B"))
                + sum(s["frames"] for s in summary["scans"].values()))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    shutil.rmtree(out, ignore_errors=True)
    return {"wall_s": wall, "cpu_s": cpu, "user_s": user, "sys_s": system,
            "machine_cpu_s": machine, "images": n_images,
            "images_per_s": n_images / wall, "cpu_ms_per_image": 1e3 * cpu / n_images,
            "frames_per_scan": {k: s["frames"] for k, s in summary["scans"].items()},
            "bytes": size, "load_before": load0, "load_after": os.getloadavg()[0]}


def _line(key: str, r: dict) -> str:
    runs = r["runs"]
    med = {k: statistics.median(x.get(k, float("nan")) for x in runs)
           for k in ("wall_s", "cpu_s", "sys_s", "images_per_s")}
    mach = statistics.median(x.get("machine_cpu_s", float("nan")) for x in runs)
    load = statistics.median(x["load_before"] for x in runs)
    return (f"{key:22s} wall {med['wall_s']:6.1f} s, cpu {med['cpu_s']:6.1f} s (process tree; "
            f"sys {med['sys_s']:4.1f} s), "
            f"{runs[0]['images']} images, {med['images_per_s']:5.2f} images/s, "
            f"median of {len(runs)}, load avg {load:.1f}, machine cpu {mach:6.1f} s, "
            f"threads {r.get('threads', '?')}, target {r['target_s']:.0f} s")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["paper"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3, help="repeats of --quick (median reported)")
    ap.add_argument("--quick-only", action="store_true")
    ap.add_argument("--full-only", action="store_true")
    ap.add_argument("--tag", default="", help="suffix of the result keys (e.g. t1 for --threads 1)")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temp dir)")
    ap.add_argument("--src", type=Path, default=ROOT,
                    help="folder holding the crossline package to time (e.g. an export of an "
                         "older commit: git archive HEAD crossline | tar -x -C /tmp/old)")
    a = ap.parse_args(argv)
    if not _subreaper():
        print("warning: not a child subreaper: the CPU figures miss the render's workers",
              file=sys.stderr)
    work = a.work or Path(tempfile.mkdtemp(prefix="crossline-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    results: dict = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                 "platform": platform.platform()},
                     "cpu_measure": "user+sys of the render's process tree (subreaper, RUSAGE_CHILDREN)",
                     "runs": {}}
    tag = f"/{a.tag}" if a.tag else ""
    for preset in a.presets:
        if not a.full_only:
            quick = [run_once(preset, True, a.threads, work, a.src) for _ in range(a.repeat)]
            key = f"{preset}/quick{tag}"
            results["runs"][key] = {"median_wall_s": statistics.median(r["wall_s"] for r in quick),
                                    "median_cpu_s": statistics.median(r["cpu_s"] for r in quick),
                                    "threads": a.threads, "target_s": 20.0, "src": str(a.src),
                                    "runs": quick}
            print(_line(key, results["runs"][key]), flush=True)
        if not a.quick_only:
            full = run_once(preset, False, a.threads, work, a.src)
            key = f"{preset}/full{tag}"
            results["runs"][key] = {"median_wall_s": full["wall_s"], "median_cpu_s": full["cpu_s"],
                                    "threads": a.threads, "target_s": 180.0, "src": str(a.src),
                                    "runs": [full]}
            print(_line(key, results["runs"][key]) + f", {full['bytes'] / 1e6:.0f} MB", flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    old = RESULTS / "render.json"
    if old.is_file():
        try:
            prev = json.loads(old.read_text()).get("runs", {})
        except json.JSONDecodeError:
            prev = {}
        # older files measured the machine's CPU, not the render's: keep only comparable runs
        prev = {k: v for k, v in prev.items() if "median_cpu_s" in v}
        results["runs"] = {**prev, **results["runs"]}
    (RESULTS / "render.json").write_text(json.dumps(results, indent=2) + "\n")
    txt = [_line(k, r) for k, r in sorted(results["runs"].items())]
    (RESULTS / "render.txt").write_text("\n".join(txt) + "\n")
    if a.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

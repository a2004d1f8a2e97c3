"""Time the report rule (``crossline report``) on the paper demo capture; target <= 30 s.

Usage (from the repository root):

    python benchmarks/bench_report.py                 # data/{raw,interim,processed}/demo
    python benchmarks/bench_report.py --capture NAME  # another capture the workflow processed
    python benchmarks/bench_report.py --synthetic     # no demo yet: a synthetic capture of the
                                                      # demo's size (4 scans x 300 frames)

Each repetition runs the rule's command in a fresh process (imports included, as Snakemake
runs it); the median is the figure. One more in-process run splits the time into measuring
(``build_report``) and drawing (``render_pdf``). Results are printed and written to
``benchmarks/results/report.json`` and ``report.txt``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TARGET_S = 30.0


def _synthetic(root: Path, frames: int, rays: int) -> tuple[Path, Path, Path]:
    sys.path.insert(0, str(REPO))
    from crossline.fuse import run_fuse
    from tests.test_report_synthetic import make_capture

    raw, interim, processed = root / "raw" / "synthetic", root / "interim", root / "processed"
    t = time.perf_counter()
    make_capture(raw, interim, frames=frames, rays=rays, noise=0.004)
    for pq in sorted((interim / "points").glob("*.parquet")):
        run_fuse(pq, processed / f"{pq.stem}.ply", stats=processed / f"{pq.stem}.fuse.json")
    print(f"synthetic capture ({frames} frames, {rays} rays per stripe) built in "
          f"{time.perf_counter() - t:.1f} s")
    return raw, interim, processed


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; return 0 if the median meets the target."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", default="demo", help="capture name under data/ (default demo)")
    ap.add_argument("--synthetic", action="store_true", help="time a synthetic demo-sized capture")
    ap.add_argument("--dirs", nargs=3, type=Path, metavar=("RAW", "INTERIM", "PROCESSED"),
                    help="a processed capture elsewhere: its folder, interim and processed folders")
    ap.add_argument("--frames", type=int, default=300, help="synthetic: frames per scan")
    ap.add_argument("--rays", type=int, default=2000, help="synthetic: points per stripe")
    ap.add_argument("--repeat", type=int, default=3, help="runs of the rule (default 3)")
    ap.add_argument("--config-json", default=None, help="the rule's --config-json (optional)")
    a = ap.parse_args(argv)

    tmp = None
    raw = REPO / "data" / "raw" / a.capture
    interim = REPO / "data" / "interim" / a.capture
    processed = REPO / "data" / "processed" / a.capture
    if a.dirs:
        raw, interim, processed = a.dirs
        source = str(raw)
    elif a.synthetic or not (raw / "rig.yaml").is_file() or not processed.is_dir():
        if not a.synthetic:
            print(f"no processed capture '{a.capture}' under data/: timing a synthetic one")
        tmp = tempfile.TemporaryDirectory(prefix="bench_report_")
        raw, interim, processed = _synthetic(Path(tmp.name), a.frames, a.rays)
        source = f"synthetic ({a.frames} frames x {a.rays} rays per stripe, 4 scans)"
    else:
        source = f"data/raw/{a.capture}"
    out = Path(tempfile.mkdtemp(prefix="bench_report_out_"))
    cmd = [sys.executable, "-m", "crossline.cli", "report", str(raw), "--interim", str(interim),
           "--processed", str(processed), "--pdf", str(out / "accuracy.pdf"),
           "--metrics", str(out / "metrics.json")]
    if a.config_json:
        cmd += ["--config-json", a.config_json]
    times, cpu = [], []
    for i in range(a.repeat):
        t = time.perf_counter()
        c0 = os.times()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       env={**os.environ, "PYTHONHASHSEED": "0"})
        c1 = os.times()
        times.append(time.perf_counter() - t)
        # CPU time of the child: what the rule costs when the machine is shared
        cpu.append((c1.children_user - c0.children_user) + (c1.children_system - c0.children_system))
        print(f"run {i + 1}: {times[-1]:.2f} s wall, {cpu[-1]:.2f} s CPU")

    from crossline.report.accuracy import build_report
    from crossline.report.pages import render_pdf

    t = time.perf_counter()
    data = build_report(raw, interim, processed, a.config_json)
    t_build = time.perf_counter() - t
    t = time.perf_counter()
    render_pdf(data, out / "again.pdf")
    t_render = time.perf_counter() - t
    points = {n: s.get("cloud_points") for n, s in data.metrics["scans"].items()}
    med = statistics.median(times)
    res = {
        "benchmark": "report rule (crossline report)",
        "source": source,
        "repeat": a.repeat,
        "times_s": [round(x, 3) for x in times],
        "median_s": round(med, 3),
        "cpu_s": [round(x, 3) for x in cpu],
        "median_cpu_s": round(statistics.median(cpu), 3),
        "target_s": TARGET_S,
        "meets_target": med <= TARGET_S,
        "in_process_build_s": round(t_build, 3),
        "in_process_render_s": round(t_render, 3),
        "points_per_scan": points,
        "pages_pdf_bytes": (out / "accuracy.pdf").stat().st_size,
        "identical_bytes": (out / "accuracy.pdf").read_bytes() == (out / "again.pdf").read_bytes(),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                    "platform": platform.platform()},
    }
    lines = [
        f"report rule on {source}",
        f"  runs: {', '.join(f'{x:.2f}' for x in times)} s; median {med:.2f} s "
        f"(target <= {TARGET_S:.0f} s: {'met' if res['meets_target'] else 'NOT met'})",
        f"  CPU per run: {', '.join(f'{x:.2f}' for x in cpu)} s (median "
        f"{statistics.median(cpu):.2f} s; wall > CPU when other jobs share the cores)",
        f"  in process: measure {t_build:.2f} s, draw {t_render:.2f} s",
        f"  points per scan: {points}",
        f"  same bytes as the rule's PDF: {res['identical_bytes']}",
    ]
    print("\n".join(lines))
    results = REPO / "benchmarks" / "results"
    results.mkdir(parents=True, exist_ok=True)
    (results / "report.json").write_text(json.dumps(res, indent=2) + "\n")
    (results / "report.txt").write_text("\n".join(lines) + "\n")
    if tmp is not None:
        tmp.cleanup()
    return 0 if res["meets_target"] else 1


if __name__ == "__main__":
    sys.exit(main())

"""The ball bar's sphere-spacing error SD (ISO 10360-8) against the truth, through the workflow's stages.

For each rig, a quick capture with the ball bar (``crossline simulate --quick --ball-bar``:
three positions, ``bar_1`` and ``bar_2`` level and turned by 60°, ``bar_3`` turned again and
inclined by 15°), calibrated from its own views (``calibrate-camera``, ``calibrate-lasers``,
``calibrate-handeye``), every bar scan through ``extract-stripes``, ``triangulate``, ``fuse``
(pose refinement on) and ``report``, as the workflow runs them (config.yaml's defaults), each
through the CLI in this process. Printed per position: SD as the report checks it (distance −
the bar's nominal length), its U (k = 2), the error against the TRUE distance of the two true
centres and E_n = error / U, each ball's size error and form; then the largest |SD| over the
positions, which is what an acceptance test compares with MPE_SD.

    python benchmarks/bench_ball_bar.py                       # paper and compact, ~6 min
    python benchmarks/bench_ball_bar.py --rigs random-small:1

Results: benchmarks/results/ball_bar.txt and .json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
CACHE = HERE / ".cache" / "ball_bar"
sys.path[:0] = [str(REPO), str(HERE)]


def run_rig(preset: str, seed: int) -> dict:
    """Render, calibrate, scan and report one rig; the report's metrics."""
    from crossline.cli import main
    from crossline.io.capture import read_rig
    from crossline.sim import simulate

    work = CACHE / f"{preset}-{seed}"
    cap = work / "capture"
    if not (cap / "rig.yaml").is_file():
        simulate(cap, preset=preset, seed=seed, quick=True, ball_bar=True, threads=2, progress=False,
                 scans=["bar_1", "bar_2", "bar_3"])
    cal, interim, processed = work / "interim" / "calibration", work / "interim", work / "processed"
    steps = [
        ["calibrate-camera", str(cap), "--out", str(cal / "camera.json"), "--threads", "2"],
        ["calibrate-lasers", str(cap), "--camera", str(cal / "camera.json"), "--out",
         str(cal / "lasers.json"), "--threads", "2"],
        ["calibrate-handeye", str(cap), "--camera", str(cal / "camera.json"), "--out",
         str(cal / "handeye.json"), "--threads", "2"],
    ]
    for s in sorted(read_rig(cap / "rig.yaml").scans):
        st, pts = interim / "stripes" / f"{s}.parquet", interim / "points" / f"{s}.parquet"
        steps += [
            ["extract-stripes", str(cap), s, "--out", str(st), "--threads", "2"],
            ["triangulate", str(cap), s, "--stripes", str(st), "--camera", str(cal / "camera.json"),
             "--lasers", str(cal / "lasers.json"), "--handeye", str(cal / "handeye.json"), "--out", str(pts)],
            ["fuse", str(pts), "--out", str(processed / f"{s}.ply"), "--stats",
             str(processed / f"{s}.fuse.json"), "--refine-poses", "true",
             "--frames", str(cap / "scans" / s / "frames.csv"), "--threads", "2",
             "--arm-draws", "64", "--arm-draws-out", str(processed / f"{s}.arm.npz")],
        ]
    steps.append(["report", str(cap), "--interim", str(interim), "--processed", str(processed),
                  "--pdf", str(work / "accuracy.pdf"), "--metrics", str(work / "metrics.json")])
    for argv in steps:
        if main(argv) != 0:
            raise SystemExit(f"stage failed: crossline {' '.join(argv)}")
    return json.loads((work / "metrics.json").read_text())


def rows(name: str, m: dict) -> tuple[list[str], dict]:
    """Lines of the table for one rig, and its figures."""
    out, figs = [], {}
    um = 1000.0
    for scan in sorted(k for k, s in m["scans"].items() if s["artefact"] == "ball_bar"):
        s = m["scans"][scan]
        if "measurement" not in s:
            out.append(f"  {name:13s} {scan:6s} FAILED: {s.get('error')}")
            continue
        meas, t = s["measurement"], s.get("truth") or {}
        fig = ((s.get("uncertainty") or {}).get("figures") or {}).get("length_mm") or {}
        U = fig.get("U")
        err = t.get("length_error_mm")
        en = err / U if err is not None and U else None
        sizes = [b["size_error_mm"] * um for b in meas["balls"]]
        forms = [b["form_error_mm"] * um for b in meas["balls"]]
        figs[scan] = {"sd_mm": meas["length_error_mm"], "U_mm": U, "error_vs_truth_mm": err, "E_n": en,
                      "size_errors_mm": [x / um for x in sizes], "form_errors_mm": [x / um for x in forms],
                      "length_mm": meas["length_mm"], "nominal_mm": meas["nominal_length_mm"]}
        def fmt(x: float | None, f: str = "+7.1f") -> str:
            return format(x, f) if x is not None else "      -"

        cells = [f"{meas['nominal_length_mm']:8.3f}", fmt(meas["length_error_mm"] * um),
                 fmt(U * um if U else None, "7.1f"), fmt(err * um if err is not None else None),
                 fmt(en, "+6.2f")]
        out.append(f"  {name:13s} {scan:6s} {' '.join(cells)}   {sizes[0]:+6.1f} {sizes[1]:+6.1f}   "
                   f"{forms[0]:5.1f} {forms[1]:5.1f}")
    if figs:
        worst = max(figs.values(), key=lambda f: abs(f["sd_mm"]))
        out.append(f"  {name:13s} largest |SD| over {len(figs)} positions: {abs(worst['sd_mm']) * um:.1f} um")
    return out, figs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rigs", default="paper:0,compact:0", help="preset:seed, comma separated")
    a = ap.parse_args(argv)
    from run_all import machine

    t0 = time.perf_counter()
    lines = [
        "Ball bar (ISO 10360-8 sphere-spacing error SD): quick captures with crossline simulate --ball-bar,",
        "calibrated from their own views, each bar position scanned, fused (pose refinement) and reported",
        "with config.yaml's defaults. SD = distance of the two least-squares spheres' centres - nominal",
        "length; U its Monte Carlo expanded uncertainty (k = 2); error = distance - the TRUE centres'",
        "distance; E_n = error / U. Sizes: each ball's diameter - nominal; form: range of radial residuals.",
        f"machine: {machine()}",
        "  rig           scan    nominal   SD(um)  U(um) err(um)    E_n   size 1/2 (um)  form 1/2 (um)",
    ]
    results = {}
    for spec in (x for x in a.rigs.split(",") if x):
        preset, _, seed = spec.partition(":")
        name = f"{preset}-{seed or 0}"
        m = run_rig(preset, int(seed or 0))
        table, figs = rows(name, m)
        lines += table
        results[name] = figs
        print("\n".join(table), flush=True)
    lines.append(f"wall {time.perf_counter() - t0:.0f} s")
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "ball_bar.txt").write_text("\n".join(lines) + "\n")
    (RESULTS / "ball_bar.json").write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())

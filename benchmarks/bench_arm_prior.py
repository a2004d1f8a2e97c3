"""The pose refinement's arm prior: the stated precision (config's 0.02 mm) against ``auto`` (the
arm's noise that the hand-eye calibration estimated from its views), on random rigs.

Reads the workflow run of ``bench_rigs.py`` (its cache, benchmarks/.cache/rigs/work: run that
first with the same seeds), whose fuse stage used config.yaml's ``fuse.arm_precision_mm``; fuses
every scan of each rig again with ``--arm-precision-mm auto`` and the rig's own handeye.json,
builds the report again from those clouds (the stages before fuse are the workflow's), and
prints per rig: the arm's true noise per axis (truth.json), the prior each way, and the figures
of bench_rigs.py that the poses move (gauge, plate, sphere, freeform) with the stated prior ->
with auto, and each report's E_n (error / U) of the ball's diameter and the gauge's height.

Usage: python benchmarks/bench_arm_prior.py [--seeds 0-19] [--jobs 2]
Writes benchmarks/results/arm_prior.txt and arm_prior.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import yaml

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_rigs import CACHE, REPO, RESULTS, figures, parse_seeds  # noqa: E402

from crossline.fuse import arm_prior  # noqa: E402

OUT = HERE / ".cache" / "arm_prior"
FIGURES = ("gauge_bias_um", "gauge_sigma_um", "plate_within_pct", "sphere_size_um", "sphere_form_um",
           "freeform_rms_um")
SECTIONS = ("camera", "lasers", "handeye", "stripes", "points", "fuse", "report")  # the report's


def say(text: str = "") -> None:
    print(text, flush=True)


def rerun(name: str, cfg: dict[str, Any]) -> Path:
    """Fuse every scan of ``name`` with the prior ``auto``, then its report; returns its folder."""
    wd, out = CACHE / "work", OUT / name
    interim, raw, fu = wd / "data" / "interim" / name, wd / "data" / "raw" / name, cfg["fuse"]
    out.mkdir(parents=True, exist_ok=True)
    (out / "processed").mkdir(exist_ok=True)
    handeye = interim / "calibration" / "handeye.json"
    for points in sorted((interim / "points").glob("*.parquet")):
        s = points.stem
        subprocess.run([
            "crossline", "fuse", str(points), "--out", str(out / "processed" / f"{s}.ply"),
            "--stats", str(out / "processed" / f"{s}.fuse.json"),
            "--neighbours", str(fu["neighbours"]), "--std-ratio", str(fu["std_ratio"]),
            "--voxel-mm", str(fu["voxel_mm"]), "--normal-radius-mm", str(fu["normal_radius_mm"]),
            "--refine-poses", str(fu["refine_poses"]).lower(),
            "--frames", str(raw / "scans" / s / "frames.csv"), "--handeye", str(handeye),
            "--arm-precision-mm", "auto", "--arm-precision-rad", str(fu["arm_precision_rad"]),
            "--arm-smooth-fraction", str(fu["arm_smooth_fraction"]),
            "--arm-corr-time-s", str(fu["arm_corr_time_s"]),
            "--crossing-half-mm", str(fu["crossing_half_mm"]),
            "--crossing-min-angle-deg", str(fu["crossing_min_angle_deg"]),
            "--crossing-max-width-ratio", str(fu["crossing_max_width_ratio"]),
            "--arm-draws", str(fu["arm_draws"]), "--arm-draws-out", str(out / "processed" / f"{s}.arm.npz"),
        ], check=True, capture_output=True)
    rc = {k: cfg[k] for k in SECTIONS}
    rc["fuse"] = {**cfg["fuse"], "arm_precision_mm": "auto"}
    subprocess.run(["crossline", "report", str(raw), "--interim", str(interim), "--processed",
                    str(out / "processed"), "--config-json", json.dumps(rc), "--pdf",
                    str(out / "accuracy.pdf"), "--metrics", str(out / "metrics.json"),
                    "--deviation-dir", str(out / "deviation")], check=True, capture_output=True)
    return out


def coverage(metrics: dict[str, Any]) -> dict[str, float]:
    """E_n = error / U of every figure the report checks against truth."""
    return {f"{s}/{k}": v["E_n"] for s, scan in (metrics.get("scans") or {}).items()
            for k, v in ((scan.get("truth") or {}).get("uncertainty_coverage") or {}).items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-19")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args(argv)
    cfg = yaml.safe_load((REPO / "config.yaml").read_text())
    names = [f"random-small-{s}" for s in parse_seeds(a.seeds)]
    missing = [n for n in names if not (CACHE / "work" / "reports" / n / "metrics.json").is_file()]
    if missing:
        say(f"no bench_rigs.py run for {', '.join(missing)}: run benchmarks/bench_rigs.py first")
        return 1
    t0 = time.perf_counter()
    with ThreadPoolExecutor(a.jobs) as ex:
        dirs = dict(zip(names, ex.map(lambda n: rerun(n, cfg), names), strict=True))
    wall = time.perf_counter() - t0
    lines = [f"{len(names)} rigs of bench_rigs.py's cache (quick captures), fuse and report again with "
             f"fuse.arm_precision_mm auto ({wall:.0f} s); the stated prior is config.yaml's "
             f"{cfg['fuse']['arm_precision_mm']} mm",
             "rig: the arm's true sigma per axis (truth.json) | the prior's sigma per axis, stated -> auto "
             "(um) | figure stated -> auto | E_n stated -> auto"]
    rows = {}
    for n in names:
        cap = CACHE / "work" / "data" / "raw" / n
        rig = yaml.safe_load((cap / "rig.yaml").read_text())
        truth = json.loads((cap / "truth.json").read_text())["arm_noise"]
        old = json.loads((CACHE / "work" / "reports" / n / "metrics.json").read_text())
        new = json.loads((dirs[n] / "metrics.json").read_text())
        fo, fn = figures(old, rig), figures(new, rig)
        prior = {}
        for tag, d in (("stated", CACHE / "work" / "data" / "processed" / n),
                       ("auto", dirs[n] / "processed")):
            st = json.loads(next(iter(sorted(d.glob("*.fuse.json")))).read_text())
            known = (st.get("arm_prior") or {}).get("sigma_mm")  # absent in fuse runs before 123680e
            if known is None:
                known = arm_prior(cfg["fuse"]["arm_precision_mm"])[0].sigma_mm
            prior[tag] = known
        co, cn = coverage(old), coverage(new)
        rows[n] = {"arm_sigma_mm": truth["sigma_axis_mm"], "prior_sigma_mm": prior,
                   "stated": fo, "auto": fn, "E_n": {"stated": co, "auto": cn}}
        figs = " ".join(f"{k.rsplit('_', 1)[0]} {fo.get(k, float('nan')):.1f}>{fn.get(k, float('nan')):.1f}"
                        for k in FIGURES)
        en = " ".join(f"{k} {co[k]:+.2f}>{cn.get(k, float('nan')):+.2f}" for k in co)
        lines.append(f"{n:16s} arm {1e3 * truth['sigma_axis_mm']:5.1f} | prior {1e3 * prior['stated']:5.1f}>"
                     f"{1e3 * prior['auto']:5.1f} | {figs} | {en}")
    for ln in lines:
        say(ln)
    tag = "" if a.seeds == "0-19" else "_" + a.seeds
    (RESULTS / f"arm_prior{tag}.txt").write_text("\n".join(lines) + "\n")
    (RESULTS / f"arm_prior{tag}.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Does the report's U cover the truth? Coverage of the Monte Carlo uncertainty (issue 20.1).

Independently seeded quick captures of one rig (`crossline simulate --preset paper --seed N
--quick --scans gauge,plate,ball` by default) go through the whole workflow; each report's
`metrics.json` gives every figure's expanded uncertainty U (k = 2) and, from `truth.json`,
its true error. A figure's coverage is the share of captures whose |error| <= U: for an
honest U about 95 %, and the issue asks for 90-99 % (too wide is as wrong as too narrow).
`z = error / u` should then scatter with a standard deviation near 1.

Only figures with a true value are scored: the gauge block's mean height and the ball's
diameter. A plate's flatness and a ball's form error are 0 in truth and their measured values
are noise statistics, so no interval around them can cover 0 in the GUM sense.

Usage: python benchmarks/bench_uncertainty.py [--seeds 0-19] [--preset paper] [--cores 2]
       [--score-only]  (the last run's reports scored again)
Writes benchmarks/results/uncertainty.txt and uncertainty.json.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_rigs import parse_seeds, render, run_workflow  # noqa: E402

from crossline.report.scan_truth import uncertainty_coverage  # noqa: E402

CACHE = HERE / ".cache" / "uncertainty"
RESULTS = HERE / "results"

# figure -> (scan, Monte Carlo figure): scored as the report's validation scores it
SCORED = {
    "gauge_height": ("gauge", "mean_mm"),
    "sphere_diameter": ("ball", "diameter_mm"),
}


def score(metrics: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Per scored figure: the true error, u, U and whether |error| <= U (NaN: not measured), as
    the report's validation scores it (crossline.report.scan_truth.uncertainty_coverage)."""
    out = {}
    for name, (scan, fig) in SCORED.items():
        s = (metrics.get("scans") or {}).get(scan) or {}
        f = ((s.get("uncertainty") or {}).get("figures") or {}).get(fig) or {}
        c = uncertainty_coverage(s.get("truth") or {}, {fig: f}).get(fig)
        if c is None:
            out[name] = {"error_um": math.nan, "u_um": math.nan, "U_um": math.nan,
                         "covered": math.nan, "dominant": None}
            continue
        out[name] = {"error_um": 1e3 * c["error_mm"], "u_um": 1e3 * f["u"], "U_um": 1e3 * c["U_mm"],
                     "covered": float(c["covered"]), "dominant": f["dominant"],
                     "budget_um": {k: 1e3 * b["u"] for k, b in f["budget"].items()}}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-19", help="seeds, e.g. 0-19 or 3,5,8")
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--score-only", action="store_true",
                    help="score the reports of the last run again, without rendering or running")
    a = ap.parse_args(argv)
    seeds = parse_seeds(a.seeds)
    if a.score_only:
        caps = {f"{a.preset}-{s}": CACHE / "captures" / f"{a.preset}-{s}" for s in seeds}
        wd = CACHE / "work"
        wall = json.loads((RESULTS / "uncertainty.json").read_text())["wall_s"]
    else:
        caps = render(seeds, quick=True, preset=a.preset, cache=CACHE,
                      scans=["gauge", "plate", "ball"])
        wd, wall = run_workflow(caps, a.cores, cache=CACHE)
    rows = {}
    for name in caps:
        mpath = wd / "reports" / name / "metrics.json"
        rows[name] = score(json.loads(mpath.read_text())) if mpath.is_file() else None
    lines = [f"{len(caps)} quick captures of --preset {a.preset}, seeds {a.seeds}; workflow wall "
             f"{wall:.0f} s on {a.cores} cores. Per figure: true error, U (k = 2), covered "
             "(|error| <= U); in µm",
             "capture      " + "".join(f"{k:>34}" for k in SCORED)]
    for name, row in rows.items():
        if row is None:
            lines.append(f"{name:<12} no report (see {wd / 'snakemake.log'})")
            continue
        cells = []
        for k in SCORED:
            r = row[k]
            cov = {1.0: "yes", 0.0: "no"}.get(r["covered"], "-")
            cells.append(f"{r['error_um']:+9.2f} {r['U_um']:8.2f} {cov:>4} {str(r['dominant'])[:10]:>10}")
        lines.append(f"{name:<12} " + "".join(f"{c:>34}" for c in cells))
    summary = {}
    for k in SCORED:
        got = [r[k] for r in rows.values() if r is not None and math.isfinite(r[k]["covered"])]
        if not got:
            summary[k] = {"n": 0}
            continue
        z = np.array([g["error_um"] / g["u_um"] for g in got if g["u_um"] > 0])
        summary[k] = {"n": len(got), "coverage": float(np.mean([g["covered"] for g in got])),
                      "z_mean": float(z.mean()) if z.size else math.nan,
                      "z_std": float(z.std(ddof=1)) if z.size > 1 else math.nan,
                      "median_U_um": float(np.median([g["U_um"] for g in got])),
                      "median_budget_um": {c: float(np.median([g["budget_um"][c] for g in got]))
                                           for c in got[0]["budget_um"]}}
        s = summary[k]
        ok = 0.90 <= s["coverage"] <= 0.99
        lines.append(f"{k}: coverage {100 * s['coverage']:.0f} % of {s['n']} (target 90-99 %: "
                     f"{'met' if ok else 'NOT met'}), z = error/u: mean {s['z_mean']:+.2f}, std "
                     f"{s['z_std']:.2f} (1 for an honest u), median U {s['median_U_um']:.2f} µm; "
                     "median u by contributor (µm): " + ", ".join(
                         f"{c} {v:.2f}" for c, v in s["median_budget_um"].items()))
    text = "\n".join(lines)
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "uncertainty.txt").write_text(text + "\n")
    (RESULTS / "uncertainty.json").write_text(json.dumps({"wall_s": wall, "rows": rows,
                                                          "summary": summary}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

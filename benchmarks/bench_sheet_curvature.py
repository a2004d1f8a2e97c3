"""The sheet-curvature correction against truth, the ball alone (issues 17.6 and 22.3).

For each rig (``--preset random-small --quick`` by default; ``--preset paper`` draws the
built-in rig with the seed), the ball scan is rendered alone; its
frames.csv is given the arm's true poses and the calibration is the true one (written from
truth.json), so that only the stripe centres can put the points off the ball. The centres are
extracted once (the workflow's Gaussian fit) and triangulated with and without the correction
(``points.sheet_curvature``). Printed per rig: the points' median radial residual against the
true sphere (all, per laser, per 10 degree elevation band), the report's sphere fit
(``measure_sphere``) diameter error, the sheet sigma found against the render's, and the
predicted shift against the centres' bias from the true centre lines (median px, column
profiles). ``--thin K`` renders the rig with its sheets K times as thick as drawn (the
cause's check: the bias goes as the sheet's variance).

Usage: python benchmarks/bench_sheet_curvature.py [--seeds 0,3,6,7,8] [--thin 0.35] [--preset paper]
Writes benchmarks/results/sheet_curvature.txt (_thin<K>.txt with --thin, _paper.txt with
--preset paper).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crossline.report.artefacts import measure_sphere  # noqa: E402
from crossline.scan.stripes import run_extract_stripes  # noqa: E402
from crossline.scan.triangulate import run_triangulate  # noqa: E402
from crossline.sim import simulate, write_true_calibration  # noqa: E402
from crossline.sim.random_rig import random_rig  # noqa: E402

CACHE = REPO / "benchmarks" / ".cache" / "sheet_curvature"
RESULTS = REPO / "benchmarks" / "results"


def _capture(seed: int, thin: float | None, preset: str = "random-small") -> Path:
    prefix = "rig" if preset == "random-small" else f"{preset}-"
    root = CACHE / (f"{prefix}{seed}" + ("" if thin is None else f"-thin{thin:g}"))
    cap = root / "cap"
    if (cap / "truth.json").is_file():
        return root
    shutil.rmtree(root, ignore_errors=True)
    rig = random_rig(seed, small=True) if preset == "random-small" else preset
    if thin is not None:
        thinner = {n: replace(las, waist_mm=las.waist_mm * thin) for n, las in rig.lasers.items()}
        rig = replace(rig, lasers=thinner)
    simulate(cap, rig, seed=seed, quick=True, scans=["ball"], parts=("scans",), progress=False)
    frames = pd.read_csv(cap / "scans/ball/frames.csv")
    tp = pd.read_parquet(cap / "truth/ball_poses.parquet").set_index("frame")
    for c in ("x", "y", "z", "qw", "qx", "qy", "qz"):
        frames[c] = tp.loc[frames["frame"], c].to_numpy()
    frames.to_csv(cap / "scans/ball/frames.csv", index=False)
    write_true_calibration(cap, root / "cal")
    run_extract_stripes(cap, "ball", root / "stripes.parquet", extractor="gaussian", threshold=0.10)
    return root


def _centre_line_errors(points: pd.DataFrame, lines: pd.DataFrame) -> np.ndarray:
    """Each column-profiled centre's row minus the true centre line's (NaN where unmatched)."""
    def key(df):
        return (df["frame"].astype(np.int64) * 10**6 + (df["laser"] == "B").astype(np.int64) * 10**5
                + df["u"].round().astype(np.int64)).to_numpy()
    tk = key(lines)
    o = np.argsort(tk, kind="stable")
    tk, tv = tk[o], lines["v"].to_numpy()[o]
    pk, pv = key(points), points["v"].to_numpy()
    i = np.searchsorted(tk, pk)
    err = np.full(len(points), np.nan)
    for k in range(3):
        j = np.clip(i + k, 0, len(tk) - 1)
        ok = (tk[j] == pk) & (np.abs(tv[j] - pv) < 2) & np.isnan(err)
        err[ok] = pv[ok] - tv[j][ok]
    return np.where(points["axis"].to_numpy() == 0, err, np.nan)


def run(seed: int, thin: float | None, preset: str = "random-small") -> list[str]:
    root = _capture(seed, thin, preset)
    cap, cal = root / "cap", root / "cal"
    truth = json.loads((cap / "truth.json").read_text())
    c = np.array(truth["scans"]["ball"]["center_base"])
    D = truth["scans"]["ball"]["diameter"]
    lines = pd.read_parquet(cap / "truth/ball_centrelines.parquet")
    lines = lines[(lines["surface"] == "ball") & lines["visible"]]
    out, pts = [], {}
    for on in (False, True):
        path = root / f"points_{'on' if on else 'off'}.parquet"
        meta = run_triangulate(cap, "ball", root / "stripes.parquet", cal / "camera.json",
                               cal / "lasers.json", cal / "handeye.json", path, smooth_px=7,
                               sheet_curvature=on)
        p = pd.read_parquet(path)
        pts[on] = p
        x = p[["x", "y", "z"]].to_numpy()
        r = np.linalg.norm(x - c, axis=1) - D / 2
        m = np.abs(r) < 0.2
        el = np.degrees(np.arcsin((x[:, 2] - c[2]) / np.linalg.norm(x - c, axis=1)))
        bands = " ".join(f"{lo}:{1e3 * np.median(r[m & (el >= lo) & (el < lo + 10)]):+.1f}"
                         for lo in range(0, 90, 10) if (m & (el >= lo) & (el < lo + 10)).sum() > 20)
        lasers = " ".join(f"{L} {1e3 * np.median(r[m & (p['laser'] == L).to_numpy()]):+.1f}"
                          for L in ("A", "B") if (m & (p["laser"] == L).to_numpy()).sum() > 20)
        try:
            fit = f"{1e3 * (2 * measure_sphere(x, D).radius - D):+.1f} um"
        except ValueError as exc:
            fit = f"none ({exc})"
        out.append(f"  {'corrected' if on else 'extracted'}: points {1e3 * np.median(r[m]):+.1f} um "
                   f"({lasers}), by elevation {bands}; sphere fit diameter {fit}")
        if on:
            sc = meta["sheet_curvature"]
            found = sc.get("sheet_sigma_mm", {})
            drawn = {k: truth["lasers"][k]["waist_mm"] / 2 for k in found}
            out.append("  sheet sigma found / drawn at its waist (mm): "
                       + " ".join(f"{k} {found[k]:.3f}/{drawn[k]:.3f}" for k in found)
                       + f"; blur {sc.get('blur_sigma_px')} px; {sc.get('points_moved')} centres moved")
    err = _centre_line_errors(pts[False], lines)
    pred = pts[False]["v"].to_numpy() - pts[True]["v"].to_numpy()
    same = pts[False]["u"].to_numpy() == pts[True]["u"].to_numpy()
    row = []
    for L in ("A", "B"):
        m = np.isfinite(err) & same & (pts[False]["laser"] == L).to_numpy()
        if m.sum() > 20:
            row.append(f"{L} {np.median(pred[m]):+.4f}/{np.median(err[m]):+.4f} px")
    out.append("  predicted shift / bias against the true centre lines: " + "  ".join(row))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,3,6,7,8")
    ap.add_argument("--thin", type=float, default=None, help="sheets this many times as thick")
    ap.add_argument("--preset", default="random-small", help="random-small (default) or paper")
    a = ap.parse_args()
    if a.thin is not None and a.preset != "random-small":
        ap.error("--thin draws a random rig anew; it needs --preset random-small")
    lines = [f"sheet-curvature correction, ball alone, true calibration and poses ({a.preset} quick)"
             + ("" if a.thin is None else f", sheets x{a.thin:g} as thick")]
    for s in (int(x) for x in a.seeds.split(",")):
        lines.append(f"{a.preset}-{s}")
        lines += run(s, a.thin, a.preset)
        print("\n".join(lines[-5:]), flush=True)
    RESULTS.mkdir(exist_ok=True)
    name = ("sheet_curvature" + ("" if a.thin is None else f"_thin{a.thin:g}")
            + ("" if a.preset == "random-small" else f"_{a.preset}") + ".txt")
    (RESULTS / name).write_text("\n".join(lines) + "\n")
    print(f"wrote {RESULTS / name}")


if __name__ == "__main__":
    main()

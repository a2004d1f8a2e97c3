"""The whole workflow on random rigs (issue 17.5): one row per rig against truth, then how
many rigs meet every target.

Each rig is drawn by the simulator (`crossline simulate OUT --preset random-small --seed N
--quick` by default: sensors up to 2.3 MP, so that twenty rigs fit in a benchmark run;
`--preset random` draws sensors of 1-12 MP, about 3-5 minutes per quick render here),
the workflow runs on all of them in one Snakemake call (`--keep-going`: a rig that fails a
stage is reported, not fatal), and the figures are read back from each report's
`metrics.json` (its validation part compares the estimates with `truth.json`).

Usage: python benchmarks/bench_rigs.py [--seeds 0-19] [--preset random-small] [--full] [--cores 2]
Writes benchmarks/results/rigs.txt and rigs.json (``--tag _x``: rigs_x.txt and rigs_x.json).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CACHE = HERE / ".cache" / "rigs"
RESULTS = HERE / "results"

# figure -> (target, how it is compared); the targets of issue 17.5
TARGETS: dict[str, tuple[float, str]] = {
    "camera_px": (0.02, "<="),
    "plane_deg": (0.005, "<="),
    "handeye_mm": (0.01, "<="),
    "gauge_bias_um": (3.0, "abs<="),
    "gauge_sigma_um": (6.0, "<="),
    "plate_within_pct": (99.0, ">="),
    "sphere_size_um": (10.0, "abs<="),
    "sphere_form_um": (30.0, "<="),
    "freeform_rms_um": (30.0, "<="),
}


def _get(d: Any, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _num(x: Any, scale: float = 1.0) -> float:
    return float(x) * scale if isinstance(x, int | float) and not isinstance(x, bool) else math.nan


def figures(metrics: dict[str, Any], rig: dict[str, Any]) -> dict[str, float]:
    """The benchmark's figures of one capture from its metrics.json (NaN where absent)."""
    v = metrics.get("validation") or {}
    out = {
        "camera_px": _num(_get(v, "camera", "rms_px")),
        "plane_deg": max((_num(_get(v, "lasers", L, "angle_deg")) for L in ("A", "B")
                          if _get(v, "lasers", L) is not None), default=math.nan),
        "handeye_mm": _num(_get(v, "handeye", "chosen", "rms_mm")),
    }
    kinds = {name: spec.get("artefact") for name, spec in (rig.get("scans") or {}).items()}
    for name, scan in (metrics.get("scans") or {}).items():
        kind = kinds.get(name)
        if kind == "gauge_block":
            out["gauge_bias_um"] = _num(_get(scan, "truth", "mean_error_mm"), 1e3)
            out["gauge_sigma_um"] = _num(_get(scan, "measurement", "std_mm"), 1e3)
        elif kind == "plane":
            share = _get(scan, "truth", "distance_to_true_plane", "share_within_band")
            out["plate_within_pct"] = _num(share, 100.0)
        elif kind == "sphere":
            out["sphere_size_um"] = _num(_get(scan, "truth", "diameter_error_mm"), 1e3)
            out["sphere_form_um"] = _num(_get(scan, "measurement", "form_error_mm"), 1e3)
        elif kind == "freeform":
            out["freeform_rms_um"] = _num(_get(scan, "truth", "deviation_to_true_mesh", "rms_mm"), 1e3)
    return out


def frame_free(metrics: dict[str, Any]) -> dict[str, float]:
    """Camera, plane and hand-eye figures after the camera frame's best rotation (metrics'
    ``frame_free``: what bends measured points), and that rotation; NaN where absent."""
    v = metrics.get("validation") or {}
    return {
        "camera_px": _num(_get(v, "camera", "frame_free", "rms_px")),
        "rotation_deg": _num(_get(v, "camera", "frame_free", "rotation_deg")),
        "plane_deg": max((_num(_get(v, "lasers", L, "frame_free", "angle_deg")) for L in ("A", "B")
                          if _get(v, "lasers", L, "frame_free") is not None), default=math.nan),
        "handeye_mm": _num(_get(v, "handeye", "chosen", "frame_free", "rms_mm")),
    }


def meets(name: str, value: float) -> bool | None:
    """Whether a figure meets its target (None when it was not measured)."""
    if not math.isfinite(value):
        return None
    target, how = TARGETS[name]
    if how == "<=":
        return value <= target
    if how == ">=":
        return value >= target
    return abs(value) <= target


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``0-19`` or ``3,5,8`` (ranges inclusive)."""
    seeds: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        seeds += list(range(int(lo), int(hi or lo) + 1))
    return seeds


def render(seeds: list[int], quick: bool, preset: str = "random-small", *, cache: Path = CACHE,
           scans: list[str] | None = None) -> dict[str, Path]:
    """Render (or reuse) one capture per seed (``scans``: a subset of the preset's); returns
    capture name -> folder."""
    caps = {}
    for seed in seeds:
        name = f"{preset}-{seed}{'' if quick else '-full'}"
        out = cache / "captures" / name
        if not (out / "rig.yaml").is_file():
            shutil.rmtree(out, ignore_errors=True)
            cmd = ["crossline", "simulate", str(out), "--preset", preset, "--seed", str(seed)]
            cmd += ["--quick"] if quick else []
            cmd += ["--scans", ",".join(scans)] if scans else []
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True, text=True)
            print(f"rendered {name} in {time.perf_counter() - t0:.0f} s", flush=True)
        caps[name] = out
    return caps


def run_workflow(caps: dict[str, Path], cores: int, cache: Path = CACHE) -> tuple[Path, float]:
    """All captures through the workflow in one Snakemake run; returns the workdir and wall time."""
    wd = cache / "work"
    wd.mkdir(parents=True, exist_ok=True)
    shutil.copy(REPO / "Snakefile", wd)
    for d in ("workflow", "profiles"):
        shutil.rmtree(wd / d, ignore_errors=True)
        shutil.copytree(REPO / d, wd / d, ignore=shutil.ignore_patterns("__pycache__"))
    cfg = yaml.safe_load((REPO / "config.yaml").read_text())
    cfg["captures"] = sorted(caps)
    cfg["simulate"] = {}
    (wd / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    raw = wd / "data" / "raw"
    raw.mkdir(parents=True, exist_ok=True)
    for name, path in caps.items():
        link = raw / name
        if not link.exists():
            link.symlink_to(path.resolve(), target_is_directory=True)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "snakemake", "--cores", str(cores), "--keep-going",
                           "--rerun-incomplete"],  # a run stopped half-way does not block the next
                          cwd=wd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    (wd / "snakemake.log").write_text(proc.stdout + proc.stderr)
    return wd, wall


def stripe_recall(capture: Path, interim: Path) -> dict[str, dict[str, float]]:
    """Per surface, over every scan: the true centre-line points lit and seen (truth/), how
    many of them an unflagged centre of the workflow's stripes lies within 5 px of (along the
    column, at the centre's rounded column: steep stripes' row centres included), and the RMS
    row error of the column-profiled ones within 2 px."""
    import numpy as np
    import pandas as pd

    win = yaml.safe_load((capture / "rig.yaml").read_text()).get("scan_window") or {}
    out: dict[str, dict[str, list]] = {}
    for tpath in sorted((capture / "truth").glob("*_centrelines.parquet")):
        scan = tpath.name.removesuffix("_centrelines.parquet")
        spath = interim / "stripes" / f"{scan}.parquet"
        if not spath.is_file() or not win:
            continue
        tl = pd.read_parquet(tpath)
        tl = tl[tl["visible"] & tl["lit"] & tl["unoccluded"]]
        st = pd.read_parquet(spath)
        st = st[st["flags"] == 0].assign(ui=lambda d: np.round(d["u"]).astype(np.int64))
        for L in ("A", "B"):
            t = tl[tl["laser"] == L][["frame", "u", "v", "surface"]].rename(columns={"v": "vt", "u": "ui"})
            m = st[st["lasers"].str.contains(L)].merge(t, on=["frame", "ui"])
            m["e"] = m["v"] - m["vt"]
            near = m[np.abs(m["e"]) < 5.0]
            found = near.drop_duplicates(["frame", "ui", "vt"])
            fine = near[(near["axis"] == 0) & (np.abs(near["e"]) < 2.0)]
            for surf, g in t.groupby("surface"):
                o = out.setdefault(surf, {"truth": 0, "found": 0, "e": []})
                o["truth"] += len(g)
                o["found"] += int((found["surface"] == surf).sum())
                o["e"].append(fine.loc[fine["surface"] == surf, "e"].to_numpy())
    res = {}
    for surf, o in out.items():
        e = np.concatenate(o["e"]) if o["e"] else np.empty(0)
        res[surf] = {"truth": o["truth"], "found": o["found"],
                     "rms_px": float(np.sqrt(np.mean(e**2))) if e.size else math.nan}
    return res


def _fmt(name: str, value: float) -> str:
    if not math.isfinite(value):
        return "    -   "
    ok = meets(name, value)
    return f"{value:7.3f}{' ' if ok else '*'}" if name.endswith(("px", "deg", "mm")) else \
        f"{value:7.1f}{' ' if ok else '*'}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-19", help="seeds, e.g. 0-19 or 3,5,8")
    ap.add_argument("--preset", default="random-small", help="random-small (default) or random")
    ap.add_argument("--full", action="store_true", help="full captures instead of --quick ones")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--tag", default="", help="suffix of the result files, e.g. _20-39")
    a = ap.parse_args(argv)
    seeds = parse_seeds(a.seeds)
    caps = render(seeds, quick=not a.full, preset=a.preset)
    wd, wall = run_workflow(caps, a.cores)
    rows: dict[str, dict[str, Any]] = {}
    for name, path in caps.items():
        rig = yaml.safe_load((path / "rig.yaml").read_text())
        mpath = wd / "reports" / name / "metrics.json"
        row: dict[str, Any] = {"rig": rig.get("description")}
        if mpath.is_file():
            m = json.loads(mpath.read_text())
            row["figures"], row["frame_free"], row["result"] = figures(m, rig), frame_free(m), m.get("result")
        else:
            row["figures"] = {k: math.nan for k in TARGETS}
            logs = sorted((wd / "logs" / name).rglob("*.log")) if (wd / "logs" / name).is_dir() else []
            errors = [ln for p in logs for ln in p.read_text(errors="replace").splitlines()
                      if ": error:" in ln]
            row["error"] = errors[0] if errors else "no report (see snakemake.log)"
        row["meets"] = {k: meets(k, row["figures"].get(k, math.nan)) for k in TARGETS}
        rows[name] = row
    kind = "full" if a.full else "quick"
    fresh = "Nothing to be done" in (wd / "snakemake.log").read_text(errors="replace")
    lines = [f"{len(caps)} rigs of --preset {a.preset} ({kind} captures), workflow wall "
             f"{wall:.0f} s on {a.cores} cores"
             + (" (every output was up to date: nothing rerun)" if fresh else "")
             + "; * = target missed, - = not measured",
             "targets: " + ", ".join(f"{k} {h} {t:g}" for k, (t, h) in TARGETS.items()),
             "rig          " + " ".join(f"{k[:8]:>8}" for k in TARGETS)]
    all_ok = 0
    for name, row in rows.items():
        f = row["figures"]
        lines.append(f"{name:<12} " + " ".join(_fmt(k, f.get(k, math.nan)) for k in TARGETS)
                     + (f"  ERROR {row['error']}" if "error" in row else ""))
        if all(v is not False for v in row["meets"].values()) and "error" not in row:
            all_ok += 1
    per = {k: sum(1 for r in rows.values() if r["meets"][k]) for k in TARGETS}
    measured = {k: sum(1 for r in rows.values() if r["meets"][k] is not None) for k in TARGETS}
    lines.append("met          " + " ".join(f"{per[k]:>4}/{measured[k]:<3}" for k in TARGETS))
    lines.append(f"rigs meeting every target they measure: {all_ok} of {len(rows)}")
    lines.append("the same after the camera frame's best rotation (the part of the camera error that bends "
                 "rays; planes and hand-eye turned by that rotation): camera_px plane_deg handeye_mm "
                 "rotation_deg")
    for name, row in rows.items():
        ff = row.get("frame_free") or {}
        lines.append(f"{name:<16} " + " ".join(
            _fmt(k, ff.get(k, math.nan)) for k in ("camera_px", "plane_deg", "handeye_mm"))
            + f" {ff.get('rotation_deg', math.nan):7.4f}")
    lines.append("does the report's expanded uncertainty U (k = 2) cover the error against truth? E_n = "
                 "error / U per scan and figure (|E_n| <= 1: covered; the report's validation)")
    covered = checked = 0
    for name in caps:
        mpath = wd / "reports" / name / "metrics.json"
        scans = json.loads(mpath.read_text()).get("scans", {}) if mpath.is_file() else {}
        cov = {f"{k}/{fig}": c for k, s in sorted(scans.items())
               for fig, c in ((s.get("truth") or {}).get("uncertainty_coverage") or {}).items()}
        rows[name]["coverage"] = cov
        covered += sum(c["covered"] for c in cov.values())
        checked += len(cov)
        lines.append(f"{name:<16} " + ("  ".join(
            f"{k} {1e3 * c['error_mm']:+.1f}/{1e3 * c['U_mm']:.1f} um = {c['E_n']:+.2f}"
            + ("" if c["covered"] else "*") for k, c in cov.items()) or "no U"))
    lines.append(f"U covers the error in {covered} of {checked} figures (* = not covered)")
    lines.append("A/B labels of the AB points against the true centre lines (the report's validation), "
                 "every scan: wrong / checked, and the laser states of its first frames")
    for name, path in caps.items():
        mpath = wd / "reports" / name / "metrics.json"
        scans = json.loads(mpath.read_text()).get("scans", {}) if mpath.is_file() else {}
        labels = {k: s.get("truth_labels") or {} for k, s in scans.items()}
        rows[name]["labels"] = labels
        frames = sorted((path / "scans").glob("*/frames.csv"))
        pattern = ",".join(dict.fromkeys(ln.split(",")[2] for ln in
                                         frames[0].read_text().splitlines()[1:7])) if frames else "?"
        lines.append(f"{name:<16} " + "  ".join(
            f"{k} {lab.get('wrong', '-')}/{lab.get('checked', '-')}" for k, lab in sorted(labels.items()))
            + f"  (states {pattern})")
    lines.append("stripe centres against the speckle limit of each rig's optics (the report's validation, "
                 "crossline.report.speckle), every scan and laser: achieved robust sigma / bound on one "
                 "profile = ratio, and the ratio to the bound after the centre lines' smoothing; then "
                 "the sensor's Cramer-Rao bound (shot, background and read noise) and the bound of "
                 "speckle and sensor together for each profile's width (stripe_bound_px), one profile "
                 "(smoothed, neighbouring profiles sharing grains) and the achieved sigma's ratio to it; "
                 "the lateral resolution the smoothing leaves: the points' spacing along the stripe and "
                 "the ripple it passes at half amplitude")
    for name in caps:
        parts = []
        for scan, lab in sorted((rows[name].get("labels") or {}).items()):
            for laser, sl in sorted((lab.get("speckle_limit") or {}).items()):
                part = (f"{scan}/{laser} {sl['achieved_sigma_px']:.3f}/{sl['bound_px']:.3f} px = "
                        f"{sl['ratio']:.2f}x ({sl['ratio_smoothed']:.2f}x)")
                if sl.get("ratio_combined") is not None:
                    part += (f", sensor {sl['sensor_bound_px']:.3f} px, bound "
                             f"{sl['combined_bound_px']:.3f} px ("
                             f"{sl['combined_bound_smoothed_px']:.3f}) = {sl['ratio_combined']:.2f}x "
                             f"({sl['ratio_combined_smoothed']:.2f}x)")
                if sl.get("spacing_mm") is not None and sl.get("half_amplitude_mm") is not None:
                    part += (f", spacing {sl['spacing_mm'] * 1e3:.0f} um, half amplitude at "
                             f"{sl['half_amplitude_mm']:.2f} mm")
                parts.append(part)
        lines.append(f"{name:<16} " + ("  ".join(parts) if parts else "no speckle figures"))
    lines.append("sphere form against what sets it: the range of n residuals is form / rms times their "
                 "RMS; the arm's pose noise per axis (truth.json) goes into the ball unrefined where its "
                 "scan has no A-B crossings (24 frames of a quick capture often have none)")
    lines.append(f"{'rig':<16} {'form':>6} {'vdi':>6} {'rms':>5} {'ratio':>5} {'n':>6} {'crossings':>9} "
                 f"{'arm':>5}  (um; arm = its sigma per axis)")
    for name, path in caps.items():
        mpath = wd / "reports" / name / "metrics.json"
        ball = json.loads(mpath.read_text()).get("scans", {}).get("ball", {}) if mpath.is_file() else {}
        me = ball.get("measurement") or {}
        ref = _get(ball, "counts", "fused", "pose_refinement") or {}
        arm = json.loads((path / "truth.json").read_text()).get("arm_noise", {})
        form, rms = _num(me.get("form_error_mm"), 1e3), _num(me.get("rms_mm"), 1e3)
        rows[name]["form"] = {"form_um": form, "form_vdi_um": _num(me.get("form_error_vdi_mm"), 1e3),
                              "rms_um": rms, "n": me.get("n"), "crossings": ref.get("crossings"),
                              "refinement_skipped": ref.get("skipped"),
                              "arm_sigma_axis_um": _num(arm.get("sigma_axis_mm"), 1e3)}
        fr = rows[name]["form"]
        cross = "skipped" if fr["refinement_skipped"] else str(fr["crossings"])
        lines.append(f"{name:<16} {form:6.1f} {fr['form_vdi_um']:6.1f} {rms:5.1f} {form / rms:5.1f} "
                     f"{fr['n'] or 0:6d} {cross:>9} {fr['arm_sigma_axis_um']:5.1f}")
    lines.append("stripe centres against the true centre lines (truth/*_centrelines.parquet: lit, seen, "
                 "not occluded), every scan: found = within 5 px of an unflagged centre; rms: row error "
                 "of the column-profiled ones within 2 px")
    for name, path in caps.items():
        rec = stripe_recall(path, wd / "data" / "interim" / name)
        rows[name]["stripes"] = rec
        lines.append(f"{name:<16} " + "  ".join(
            f"{surf} {r['found']}/{r['truth']} ({100 * r['found'] / max(r['truth'], 1):.0f} %, "
            f"{r['rms_px']:.3f} px)" for surf, r in sorted(rec.items())))
    text = "\n".join(lines)
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"rigs{a.tag}.txt").write_text(text + "\n")
    (RESULTS / f"rigs{a.tag}.json").write_text(json.dumps({"wall_s": wall, "rows": rows}, indent=1,
                                                  default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

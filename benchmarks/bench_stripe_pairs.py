"""Stripe centres beside another stripe and beside the frame's border, against truth.

    python benchmarks/bench_stripe_pairs.py

Prints, and writes to benchmarks/results/stripe_pairs.txt and .json:

- the Gaussian fit's mean centre error (px) of a stripe (sigma 2 px, 8-bit) whose centre
  lies 4, 6 and 8 rows from the frame's top border;
- the same for two stripes 10, 12 and 14 px apart in every column, of equal height and of
  heights 1 : 0.3 (the first, the second);
- on rendered quick captures (the paper rig, random rig 1; rendered once into
  benchmarks/.cache/stripe_pairs/), the RMS row error against the true centre lines
  (truth/<scan>_centrelines.parquet) of the column-profiled centres within 2 px of one,
  for centres flagged ``close`` (another stripe in the column within reach) and the others.

Run at another commit (copy the script there) to compare: the figures quoted in
docs/method.md before the border windows and the joint fit of close stripes were printed by
this script at c0e38ca (before both) and be90508 (border windows only).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from scipy.special import erf

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crossline.scan.stripes import CLOSE, gaussian, run_extract_stripes  # noqa: E402

CACHE = REPO / "benchmarks" / ".cache" / "stripe_pairs"
RESULTS = REPO / "benchmarks" / "results"
H, W, SIGMA = 120, 400, 2.0
CAPTURES = {"paper": (["--preset", "paper"], ["plate", "gauge", "ball", "part"]),
            "random-small-1": (["--preset", "random-small", "--seed", "1"], ["plate", "gauge"])}


def stripe_image(centres: list[np.ndarray], peaks: list[float], bg: float = 6.0) -> np.ndarray:
    """8-bit columns holding pixel-integrated Gaussian stripes centred on rows ``centres[k]``."""
    rows = np.arange(H, dtype=float)[:, None]
    img = np.full((H, W), bg)
    for c, a in zip(centres, peaks, strict=True):
        lo, hi = (rows - 0.5 - c[None]) / (np.sqrt(2) * SIGMA), (rows + 0.5 - c[None]) / (np.sqrt(2) * SIGMA)
        img = img + a * SIGMA * np.sqrt(np.pi / 2) * (erf(hi) - erf(lo))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def synthetic() -> dict[str, float]:
    """Mean centre errors (px) by the border and beside a second stripe."""
    rng = np.random.default_rng(3)
    out = {}
    for top in (4.0, 6.0, 8.0):
        t = top + rng.uniform(0, 1, W)
        c = gaussian(stripe_image([t], [150.0]), across=False)
        out[f"border_{top:.0f}_rows"] = float(np.mean(c["v"] - t[c["u"].astype(int)]))
    for sep in (10.0, 12.0, 14.0):
        for ratio in (1.0, 0.3):
            t = 40.0 + rng.uniform(0, 1, W)
            c = gaussian(stripe_image([t, t + sep], [150.0, 150.0 * ratio]), across=False)
            for k, truth in ((0, t), (1, t + sep)):
                out[f"pair_{sep:.0f}px_{ratio:g}_stripe{k + 1}"] = float(np.mean(c["v"][k::2] - truth))
    return out


def rendered(name: str, args: list[str], scans: list[str]) -> dict[str, dict[str, float]]:
    """RMS row error (px) of close and other centres against the true centre lines."""
    cap = CACHE / name
    if not (cap / "rig.yaml").is_file():
        CACHE.mkdir(parents=True, exist_ok=True)
        subprocess.run(["crossline", "simulate", str(cap), *args, "--quick", "--force"], check=True,
                       capture_output=True)
    cfg = yaml.safe_load((REPO / "config.yaml").read_text())["stripes"]
    kw = {k: cfg[k] for k in ("threshold", "min_width", "max_width", "sigma", "pad", "fit_pad",
                              "fit_across", "min_peak", "off_frames")}
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for scan in scans:
            path = Path(tmp) / f"{scan}.parquet"
            run_extract_stripes(cap, scan, path, extractor=cfg["extractor"], threads=2, **kw)
            st = pd.read_parquet(path)
            st = st[st["axis"] == 0].reset_index(drop=True)
            st["ui"] = np.round(st["u"]).astype(int)
            st["i"] = np.arange(len(st))
            tl = pd.read_parquet(cap / "truth" / f"{scan}_centrelines.parquet")
            tl = tl[tl["visible"] & tl["lit"] & tl["unoccluded"]]
            m = st.merge(tl[["frame", "u", "v"]].rename(columns={"u": "ui", "v": "vt"}), on=["frame", "ui"])
            m["e"] = m["v"] - m["vt"]
            m = m.loc[m["e"].abs().groupby(m["i"]).idxmin()]  # the nearest true line
            m = m[m["e"].abs() < 2.0]
            close = (m["flags"] & CLOSE) != 0
            out[scan] = {"close_rms_px": float(np.sqrt(np.mean(m["e"][close] ** 2))),
                         "close_n": int(close.sum()),
                         "other_rms_px": float(np.sqrt(np.mean(m["e"][~close] ** 2))),
                         "other_n": int((~close).sum())}
    return out


def main() -> int:
    res = {"synthetic_mean_error_px": synthetic(),
           "rendered": {name: rendered(name, a, s) for name, (a, s) in CAPTURES.items()}}
    lines = ["Gaussian fit, sigma 2 px, 8-bit: mean centre error (px)"]
    lines += [f"  {k:28s} {v:+.4f}" for k, v in res["synthetic_mean_error_px"].items()]
    lines.append("quick captures: RMS row error against the true centre lines (px), close centres | others")
    for name, scans in res["rendered"].items():
        for scan, r in scans.items():
            lines.append(f"  {name:15s} {scan:6s} close {r['close_rms_px']:.3f} (n {r['close_n']})"
                         f"  others {r['other_rms_px']:.3f} (n {r['other_n']})")
    text = "\n".join(lines)
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "stripe_pairs.txt").write_text(text + "\n")
    (RESULTS / "stripe_pairs.json").write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The renderer's speckle against coherent imaging and Dorsch's figure (issue 22.1).

The renderer multiplies a stripe's image by a log-normal field of contrast C per pixel,
correlated over ``speckle_grain_px`` (``crossline.sim.optics.speckle_field``). Real speckle is
the interference of the light the aperture collects from a rough surface: the image field is
the coherent (amplitude) point-spread function h convolved with the object's field
``sqrt(I) exp(i phi)``, phi random, and the image is ``|E|^2``, fully developed (contrast 1);
a multimode diode, a depolarising surface and the like lower its contrast, which is drawn
here as the mixture ``(1 - c) <I> + c |E|^2`` (same mean; a sum of 1 / c^2 independent patterns
has the same second-order statistics). The pixels integrate the pattern, which lowers its
contrast once more, by ``kappa`` (the variance of a pixel's mean over a field of Gaussian
correlation, per axis, squared); ``c = C / kappa`` gives both models the contrast C per pixel
that the renderer states and that the extractor measures from the frames (relative noise).
h is a Gaussian whose intensity ``|h|^2`` has the grain's sigma, as the renderer's grain is
the aperture's diffraction-limited spot (0.41 lambda N / pitch). Both models are drawn on
the same mean image (a straight stripe of Gaussian profile, sigma across it after the PSF,
at an angle to the rows), speckle only (no sensor noise), and their centres measured:

- ``centroid``: the intensity centroid of each column profile (+-3 sigma of the column cut);
- ``gaussian``: the workflow's extractor (``crossline.scan.stripe_frame.extract``, the
  default ``gaussian``, at any angle), as the stage runs it.

Each error is the centre's distance from the true line, across it (robust sigma, px). Dorsch,
Häusler & Herrmann's figure ``C lambda N (1 + m) / pi`` (``crossline.report.speckle``) is
printed beside them, with the ratio of each model to it; and the bound of speckle and sensor
noise together for the stripe's width (``crossline.report.speckle.stripe_bound_px``, the
profile the extractor takes: the column below 45 deg, the row above), with the extractor's
ratio to it under each model.

Usage: python benchmarks/bench_speckle.py [--frames 30] [--f-numbers 4.3,8,14.5] [--angles 0,45,85]
Writes benchmarks/results/speckle.txt and speckle.json.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from crossline.optics import grain_px as optics_grain_px  # noqa: E402
from crossline.report.speckle import centre_bound_px, stripe_bound_px  # noqa: E402
from crossline.robust import robust_sigma  # noqa: E402
from crossline.scan.stripe_frame import extract  # noqa: E402
from crossline.sim.optics import speckle_field  # noqa: E402

RESULTS = HERE / "results"
# the paper rig's optics: 405 nm, 2.4 um pixels, contrast 0.15, magnification ~0.08 (f/8)
WAVELENGTH_NM, PITCH_UM, CONTRAST, MAGNIFICATION = 405.0, 2.4, 0.15, 0.08


def grain_px(f_number: float) -> float:
    """The image-plane speckle grain (px) of an f-number, as ``crossline.sim.random_rig``."""
    return optics_grain_px(WAVELENGTH_NM, f_number, PITCH_UM)


def profile_bound_px(sigma: float, angle_deg: float, grain: float) -> float:
    """The bound across the line for the profile the extractor takes (column or row)."""
    t = math.radians(angle_deg)
    cos_p = max(math.cos(t), math.sin(t))
    one, _ = stripe_bound_px(PEAK_DN, sigma / cos_p, 0.0, math.hypot(READ_DN, 1 / math.sqrt(12)),
                             contrast=CONTRAST, grain=grain, shot=False)
    return cos_p * one


SS = 4  # sub-samples per pixel of the coherent model's grid
SHAPE = (160, 256)  # frame (rows, columns)
MODELS = ("sensor", "renderer", "coherent")  # no speckle, the renderer's, coherent imaging
# the sensor as the paper rig's frames show it (bench_scan: background noise 0.62 DN): an
# 8-bit frame, the stripe's mean peak 200 DN on a 2 DN background, read noise 0.6 DN. Without
# an additive floor the extractor's weights (1 / (r^2 yhat^2 + sigma_n^2)) would trust the
# profile's far tails as much as its peak, which no sensor allows
PEAK_DN, BACKGROUND_DN, READ_DN = 200.0, 2.0, 0.6


def _line_distance(shape: tuple[int, int], ss: int, angle_deg: float) -> np.ndarray:
    """Signed distance (px) of each sample centre from the line through the frame's centre at
    ``angle_deg`` to the rows, on a grid of ``ss`` samples per pixel."""
    h, w = shape
    y = (np.arange(h * ss) + 0.5) / ss - 0.5 - (h - 1) / 2
    x = (np.arange(w * ss) + 0.5) / ss - 0.5 - (w - 1) / 2
    t = math.radians(angle_deg)
    return (y[:, None] * math.cos(t) - x[None, :] * math.sin(t)).astype(np.float32)


def _bin(a: np.ndarray, ss: int) -> np.ndarray:
    h, w = a.shape[0] // ss, a.shape[1] // ss
    return a.reshape(h, ss, w, ss).mean(axis=(1, 3))


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def pixel_contrast_factor(grain_px: float) -> float:
    """kappa: a pixel's mean of a unit-contrast pattern whose intensity correlation is
    exp(-r^2 / (4 grain^2)) (|h|^2 of sigma ``grain_px``) has contrast kappa."""
    from scipy.integrate import quad

    s2 = 4.0 * grain_px**2
    per_axis = 2.0 * quad(lambda t: (1.0 - t) * math.exp(-t * t / s2), 0.0, 1.0)[0]
    return per_axis  # sqrt(per_axis^2): the two axes' variance factors multiply


def coherent_frame(rng: np.random.Generator, amp2: np.ndarray, mean_fine: np.ndarray,
                   grain_px: float, contrast: float, ss: int) -> np.ndarray:
    """One speckled image, pixel-binned: (1 - c) <I> + c |h * (a e^{i phi})|^2 / sum h^2, with
    c = contrast / kappa so that the pixels see ``contrast``."""
    a = np.sqrt(amp2)
    phase = rng.uniform(0.0, 2.0 * np.pi, a.shape).astype(np.float32)
    sig_h = math.sqrt(2.0) * grain_px * ss  # |h|^2 has the grain's sigma
    re = _blur(a * np.cos(phase), sig_h)
    im = _blur(a * np.sin(phase), sig_h)
    # cv2's kernel is normalised to sum 1 (2-D: 1 / (2 pi sig_h^2)); the mean of |E|^2 is
    # then sum(k^2) * a^2 blurred by k^2 / sum(k^2), and sum(k^2) = 1 / (4 pi sig_h^2)
    coh = (re * re + im * im) * np.float32(4.0 * math.pi * sig_h * sig_h)
    c = contrast / pixel_contrast_factor(grain_px)
    return _bin((1.0 - c) * mean_fine + c * coh, ss)


def _centroids(img: np.ndarray, angle_deg: float, sigma_px: float) -> np.ndarray:
    """Per column: the intensity centroid within +-3 sigma of the column cut about the true
    line, as its distance across the line (px)."""
    h, w = img.shape
    t = math.radians(angle_deg)
    cols = np.arange(w)
    v_true = (h - 1) / 2 + (cols - (w - 1) / 2) * math.tan(t)
    half = 3.0 * sigma_px / math.cos(t)
    rows = np.arange(h)[:, None]
    win = np.abs(rows - v_true[None, :]) <= half
    ok = (v_true - half >= 0) & (v_true + half <= h - 1)
    s = (img * win).sum(0)
    c = (img * win * rows).sum(0) / np.where(s > 0, s, 1.0)
    return ((c - v_true) * math.cos(t))[ok]


def _extracted(img: np.ndarray, angle_deg: float) -> np.ndarray:
    """The workflow's Gaussian extractor on the frame: each centre's distance across the true
    line (px), away from the frame's border."""
    c = extract(img, "gaussian", threshold=0.15)
    h, w = img.shape
    t = math.radians(angle_deg)
    u, v = c["u"].astype(np.float64), c["v"].astype(np.float64)
    d = (v - (h - 1) / 2) * math.cos(t) - (u - (w - 1) / 2) * math.sin(t)
    inner = (u > 8) & (u < w - 9) & (v > 8) & (v < h - 9)
    return d[inner]


def run(frames: int, angles: list[float], sigmas: list[float], f_number: float) -> list[dict]:
    rng = np.random.default_rng(22)
    out = []
    grain = grain_px(f_number)
    for angle in angles:
        d_fine = _line_distance(SHAPE, SS, angle)
        for sigma in sigmas:
            if sigma <= 1.2 * grain:  # no image of the stripe is narrower than the aperture's spot
                continue
            # the object's stripe: its sigma before the aperture's |h|^2 (the grain) widens it
            s0 = math.sqrt(sigma**2 - grain**2)
            amp2 = (PEAK_DN * sigma / s0 * np.exp(-0.5 * (d_fine / s0) ** 2)).astype(np.float32)
            mean_fine = _blur(amp2, grain * SS)
            mean_px = _bin(mean_fine, SS)
            mask = (mean_px > 0.01 * PEAK_DN).astype(np.uint8)
            err = {f"{m} {e}": [] for m in MODELS for e in ("centroid", "gaussian")}
            contrast_px = {m: [] for m in MODELS}
            bright = mean_px > 0.5 * mean_px.max()
            for _ in range(frames):
                light = {"sensor": mean_px,
                         "renderer": mean_px * speckle_field(rng, mask, CONTRAST, grain),
                         "coherent": coherent_frame(rng, amp2, mean_fine, grain, CONTRAST, SS)}
                for name, lit in light.items():
                    contrast_px[name].append(float(np.std(lit[bright] / mean_px[bright])))
                    img = lit + BACKGROUND_DN + READ_DN * rng.standard_normal(lit.shape)
                    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
                    if angle < 60:
                        err[f"{name} centroid"].append(
                            _centroids(img.astype(np.float64) - BACKGROUND_DN, angle, sigma))
                    err[f"{name} gaussian"].append(_extracted(img, angle))
            row = {"f_number": f_number, "grain_px": grain, "angle_deg": angle, "sigma_px": sigma,
                   "dorsch_px": centre_bound_px(CONTRAST, WAVELENGTH_NM, f_number, PITCH_UM,
                                                MAGNIFICATION),
                   "bound_px": profile_bound_px(sigma, angle, grain),
                   "contrast_per_pixel": {k: float(np.mean(v)) for k, v in contrast_px.items()}}
            for k, v in err.items():
                e = np.concatenate(v) if v else np.zeros(0)
                row[k] = {"sigma_px": robust_sigma(e), "n": int(e.size)}
            out.append(row)
            print(format_row(row), flush=True)
    return out


def format_row(r: dict) -> str:
    parts = []
    for e in ("centroid", "gaussian"):
        if not r[f"sensor {e}"]["n"]:
            continue
        s = [r[f"{m} {e}"]["sigma_px"] for m in MODELS]
        parts.append(f"{e}: " + " / ".join(f"{x:.4f}" for x in s)
                     + f" ({s[1] / r['dorsch_px']:.2f}x / {s[2] / r['dorsch_px']:.2f}x;"
                     + f" renderer / coherent {s[1] / s[2]:.2f})")
    cp = r["contrast_per_pixel"]
    g = [r[f"{m} gaussian"]["sigma_px"] / r["bound_px"] for m in MODELS[1:]]
    if r["sensor centroid"]["n"]:
        c = [r[f"{m} centroid"]["sigma_px"] / r["bound_px"] for m in MODELS[1:]]
        g[1] = f"{g[1]:.2f}x; centroid {c[0]:.2f}x / {c[1]:.2f}x"
    else:
        g[1] = f"{g[1]:.2f}x"
    return (f"f/{r['f_number']:<4g} grain {r['grain_px']:.2f} px  {r['angle_deg']:2.0f} deg  "
            f"sigma {r['sigma_px']:.1f} px  Dorsch {r['dorsch_px']:.4f}  "
            f"bound {r['bound_px']:.4f} (gaussian / bound {g[0]:.2f}x / {g[1]})  "
            + "  ".join(parts)
            + f"  contrast per pixel {cp['renderer']:.3f} / {cp['coherent']:.3f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=30, help="frames per case and model")
    ap.add_argument("--angles", default="0,45,85", help="stripe angles to the rows, deg")
    ap.add_argument("--sigmas", default="0.8,1.2,2,3", help="stripe sigmas across it, px")
    ap.add_argument("--f-numbers", default="4.3,8,14.5", help="f-numbers (the grain follows)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    head = (f"speckle only, one stripe per frame ({SHAPE[1]} x {SHAPE[0]} px), {a.frames} frames "
            f"per case and model; optics of the paper rig: {WAVELENGTH_NM:g} nm, f/{a.f_numbers} "
            f"(grain 0.41 lambda N / pitch), {PITCH_UM:g} um pixels, contrast {CONTRAST:g}, m "
            f"{MAGNIFICATION:g}; robust sigma across the true line (px) and its ratio to "
            "Dorsch's figure; each: sensor only / the renderer's speckle "
            "(crossline.sim.optics.speckle_field, contrast C per pixel) / coherent imaging "
            "(|h * (a e^{i phi})|^2 mixed to contrast C per pixel), 8-bit frames, "
            f"peak {PEAK_DN:g} DN, read noise {READ_DN:g} DN; bound: speckle and sensor "
            "together for the stripe's width (crossline.report.speckle.stripe_bound_px) and "
            "the extractor's and the centroid's ratios to it (renderer / coherent)")
    print(head, flush=True)
    rows = [r for f in a.f_numbers.split(",")
            for r in run(a.frames, [float(x) for x in a.angles.split(",")],
                         [float(x) for x in a.sigmas.split(",")], float(f))]
    RESULTS.mkdir(parents=True, exist_ok=True)
    text = head + "\n" + "\n".join(format_row(r) for r in rows) + \
        f"\n{time.perf_counter() - t0:.0f} s\n"
    (RESULTS / "speckle.txt").write_text(text)
    (RESULTS / "speckle.json").write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

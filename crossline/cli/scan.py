"""The ``crossline`` subcommands of a scan: ``extract-stripes``, ``gather-stripes``, ``triangulate``.

Each registers itself in ``crossline.cli.args.COMMANDS`` when this module is imported
(``crossline.cli`` imports it). Split from ``crossline.cli`` (issue 21.3).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from crossline.cli.args import _auto_or_count, _auto_or_fraction, _bool, _parquet_inputs, _threads, command

# ----------------------------------------------------------------------------- scan stages


@command(
    "extract-stripes",
    "stripe centres of every frame of a scan (grey-centre, Gaussian fit or Steger)",
    """
    Streams the frames of one scan (each read once) and writes every stripe centre found,
    in full-sensor pixels: frame, lasers, u, v, strength, and the extractor's extras.
    --chunk i/n processes the i-th of n equal slices of the frames (for scatter-gather).
    """,
)
def _extract_stripes(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder")
    p.add_argument("scan", help="scan name (a folder under scans/)")
    p.add_argument("--out", type=Path, required=True, help="stripes parquet to write")
    p.add_argument("--extractor", choices=("grey_centre", "gaussian", "steger"), default="gaussian",
                   help="gaussian (default): weighted least-squares Gaussian profile, speckle-aware; "
                        "grey_centre: the paper's eq. 9; steger: Hessian ridge detector")
    p.add_argument("--threshold", type=float, default=0.10,
                   help="a stripe's run: pixels above the background by this fraction of the "
                        "frame's stripe peak, and by 6 noise sigmas at least (default 0.10)")
    p.add_argument("--min-peak", type=float, default=0.17,
                   help="drop runs whose brightest pixel stands less than this fraction of the "
                        "frame's stripe peak above the background (default 0.17)")
    p.add_argument("--min-width", type=float, default=2.0, help="narrowest stripe, px")
    p.add_argument("--max-width", type=float, default=30.0, help="widest stripe, px")
    p.add_argument("--sigma", type=float, default=2.0, help="Steger's Gaussian sigma, px")
    p.add_argument("--pad", type=int, default=2,
                   help="grey-centre: px the window reaches beyond the run above threshold (default 2)")
    p.add_argument("--fit-pad", type=int, default=6,
                   help="gaussian: px the fitted window reaches beyond the run above threshold (default 6)")
    p.add_argument("--relative-noise", type=_auto_or_fraction, default=None,
                   help="gaussian: the stripe's relative intensity noise (speckle contrast) that "
                        "weights the fit, or 'auto' to estimate it in every frame (default)")
    p.add_argument("--fit-across", type=_bool, default=True,
                   help="gaussian: refit stripes steeper than 0.3 px per column across the stripe "
                        "(true, default) or keep the column fit alone (false)")
    p.add_argument("--off-frames", choices=("subtract", "ignore"), default="subtract",
                   help="a scan with off frames: subtract the room's light they show from the laser "
                        "frames between two of them where it did not move (default), or ignore them")
    p.add_argument("--decoder", choices=("auto", "fast", "opencv"), default="auto",
                   help="PNG decoder: fast (libdeflate + numba), opencv, or auto (fast if installed)")
    p.add_argument("--chunk", default="0/1", help="i/n: process the i-th of n slices (0-based)")
    _threads(p)

    def run(a: argparse.Namespace) -> int:
        from crossline.scan.stripes import run_extract_stripes

        try:
            i, n = (int(x) for x in a.chunk.split("/"))
        except ValueError:
            p.error(f"--chunk must be i/n, e.g. 0/4, got {a.chunk!r}")
        run_extract_stripes(
            a.capture, a.scan, a.out, extractor=a.extractor, threshold=a.threshold,
            min_width=a.min_width, max_width=a.max_width, sigma=a.sigma, chunk=(i, n),
            threads=a.threads, pad=a.pad, fit_pad=a.fit_pad,
            relative_noise=a.relative_noise, fit_across=a.fit_across,
            decoder=a.decoder, min_peak=a.min_peak, off_frames=a.off_frames,
        )
        return 0

    p.set_defaults(func=run)


@command(
    "gather-stripes",
    "join the stripe chunks of one scan into one parquet",
    "Concatenates the chunk files in frame order; the result equals an unsplit run.",
)
def _gather_stripes(p: argparse.ArgumentParser) -> None:
    p.add_argument("chunks", type=Path, nargs="+", help="chunk parquet files")
    p.add_argument("--out", type=Path, required=True, help="stripes parquet to write")

    def run(a: argparse.Namespace) -> int:
        from crossline.scan.stripes import gather_stripes

        _parquet_inputs(a.chunks, "stripe chunk")
        gather_stripes(a.chunks, a.out)
        return 0

    p.set_defaults(func=run)


@command(
    "triangulate",
    "label stripe centres A or B, then turn them into 3-D points in the base frame",
    """
    Labels every centre by its laser (A/B frames directly; AB frames by the paper's periodic
    rule, eq. 14-15, threshold T), undistorts it, intersects its ray with its laser's plane
    (eq. 8) and carries it to the base frame with the frame's arm pose and T_tool_cam.
    """,
)
def _triangulate(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder (for the arm poses)")
    p.add_argument("scan", help="scan name")
    p.add_argument("--stripes", type=Path, required=True, help="stripes parquet")
    p.add_argument("--camera", type=Path, required=True, help="camera.json")
    p.add_argument("--lasers", type=Path, required=True, help="lasers.json")
    p.add_argument("--handeye", type=Path, required=True, help="handeye.json")
    p.add_argument("--out", type=Path, required=True, help="points parquet to write")
    p.add_argument("--threshold-px", type=float, default=10.0,
                   help="T of eq. 14-15: largest distance to the reference stripe (default 10)")
    p.add_argument("--max-frame-gap", type=_auto_or_count, default=None,
                   help="oldest A/B reference frame an AB frame may use, in frames, or 'auto' "
                        "(default): one more than the scan's laser pattern needs (3 for A, B, AB)")
    p.add_argument("--ambiguity-px", type=float, default=3.0,
                   help="drop an AB centre whose distances to both references (both within T) "
                        "differ by less than this (default 3; 0 = the paper's nearest-wins rule)")
    p.add_argument("--predict", type=_bool, default=True,
                   help="extrapolate each reference stripe to the AB frame from the last two "
                        "frames of its laser (default true; false = the paper's latest frame)")
    p.add_argument("--end-trim-px", type=float, default=8.0,
                   help="drop centres closer than this (px along the stripe) to the end of their "
                        "stripe trace, where the cut-off cross-section biases them (default 8)")
    p.add_argument("--bridge-columns", type=int, default=8,
                   help="interpolate a reference stripe over gaps of up to this many columns "
                        "before AB centres are matched to it (default 8; 0 = off, the paper)")
    p.add_argument("--track-references", type=_bool, default=True,
                   help="an AB frame's labelled stripes are the references of the next AB frame "
                        "(default true; false = the paper: references from A and B frames only)")
    p.add_argument("--sheet-curvature", type=_bool, default=True,
                   help="move each centre by the bias a sheet of finite thickness gives it on a "
                        "curved surface, from the scan's own shape and the extractor's measured "
                        "response (default true; false = centres as extracted)")
    p.add_argument("--smooth-px", type=int, default=7,
                   help="smooth each centre line along the stripe over this many columns "
                        "(odd; local quadratic; default 7, as config.yaml; 1 = off)")
    p.add_argument("--stats", type=Path,
                   help="JSON of the labelling counts (default: --out with suffix .json)")

    def run(a: argparse.Namespace) -> int:
        from crossline.scan.triangulate import run_triangulate

        run_triangulate(
            a.capture, a.scan, a.stripes, a.camera, a.lasers, a.handeye, a.out,
            threshold_px=a.threshold_px, max_frame_gap=a.max_frame_gap,
            ambiguity_px=a.ambiguity_px, predict=a.predict, end_trim_px=a.end_trim_px,
            smooth_px=a.smooth_px, bridge_columns=a.bridge_columns,
            track_references=a.track_references, sheet_curvature=a.sheet_curvature,
            stats=a.stats,
        )
        return 0

    p.set_defaults(func=run)

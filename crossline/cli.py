"""The ``crossline`` command: one subcommand per stage of the workflow.

Each subcommand is what a Snakemake rule runs; it can be run by hand just the same.
Errors in the input (a broken capture, a missing artefact) end with a message that names
the file and exit status 2; nothing half-written is left behind.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

from crossline import __version__

log = logging.getLogger("crossline")

COMMANDS: dict[str, tuple[str, str, Callable[[argparse.ArgumentParser], None]]] = {}


def command(name: str, summary: str, details: str = ""):
    """Register a subcommand: the decorated function adds its arguments and sets ``func``."""

    def wrap(fn: Callable[[argparse.ArgumentParser], None]):
        COMMANDS[name] = (summary, textwrap.dedent(details).strip(), fn)
        return fn

    return wrap


def _bool(text: str) -> bool:
    if text.lower() in ("1", "true", "yes", "on"):
        return True
    if text.lower() in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _checked(kind: type, ok, what: str, *, auto: bool = False):
    """An argparse type: a ``kind`` value for which ``ok`` holds, or with ``auto`` also 'auto' (None)."""
    expected = f"'auto' or {what}" if auto else what

    def parse(text: str):
        if auto and text.lower() == "auto":
            return None
        try:
            x = kind(text)
        except ValueError:
            x = None
        if x is None or not ok(x):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return x

    return parse


_auto_or_fraction = _checked(float, lambda x: 0 < x < 1, "a number in (0, 1)", auto=True)
_auto_or_count = _checked(int, lambda n: n >= 1, "a positive integer", auto=True)
_auto_or_positive = _checked(float, lambda x: x > 0, "a number > 0", auto=True)
_positive = _checked(float, lambda x: x > 0, "a number > 0")
_unit_interval = _checked(float, lambda x: 0 <= x <= 1, "a number in [0, 1]")


def _board_spec(text: str):
    from crossline.board import Board

    try:
        return Board.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _parquet_inputs(paths: list[Path], what: str) -> None:
    """Raise a CrosslineError naming the first of ``paths`` that is not a readable parquet file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from crossline.errors import CrosslineError

    for path in paths:
        try:
            pq.ParquetFile(path)
        except OSError as exc:
            if isinstance(exc, pa.ArrowException):
                raise CrosslineError(f"{path}: not a {what} file (parquet: {exc})") from None
            raise CrosslineError(f"{path}: cannot read the {what} file ({exc.strerror or exc})") from None
        except (pa.ArrowException, ValueError) as exc:
            raise CrosslineError(f"{path}: not a {what} file (parquet: {exc})") from None


def _threads(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=int, default=1, help="CPU threads to use (default 1)")


# ----------------------------------------------------------------------------- simulate

_non_negative = _checked(float, lambda x: x >= 0, "a number >= 0")


@command(
    "simulate",
    "render a capture folder from a virtual rig with known truth",
    """
    Renders rig.yaml, every calibration image, every scan (frames and arm poses) and
    truth.json, exactly as a real rig would write them (DESIGN.md §2). Images are traced
    ray by ray from supersampled sensor positions through the lens distortion, then blurred,
    given shot and read noise and quantised. The same seed gives byte-identical files.
    `--preset random --seed N` (or `--rig random`) draws a whole rig from the seed: sensor
    1-12 MP and its scan window, 8/10/12/16-bit data, board type and polarity, lens and
    distortion, laser planes at any cross orientation, exposure, ambient light, noise,
    pattern, arm noise (random-small: sensors up to 2.3 MP, for tests). Options below make
    the captures real rigs write: one laser, JPEG/TIFF/BMP, colour, laser always on,
    calibration views only, a noisy arm.
    """,
)
def _simulate(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", type=Path, help="capture folder to write (must not exist or be empty)")
    p.add_argument("--preset", "--rig", dest="preset", default="paper",
                   help="virtual rig: paper (default), compact, random or random-small (drawn "
                        "from --seed)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--quick", action="store_true", help="small capture for tests (seconds)")
    p.add_argument("--frames", type=int, help="frames per scan (default: preset's)")
    p.add_argument("--pattern", help="laser pattern per period, e.g. A,B,AB or A,B,AB,AB")
    p.add_argument("--bit-depth", type=int, choices=(8, 16), help="image bit depth (container)")
    p.add_argument("--data-bits", type=int, choices=(8, 10, 12, 14, 16),
                   help="the ADC's bits inside the container (default: the rig's; a 12-bit "
                        "camera writes 0..4095 into 16-bit images)")
    p.add_argument("--lasers", choices=("A", "A,B"), metavar="A|A,B",
                   help="A: a one-line rig (default A,B)")
    p.add_argument("--image-format", choices=("png", "jpeg", "tiff", "bmp"), default="png",
                   help="file format of every image (default png; jpeg and bmp are 8-bit)")
    p.add_argument("--jpeg-quality", type=int, default=95, help="JPEG quality 1-100 (default 95)")
    p.add_argument("--colour", choices=("red", "green", "blue", "none"), default="none",
                   help="a colour (Bayer) sensor, the laser mainly in this channel (default none: grey)")
    p.add_argument("--laser-always-on", action="store_true",
                   help="laser-plane poses as <pose>_laser.* only, no laser-off twin")
    p.add_argument("--calibration-only", action="store_true", help="no scans (no scans: in rig.yaml)")
    p.add_argument("--no-handeye", action="store_true", help="no calibration/handeye/")
    p.add_argument("--parts", help="comma-separated parts to write among camera,lasers,handeye,scans "
                                   "(default all)")
    p.add_argument("--arm-noise-scale", type=_non_negative, default=1.0, metavar="K",
                   help="the arm's reported-pose noise times K (default 1)")
    p.add_argument("--scans", help="comma-separated subset of the preset's scans")
    p.add_argument("--dent", type=float, metavar="MM",
                   help="press a dent MM deep into the freeform part (not into its nominal "
                        "mesh): a defect for the report's nominal comparison to find")
    p.add_argument("--dent-sigma", type=float, default=2.5, metavar="MM",
                   help="the dent's width, the sigma of its Gaussian profile (default 2.5 mm)")
    p.add_argument("--nominal-datum", action="store_true",
                   help="rig.yaml gives each freeform part's placement (nominal_pose), as probed "
                        "with the arm, with the arm's error")
    p.add_argument("--board", type=_board_spec, metavar="SPEC",
                   help="calibration board instead of the preset's: pattern:COLSxROWS:spacing"
                        "[:diameter[:dark|light]], e.g. chessboard:12x9:4 (inner corners, square mm) "
                        "or symmetric:15x11:3.75:1.875:light")
    p.add_argument("--force", action="store_true", help="overwrite an existing capture folder")
    _threads(p)

    def run(a: argparse.Namespace) -> int:
        from crossline.sim import simulate

        parts = a.parts.split(",") if a.parts else ["camera", "lasers", "handeye", "scans"]
        if a.no_handeye:
            parts = [x for x in parts if x != "handeye"]
        simulate(
            a.out, preset=a.preset, seed=a.seed, quick=a.quick, frames=a.frames,
            pattern=a.pattern.split(",") if a.pattern else None, bit_depth=a.bit_depth,
            scans=a.scans.split(",") if a.scans else None, force=a.force, threads=a.threads,
            board=a.board, data_bits=a.data_bits,
            lasers=a.lasers.split(",") if a.lasers else None, image_format=a.image_format,
            jpeg_quality=a.jpeg_quality, colour=a.colour, laser_always_on=a.laser_always_on,
            calibration_only=a.calibration_only, arm_noise_scale=a.arm_noise_scale, parts=parts,
            dent_mm=a.dent, dent_sigma_mm=a.dent_sigma, nominal_datum=a.nominal_datum,
        )
        return 0

    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- check


@command(
    "check",
    "validate a capture folder and print its summary",
    """
    Reads rig.yaml, every CSV and every image header of a capture and prints a summary
    (views per set, frames per scan, laser pattern, duration, scan window, and which stages
    the capture allows and why not the others), or every problem found, each naming the
    file, the line and what was expected. Every part of a capture is optional; every file
    it names or holds must lie inside its folder (no '..', absolute paths or links out).
    """,
)
def _check(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder")
    p.add_argument("--json", type=Path, help="also write the summary as JSON here")
    p.add_argument("--no-images", action="store_true", help="skip the image checks")

    def run(a: argparse.Namespace) -> int:
        from crossline.io.atomic import write_json
        from crossline.io.capture import check_capture, format_summary

        summary = check_capture(a.capture, images=not a.no_images)
        print(format_summary(summary))
        if a.json:
            write_json(a.json, summary)
        return 0

    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- calibration


@command(
    "calibrate-camera",
    "intrinsics and distortion from the circle-grid views (Zhang)",
    """
    Detects the board in calibration/camera/*.png (with --views all, the default, also in
    every other lasers-off board view: laser_*/<pose>_board.png and handeye/*.png), runs
    Zhang's method (OpenCV, 5 distortion coefficients) polished by a float64 bundle
    adjustment, corrects the perspective bias of circle centres iteratively, drops views
    that are not found or whose residual is an outlier (each with its reason) and writes
    camera.json.
    """,
)
def _calibrate_camera(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder")
    p.add_argument("--out", type=Path, required=True, help="camera.json to write")
    p.add_argument("--bias-correction", type=_bool, default=True,
                   help="correct the perspective bias of circle centres (default true)")
    p.add_argument("--outlier-factor", type=float, default=3.0,
                   help="drop views whose RMS exceeds this many times the median (default 3)")
    p.add_argument("--min-views", type=int, default=6, help="fewest usable views (default 6)")
    p.add_argument("--views", choices=("camera", "all"), default="all",
                   help="board views to use: calibration/camera only, or all lasers-off board "
                        "views of the capture (default all)")
    p.add_argument("--distortion", choices=("select", "full"), default="select",
                   help="select: fix at 0 the distortion coefficients the views do not determine "
                        "(the model with the lowest predicted projection error over the scan "
                        "window, said in camera.json); full: estimate all five (default select)")
    _threads(p)

    def run(a: argparse.Namespace) -> int:
        from crossline.calibrate.camera import run_calibrate_camera

        run_calibrate_camera(
            a.capture, a.out, bias_correction=a.bias_correction,
            outlier_factor=a.outlier_factor, min_views=a.min_views, threads=a.threads,
            views=a.views, distortion=a.distortion,
        )
        return 0

    p.set_defaults(func=run)


@command(
    "calibrate-lasers",
    "the planes of lasers A and B from board poses with and without the laser",
    """
    For each pose: the board pose from the lasers-off image, stripe centres (grey-centre)
    from the laser-on image minus the lasers-off image scaled to its exposure, kept only
    where the whole profile lies on the board clear of every circle rim, their rays
    intersected with the board plane; then one robust plane per laser over all poses
    (least-median start, trimmed least squares). Writes lasers.json.
    """,
)
def _calibrate_lasers(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder")
    p.add_argument("--camera", type=Path, required=True, help="camera.json")
    p.add_argument("--out", type=Path, required=True, help="lasers.json to write")
    p.add_argument("--threshold", type=float, default=0.2,
                   help="stripe threshold as a fraction of the stripe's peak level (default 0.2)")
    p.add_argument("--trim", type=float, default=3.0,
                   help="reject points beyond this many robust sigmas from the plane (default 3)")
    p.add_argument("--margin-px", type=float, default=4.0,
                   help="keep stripe profiles this far from circle rims and the board edge "
                        "(default 4 px)")
    _threads(p)

    def run(a: argparse.Namespace) -> int:
        from crossline.calibrate.lasers import run_calibrate_lasers

        run_calibrate_lasers(
            a.capture, a.camera, a.out, threshold=a.threshold, trim=a.trim, threads=a.threads,
            margin_px=a.margin_px,
        )
        return 0

    p.set_defaults(func=run)


@command(
    "calibrate-handeye",
    "the camera's pose on the arm flange, X = T_tool_cam (AX = XB)",
    """
    Board poses from calibration/handeye/*.png and arm poses from poses.csv. Solves AX = XB
    by Chou & Kamel (the paper), alongside OpenCV's methods, rejecting motion pairs whose
    rotation angles disagree by more than --mismatch-k robust sigmas of all pairs' mismatches
    (the tolerance follows the data's noise); then refines X and the board's pose in the base
    frame by minimising the reprojection error of every board point, the reported arm poses
    free to move within their noise (estimated from the data). The refined X is kept unless a
    method's board consistency on the views is better by more than X's uncertainty explains.
    Resolves the 180-degree ambiguity of symmetric boards across views. Writes handeye.json
    with every method's X and board consistency, and which method won.
    """,
)
def _calibrate_handeye(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder")
    p.add_argument("--camera", type=Path, required=True, help="camera.json")
    p.add_argument("--out", type=Path, required=True, help="handeye.json to write")
    p.add_argument("--mismatch-k", type=float, default=4.0,
                   help="reject motion pairs whose rotation angles differ by more than this many "
                        "robust sigmas of all pairs' mismatches (default 4)")
    _threads(p)

    def run(a: argparse.Namespace) -> int:
        from crossline.calibrate.handeye import run_calibrate_handeye

        run_calibrate_handeye(
            a.capture, a.camera, a.out, mismatch_k=a.mismatch_k, threads=a.threads,
        )
        return 0

    p.set_defaults(func=run)


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
            decoder=a.decoder, min_peak=a.min_peak,
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
            track_references=a.track_references, stats=a.stats,
        )
        return 0

    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- fusion, report


@command(
    "fuse",
    "fuse the points of a scan into an Open3D cloud (PLY), optionally a mesh (STL)",
    """
    Optional refinement of every frame's arm pose from the scan itself (where line A of one
    frame crosses line B of another, the two must meet; the arm's precision is the prior),
    statistical outlier removal, optional voxel down-sampling, normals; writes the cloud
    as PLY in the base frame (mm) and, if asked, a Poisson or ball-pivoting mesh as STL.
    """,
)
def _fuse(p: argparse.ArgumentParser) -> None:
    p.add_argument("points", type=Path, help="points parquet")
    p.add_argument("--out", type=Path, required=True, help="PLY to write")
    p.add_argument("--stats", type=Path, help="JSON with the counts before and after")
    p.add_argument("--neighbours", type=int, default=20, help="outlier removal: neighbours")
    p.add_argument("--std-ratio", type=float, default=3.0, help="outlier removal: std ratio")
    p.add_argument("--voxel-mm", type=float, default=0.0, help="voxel size, 0 = keep all points")
    p.add_argument("--normal-radius-mm", type=float, default=0.5, help="normals search radius")
    p.add_argument("--mesh", choices=("none", "poisson", "ball_pivoting"), default="none")
    p.add_argument("--mesh-out", type=Path, help="STL to write when --mesh is not none")
    p.add_argument("--refine-poses", type=_bool, default=False,
                   help="refine each frame's arm pose from the A-B stripe crossings (default false "
                        "here; the workflow's config.yaml turns it on)")
    p.add_argument("--frames", type=Path,
                   help="the scan's frames.csv: frame times and flange positions for the refinement "
                        "(without it the frames' pose errors are taken as independent)")
    p.add_argument("--arm-precision-mm", type=float, default=0.02,
                   help="arm's stated precision, read as 2 sigma of the 3-D position error (mm)")
    p.add_argument("--arm-precision-rad", type=_auto_or_positive, default=None,
                   help="the same for the orientation (rad); auto = the mm figure over 300 mm")
    p.add_argument("--arm-smooth-fraction", type=_unit_interval, default=0.9,
                   help="share of the arm's error that drifts smoothly (0..1): the drift's sigma is "
                        "this share of the whole, the white part's sqrt(1 - share^2)")
    p.add_argument("--arm-corr-time-s", type=_positive, default=0.3,
                   help="correlation time of that part of the arm's error (s)")
    p.add_argument("--crossing-half-mm", type=_positive, default=0.6,
                   help="the refinement's stripe length fitted either side of a crossing (mm)")
    p.add_argument("--crossing-min-angle-deg", type=_positive, default=30.0,
                   help="smallest angle between two crossing stripes the refinement uses (deg)")
    p.add_argument("--crossing-max-width-ratio", type=float, default=2.0,
                   help="centres whose column cut is longer than this x their laser's median make "
                        "no crossings (0: any)")
    _threads(p)

    def run(a: argparse.Namespace) -> int:
        from crossline.fuse import run_fuse

        run_fuse(
            a.points, a.out, stats=a.stats, neighbours=a.neighbours, std_ratio=a.std_ratio,
            voxel_mm=a.voxel_mm, normal_radius_mm=a.normal_radius_mm, mesh=a.mesh,
            mesh_out=a.mesh_out, threads=a.threads, refine_poses=a.refine_poses,
            frames=a.frames, arm_precision_mm=a.arm_precision_mm,
            arm_precision_rad=a.arm_precision_rad, arm_smooth_fraction=a.arm_smooth_fraction,
            arm_corr_time_s=a.arm_corr_time_s, crossing_half_mm=a.crossing_half_mm,
            crossing_min_angle_deg=a.crossing_min_angle_deg,
            crossing_max_width_ratio=a.crossing_max_width_ratio,
        )
        return 0

    p.set_defaults(func=run)


@command(
    "export-cloud",
    "a fused cloud as E57, for CloudCompare and inspection software",
    """
    Writes the points and normals of a fused cloud (the fuse stage's PLY, base frame, mm) as
    one ASTM E57 scan, in metres as the standard defines, byte-reproducibly.
    """,
)
def _export_cloud(p: argparse.ArgumentParser) -> None:
    p.add_argument("cloud", type=Path, help="fused cloud (PLY) of the fuse stage")
    p.add_argument("--out", type=Path, required=True, help="E57 file to write")

    def run(a: argparse.Namespace) -> int:
        from crossline.io.clouds import run_export_cloud

        n = run_export_cloud(a.cloud, a.out)
        print(f"{a.out}: {n} points")
        return 0

    p.set_defaults(func=run)


@command(
    "report",
    "accuracy report (PDF) and metrics.json of a capture",
    """
    Measures each scan's artefact (gauge height, plane distances, sphere size and form,
    freeform deviations), compares laser A with laser B, summarises the calibrations, scores
    everything against truth.json when the capture has it, and writes a deterministic PDF.
    """,
)
def _report(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder")
    p.add_argument("--interim", type=Path, required=True,
                   help="the capture's data/interim folder (calibration/, points/)")
    p.add_argument("--processed", type=Path, required=True,
                   help="the capture's data/processed folder (<scan>.ply)")
    cfg = p.add_mutually_exclusive_group()
    cfg.add_argument("--config-json", dest="config", metavar="JSON",
                     help="JSON text of the parameters and tolerances used (report.tolerances, "
                          "report.metrology; all of it is recorded as provenance)")
    cfg.add_argument("--config", dest="config_file", type=Path,
                     help="the same from a JSON file")
    p.add_argument("--pdf", type=Path, required=True, help="accuracy.pdf to write")
    p.add_argument("--metrics", type=Path, required=True, help="metrics.json to write")
    p.add_argument("--deviation-dir", type=Path, default=None,
                   help="folder for <scan>.ply: each freeform scan compared with its nominal, "
                        "coloured by deviation, with the deviation as a scalar field")

    def run(a: argparse.Namespace) -> int:
        from crossline.report.accuracy import run_report

        config = a.config_file if a.config_file is not None else a.config
        run_report(a.capture, a.interim, a.processed, a.pdf, a.metrics, config=config,
                   deviation_dir=a.deviation_dir)
        return 0

    p.set_defaults(func=run)


@command(
    "certificate",
    "calibration certificate (PDF) and calibration.json of a capture's calibrations",
    """
    Every calibration the capture allowed, checked against the certificate's limits: camera
    parameters with their 1 sigma, per-view residuals, the residual field and the sensor's
    coverage by board points; each laser plane with its residuals per board pose; the
    hand-eye X with its consistency; PASS/FAIL. Needs the camera; lasers and hand-eye are
    shown when given. Deterministic PDF.
    """,
)
def _certificate(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder")
    p.add_argument("--summary", type=Path, help="the capture's check.json (which stages it allows)")
    p.add_argument("--camera", type=Path, required=True, help="camera.json")
    p.add_argument("--lasers", type=Path, help="lasers.json, if the capture has laser views")
    p.add_argument("--handeye", type=Path, help="handeye.json, if the capture has hand-eye views")
    cfg = p.add_mutually_exclusive_group()
    cfg.add_argument("--config-json", dest="config", metavar="JSON",
                     help="JSON text of the parameters with the limits under 'certificate'")
    cfg.add_argument("--config", dest="config_file", type=Path, help="the same from a JSON file")
    p.add_argument("--pdf", type=Path, required=True, help="calibration.pdf to write")
    p.add_argument("--json", type=Path, required=True, help="calibration.json to write")

    def run(a: argparse.Namespace) -> int:
        from crossline.report.certificate import run_certificate

        config = a.config_file if a.config_file is not None else a.config
        run_certificate(a.capture, a.pdf, a.json, summary=a.summary, camera=a.camera,
                        lasers=a.lasers, handeye=a.handeye, config=config)
        return 0

    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- main


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``crossline`` command."""
    parser = argparse.ArgumentParser(
        prog="crossline",
        description=(
            "Cross-line laser scanner on a measuring arm: capture folders to calibrations, "
            "point clouds and accuracy reports. Each subcommand is one stage of the "
            "Snakemake workflow; run `crossline <command> --help` for its options."
        ),
    )
    parser.add_argument("--version", action="version", version=f"crossline {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="<command>", required=True)
    for name, (summary, details, configure) in COMMANDS.items():
        sp = sub.add_parser(
            name, help=summary, description=f"{summary[0].upper()}{summary[1:]}.\n\n{details}",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        configure(sp)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``crossline`` command."""
    # One BLAS/OpenMP thread, set before numpy loads: OpenBLAS picks its kernels by the
    # thread count it starts with, so the same calibration would differ in its last bits
    # between a 1-core and a 2-core run (see the threadpool_limits note below).
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from crossline.errors import CrosslineError

    try:
        import cv2
        from threadpoolctl import threadpool_limits

        # Determinism: BLAS reductions and OpenCV's internal parallel loops can sum in a
        # different order with a different number of threads, which changes the last bits
        # of a calibration. So every numerical kernel runs on one thread, and a stage's
        # --threads (the rule's `threads`) is spent on its own pool of workers over images
        # or frames, whose results are combined in a fixed order.
        cv2.setNumThreads(1)
        with threadpool_limits(limits=1):
            return int(args.func(args) or 0)
    except CrosslineError as exc:
        print(f"crossline {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file the user named cannot be read or written
        where = exc.filename if exc.filename is not None else "a file"
        print(f"crossline {args.command}: error: {where}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"crossline {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: said in one line; the traceback only when asked for
        if args.verbose:
            log.exception("internal error")
        print(f"crossline {args.command}: internal error: {type(exc).__name__}: {exc} (a bug in "
              f"crossline, not in the input: please report it with this command line; -v shows "
              f"where)", file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())

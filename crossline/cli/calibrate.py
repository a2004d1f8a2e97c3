"""The ``crossline`` calibration subcommands: ``calibrate-camera``, ``-lasers``, ``-handeye``.

Each registers itself in ``crossline.cli.args.COMMANDS`` when this module is imported
(``crossline.cli`` imports it). Split from ``crossline.cli`` (issue 21.3).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from crossline.cli.args import _bool, _threads, command

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
                   help="drop views whose RMS exceeds this many times the median and 0.1 px (default 3)")
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

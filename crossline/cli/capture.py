"""The ``crossline`` subcommands on a capture folder: ``simulate`` (write one) and ``check``.

Each registers itself in ``crossline.cli.args.COMMANDS`` when this module is imported
(``crossline.cli`` imports it). Split from ``crossline.cli`` (issue 21.3).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from crossline.cli.args import _board_spec, _checked, _threads, command

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
    p.add_argument("--ball-bar", action="store_true",
                   help="add three scans of a ball bar (two balls at a known distance; "
                        "ISO 10360-8 sphere-spacing error SD)")
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
            ball_bar=a.ball_bar,
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

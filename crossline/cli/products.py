"""The ``crossline`` subcommands that make the products: ``fuse``, ``export-cloud``, ``report``,
``certificate`` (the fused cloud, its E57, the accuracy report, the calibration certificate).

Each registers itself in ``crossline.cli.args.COMMANDS`` when this module is imported
(``crossline.cli`` imports it). Split from ``crossline.cli`` (issue 21.3).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from crossline.cli.args import _auto_or_positive, _bool, _positive, _threads, _unit_interval, command

# ----------------------------------------------------------------------------- fusion, report


@command(
    "fuse",
    "fuse the points of a scan into an Open3D cloud (PLY), optionally a mesh (STL)",
    """
    Optional refinement of every frame's arm pose from the scan itself (where line A of one
    frame crosses line B of another, the two must meet; the arm's precision, stated or as the
    hand-eye views measured it, is the prior),
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
    p.add_argument("--arm-precision-mm", type=_auto_or_positive, default=0.02,
                   help="arm's stated precision, read as 2 sigma of the 3-D position error (mm); "
                        "auto: the arm's noise that the hand-eye calibration (--handeye) estimated "
                        "from its views")
    p.add_argument("--arm-precision-rad", type=_auto_or_positive, default=None,
                   help="the same for the orientation (rad); auto = the mm figure over 300 mm "
                        "(with --arm-precision-mm auto: the hand-eye's estimate, at least that)")
    p.add_argument("--handeye", type=Path,
                   help="handeye.json, whose estimate of the arm's noise --arm-precision-mm auto takes")
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
    p.add_argument("--arm-draws", type=int, default=64,
                   help="with --arm-draws-out: draw the arm's pose errors left in the cloud this "
                        "many times (the refinement's posterior, else the arm's precision above), "
                        "for the report's uncertainty (0: none)")
    p.add_argument("--arm-draws-out", type=Path,
                   help="the draws' file to write (.npz; written empty with --arm-draws 0)")
    _threads(p)

    def run(a: argparse.Namespace) -> int:
        from crossline.fuse import run_fuse

        run_fuse(
            a.points, a.out, stats=a.stats, neighbours=a.neighbours, std_ratio=a.std_ratio,
            voxel_mm=a.voxel_mm, normal_radius_mm=a.normal_radius_mm, mesh=a.mesh,
            mesh_out=a.mesh_out, threads=a.threads, refine_poses=a.refine_poses,
            frames=a.frames, handeye=a.handeye,
            arm_precision_mm="auto" if a.arm_precision_mm is None else a.arm_precision_mm,
            arm_precision_rad=a.arm_precision_rad, arm_smooth_fraction=a.arm_smooth_fraction,
            arm_corr_time_s=a.arm_corr_time_s, crossing_half_mm=a.crossing_half_mm,
            crossing_min_angle_deg=a.crossing_min_angle_deg,
            crossing_max_width_ratio=a.crossing_max_width_ratio, arm_draws=a.arm_draws,
            arm_draws_out=a.arm_draws_out,
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

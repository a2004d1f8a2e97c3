"""Captures as untrusted input, through the command line (issue 23.2): every stage that reads
a capture is run, in this process as ``crossline <command> ...`` (:func:`crossline.cli.main`),
on copies of the quick capture that hypothesis has broken at random: rig.yaml keys deleted or
set to values of any type and its bytes cut or changed; CSV cells, rows and columns of
``poses.csv`` and ``frames.csv`` changed, deleted, duplicated, swapped, renamed, reordered;
image bytes cut, changed or appended, images of another size, bit depth, channel count or
format; files and folders missing, extra files, folders and links; and names, links and
linked folders that lead out of the capture to a sentinel file beside it. fuse and the report
also read the stages' products (points, clouds, calibrations: given unbroken); what they
decode from the capture is broken: frames.csv (cells, rows, columns, valid values of another
order), rig.yaml's scans (artefacts, nominal sizes, ``nominal:`` meshes of other names, types
and places, ``nominal_pose``) and the nominal mesh's bytes, as STL or as a PLY that rig.yaml
then names (cut, flipped, appended to, empty, wrong counts, non-finite, flat or one-triangle
meshes, face indices out of range, ASCII, the other format's bytes).

For every case: exit 0 with the artefact written and readable (and sane), or exit 2 with one
``crossline <command>: error: ...`` message that names a file of the capture; never exit 3
(a bug), never a traceback (on stderr or in the log), never an artefact, a side file or a
temporary ``.<name>.*.tmp`` left behind by a failed run, never a file written into the
capture, and never a file opened outside the capture (every ``open`` is watched through an
audit hook; the sentinels are a valid board image and a valid mesh, so a read of one would
otherwise pass). Paths out of the capture must be refused, naming the row of poses.csv, the
rig.yaml key or the link: for fuse, frames.csv or its folders linked to copies beside the
capture; for the report, ``nominal:`` names out of it, part.stl linked to the sentinel mesh,
frames.csv, truth.json, poses.csv, rig.yaml or a scan's folders linked out.

Cases tried (hypothesis with a fixed seed per command: the same cases on every run; no
shrinking, so that a failure costs no more than its case). A random case is one or two
corruptions of what the command itself decodes (its images, valid but different rig.yaml
values and table cells, reordered or extra columns), at times with one more anywhere:

=================================  ==================  ====================  ========
command                            random corruptions  paths out (sentinel)  explicit
=================================  ==================  ====================  ========
check --json                       12                  4
calibrate-camera --views camera    6                   3
calibrate-lasers                   4                   3
calibrate-handeye                  6                   3                     1
extract-stripes --chunk 1/6        10                  4
triangulate                        10                  4
fuse (workflow's command line)     16                  4                     2 + 1 xfail
report (one scan's worth)          6                   6                     2
=================================  ==================  ====================  ========

107 cases in all (70 random, 31 paths out, 6 cases found once and kept, one of them an
expected failure), about 40 s of one core for the first six commands (most of it the
calibrations that pass) and about 16 s for fuse and the report (products built once included).
``CROSSLINE_FUZZ_SCALE=N`` multiplies the random and path-out cases (a longer hunt, off the
suite: N = 4 for the camera and lasers, 8 for hand-eye, 30 for the others found the case
below and nothing else; N = 10 for fuse and the report found the cases below, N = 15 then
nothing more).
The capture fuzzed is the quick capture of conftest.py without laser pose_02 and hand-eye
views 05-07 (a calibration that passes then decodes fewer images); the commands get the
rig's true calibrations from truth.json, triangulate the stripes of the unbroken capture.
fuse runs as workflow/rules/fuse.smk runs it (config.yaml's values, --refine-poses true,
--frames scans/plate/frames.csv) on the plate's points. The report runs as
workflow/rules/report.smk runs it, its --config-json config.yaml's less the Monte Carlo (2
draws on 2000 points: enough to read frames.csv again), on interim/processed folders holding
two scans' points and fused clouds: plate (a plane, whose uncertainty reads frames.csv with
the capture's reader) and part (a freeform, which reads and aligns the nominal mesh); the
capture's gauge and ball have no points (their frames.csv are read, not measured), and
truth.json is read and scored. Broken products (points, clouds, calibrations, ...) are
test_products_fuzz.py's. Not covered: a one-line or ball-bar scan's figures, the certificate.
The capture reader alone is fuzzed much harder (800 cases) in test_capture_fuzz.py.

Found: calibrate-handeye on arm poses that do not rotate (every row of poses.csv the same)
said "degenerate hand-eye motion: only 0 of 10 motion pairs rotate ..." without naming a
file; run_calibrate_handeye now names calibration/handeye/poses.csv (and calibration/handeye
when too few views show the board).
fuse on a frames.csv with two rows' frame numbers swapped (times no longer increasing with the
numbers) exited 3 ("ValueError: `times` must give one increasing time per frame of `frames`"
from the pose refinement): fuse.inputs._read_frames now names the file and the two frames.
The report read truth.json, calibration/handeye/poses.csv and frames.csv (or a scan's folder)
through links out of the capture, and read frames.csv leniently (pandas): a cell holding a
comma gave it other laser states and "internal error: ValueError: number sections must be
larger than 0" drawing their legend; build_report now refuses links out and checks each
frames.csv with the capture's reader, naming the row. A flat nominal mesh (all vertices in
one plane) exited 3 with Open3D's qhull error in the coarse alignment; nominal_align._fpfh
now says the surface is flat and asks for a datum (the report goes on without the
comparison). Fuse on a frames.csv without one of the points' frames (its last frame
renumbered) said "pose refinement: frame(s) [23] of the points are not in the scan's frames
table", naming no file; run_fuse now checks the points' frames against the table first
(fuse.inputs._frames_in_table) and names frames.csv.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import re
import shutil
import sys
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, Phase, currently_in_test_context, example, given, note, seed, settings
from hypothesis import strategies as st

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("cli_fuzz")]

# --------------------------------------------------------------------------- the capture fuzzed

DROPPED = ("calibration/laser_A/pose_02_board.png", "calibration/laser_A/pose_02_laser.png",
           "calibration/laser_B/pose_02_board.png", "calibration/laser_B/pose_02_laser.png",
           "calibration/handeye/pose_05.png", "calibration/handeye/pose_06.png",
           "calibration/handeye/pose_07.png")
SENTINEL = "sentinel.png"  # beside the capture copy, never to be opened
CHUNK = (1, 6)  # extract-stripes' chunk: frames 4..7 of the plate's 24


class Env:
    """The module's unbroken capture, calibrations and stripes, and where cases are made."""

    def __init__(self, work: Path, base: Path, cal: Path, originals: tuple[Path, ...]):
        self.work, self.base, self.cal, self.originals = work, base, cal, originals
        self.files = sorted(p.relative_to(base).as_posix() for p in base.rglob("*") if p.is_file())
        self.dirs = sorted(p.relative_to(base).as_posix() for p in base.rglob("*") if p.is_dir())
        self.images = [f for f in self.files if f.endswith(".png")]
        self.snapshot = _snapshot(base)


def _snapshot(root: Path) -> dict[str, tuple[int, int, int]]:
    return {p.relative_to(root).as_posix(): (s.st_size, s.st_mtime_ns, s.st_ino)
            for p in root.rglob("*") if p.is_file() for s in [p.stat()]}


@pytest.fixture(scope="module")
def env(quick_capture: Path, tmp_path_factory) -> Env:
    return build_env(quick_capture, tmp_path_factory.mktemp("cli-fuzz"))


def build_env(quick_capture: Path, work: Path) -> Env:
    """The capture fuzzed (a copy of the quick capture in ``work``), the rig's true
    calibrations and the plate's stripes (in ``work/cal``)."""
    from crossline.camera import Camera
    from crossline.cli import main
    from crossline.io.atomic import write_json
    from crossline.laser import LaserPlanes

    base = work / "base" / "cap"
    # a real copy (cases are hard links of it: the session's cached capture is never linked)
    shutil.copytree(quick_capture, base, ignore=lambda d, names: [
        n for n in names if (Path(d) / n).relative_to(quick_capture).as_posix() in DROPPED])
    poses = base / "calibration/handeye/poses.csv"
    rows = poses.read_text().splitlines()
    poses.write_text("\n".join(r for r in rows if r.split(",")[0] not in
                               {Path(d).name for d in DROPPED}) + "\n")
    cal = work / "cal"
    cal.mkdir()
    truth = json.loads((base / "truth.json").read_text())
    c = truth["camera"]
    Camera(np.array(c["K"]), np.array(c["dist"]), tuple(c["image_size"])).save(cal / "camera.json")
    LaserPlanes.from_dict(truth["lasers"]).save(cal / "lasers.json")
    # with the arm's true noise as the refinement's estimate of it (fuse's prior, config's auto)
    arm = {"arm_sigma_mm": truth["arm_noise"]["sigma_axis_mm"],
           "arm_sigma_rad": truth["arm_noise"]["rot_sigma_axis_rad"]}
    write_json(cal / "handeye.json", {"T_tool_cam": truth["T_tool_cam"], "method": "truth",
                                      "methods": {"refined": {"noise_model": arm}}})
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(["extract-stripes", str(base), "plate", "--out", str(cal / "stripes.parquet")])
    assert code == 0, err.getvalue()
    return Env(work, base, cal, (quick_capture.resolve(), base.resolve()))


REPO = Path(__file__).resolve().parents[1]
PRODUCTS = ("fuse", "report")  # the commands that read the products of the stages as well
FUSED = "plate"  # the scan fused; the report reads plate (a plane: its uncertainty reads
REPORTED = ("plate", "part")  # frames.csv again) and part (a freeform: its nominal mesh)


@pytest.fixture(scope="module")
def products(env: Env) -> Path:
    """The stages' products that fuse and the report read beside the capture (interim/ and
    processed/ in ``env.work``, as the workflow lays them out): the points of plate and part
    (triangulated with the true calibrations) and their fused clouds; and part.stl as a PLY."""
    import open3d as o3d

    from crossline.cli import main

    interim, processed = env.work / "interim", env.work / "processed"
    (interim / "points").mkdir(parents=True)
    processed.mkdir()
    shutil.copytree(env.cal, interim / "calibration", ignore=lambda d, names: ["stripes.parquet"])
    err = io.StringIO()
    for scan in REPORTED:
        stripes = env.cal / "stripes.parquet" if scan == "plate" else env.work / f"{scan}-stripes.parquet"
        points = interim / "points" / f"{scan}.parquet"
        runs = [] if scan == "plate" else [["extract-stripes", env.base, scan, "--out", stripes]]
        runs += [["triangulate", env.base, scan, "--stripes", stripes, "--camera", env.cal / "camera.json",
                  "--lasers", env.cal / "lasers.json", "--handeye", env.cal / "handeye.json",
                  "--out", points],
                 _fuse_argv(points, env.base / "scans" / scan / "frames.csv", processed / f"{scan}.ply",
                            processed / f"{scan}.fuse.json", env.cal / "handeye.json")]
        for argv in runs:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                code = main([str(a) for a in argv])
            assert code == 0, err.getvalue()
    mesh = o3d.io.read_triangle_mesh(str(env.base / "part.stl"))
    assert o3d.io.write_triangle_mesh(str(env.work / "part.ply"), mesh, write_ascii=False)
    return env.work


def _fuse_argv(points: Path, frames: Path, cloud: Path, stats: Path, handeye: Path,
               arm: Path | None = None) -> list:
    """fuse's command line as workflow/rules/fuse.smk gives it, with config.yaml's values (the
    arm's draws written to ``arm`` when given)."""
    c = yaml.safe_load((REPO / "config.yaml").read_text())["fuse"]
    opts = {k: c[k] for k in ("neighbours", "std_ratio", "voxel_mm", "normal_radius_mm", "mesh")}
    more = {k: c[k] for k in ("arm_precision_mm", "arm_precision_rad", "arm_smooth_fraction",
                              "arm_corr_time_s", "crossing_half_mm", "crossing_min_angle_deg",
                              "crossing_max_width_ratio")}
    flag = [(f"--{k.replace('_', '-')}", v) for k, v in opts.items()]
    flag += [("--mesh-out", cloud.with_suffix(".stl")), ("--refine-poses", str(c["refine_poses"]).lower()),
             ("--frames", frames), ("--handeye", handeye)]
    flag += [(f"--{k.replace('_', '-')}", v) for k, v in more.items()]
    if arm is not None:
        flag += [("--arm-draws", c["arm_draws"]), ("--arm-draws-out", arm)]
    return ["fuse", points, "--out", cloud, "--stats", stats, *[x for f in flag for x in f], "--threads", 1]


def _report_config() -> str:
    """The report's --config-json as workflow/rules/common.smk's report_config() gives it, less
    the Monte Carlo (2 draws on 2000 points: its reading of frames.csv, not its figures)."""
    c = yaml.safe_load((REPO / "config.yaml").read_text())
    full = {k: c[k] for k in ("camera", "lasers", "handeye", "stripes", "points", "fuse", "report")}
    full["report"]["metrology"].update(uncertainty_draws=2, uncertainty_points=2000)
    return json.dumps(full, sort_keys=True)


# --------------------------------------------------------------------------- the commands


def _argv(command: str, root: Path, out: Path, cal: Path) -> tuple[list, Path]:
    """The command line of ``command`` on capture ``root`` and the artefact it writes in ``out``."""
    calib = ["--camera", cal / "camera.json"]
    argv, art = {
        "check": (["check", root, "--json", out / "check.json"], out / "check.json"),
        "calibrate-camera": (["calibrate-camera", root, "--views", "camera", "--out", out / "camera.json"],
                             out / "camera.json"),
        "calibrate-lasers": (["calibrate-lasers", root, *calib, "--out", out / "lasers.json"],
                             out / "lasers.json"),
        "calibrate-handeye": (["calibrate-handeye", root, *calib, "--out", out / "handeye.json"],
                              out / "handeye.json"),
        "extract-stripes": (["extract-stripes", root, "plate", "--chunk", f"{CHUNK[0]}/{CHUNK[1]}",
                             "--out", out / "stripes.parquet"], out / "stripes.parquet"),
        "triangulate": (["triangulate", root, "plate", "--stripes", cal / "stripes.parquet", *calib,
                         "--lasers", cal / "lasers.json", "--handeye", cal / "handeye.json",
                         "--out", out / "points.parquet"], out / "points.parquet"),
        "fuse": (_fuse_argv(cal.parent / "interim" / "points" / f"{FUSED}.parquet",
                            root / "scans" / FUSED / "frames.csv", out / f"{FUSED}.ply",
                            out / f"{FUSED}.fuse.json", cal / "handeye.json"), out / f"{FUSED}.ply"),
        "report": (["report", root, "--interim", cal.parent / "interim",
                    "--processed", cal.parent / "processed",
                    "--config-json", _report_config(), "--pdf", out / "accuracy.pdf",
                    "--metrics", out / "metrics.json", "--deviation-dir", out / "deviation"],
                   out / "metrics.json"),
    }[command]
    return [str(a) for a in argv], art


def _read_artefact(command: str, art: Path) -> None:
    """The artefact of a run that passed: readable, and what it holds is sane."""
    import pandas as pd

    if command == "check":
        summary = json.loads(art.read_text())
        assert isinstance(summary, dict) and "stages" in summary
    elif command == "calibrate-camera":
        from crossline.camera import Camera

        cam = Camera.load(art)
        assert np.all(np.isfinite(cam.K)) and np.all(np.isfinite(cam.dist)) and cam.fx > 0
    elif command == "calibrate-lasers":
        from crossline.laser import LaserPlanes

        planes = LaserPlanes.load(art)
        for name in planes.names:
            p = planes[name]
            assert np.isfinite(p.d) and abs(np.linalg.norm(p.normal) - 1) < 1e-9
    elif command == "calibrate-handeye":
        from crossline.calibrate.handeye import HandEye

        T = HandEye.load(art).T_tool_cam
        assert np.all(np.isfinite(T)) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    elif command == "fuse":
        from crossline.io.ply import read_ply

        cloud = read_ply(art)
        assert len(cloud["points"]) and np.all(np.isfinite(cloud["points"]))
        stats = json.loads(art.with_name(f"{FUSED}.fuse.json").read_text())
        assert stats["parameters"]["refine_poses"] is True and "refine" in stats
    elif command == "report":
        metrics = json.loads(art.read_text())
        assert metrics["result"] in ("PASS", "FAIL", "INCOMPLETE")
        assert sorted(metrics["scans"]) == metrics["capture"]["scans"]
        assert (art.parent / "accuracy.pdf").read_bytes().startswith(b"%PDF")
    elif command == "export-cloud":
        from crossline.io.clouds import read_e57

        cloud = read_e57(art)
        assert len(cloud["points"]) and np.all(np.isfinite(cloud["points"]))
    else:
        table = pd.read_parquet(art)
        cols = ["u", "v"] if command == "extract-stripes" else ["x", "y", "z"]
        assert np.all(np.isfinite(table[cols].to_numpy()))
        if command == "triangulate":
            assert set(table["laser"]) <= {"A", "B"}


# images and folders each command reads (corruptions pick among them as often as among all);
# triangulate reads no image: the frames of its scan, which it must do without
def _relevant(env: Env, command: str) -> tuple[list[str], list[str]]:
    frames = [f"scans/plate/frames/{i:06d}.png" for i in range(4 * CHUNK[0], 4 * CHUNK[0] + 4)]
    images = {
        "check": env.images,
        "calibrate-camera": [f for f in env.images if f.startswith("calibration/camera/")],
        "calibrate-lasers": [f for f in env.images if f.startswith("calibration/laser_")],
        "calibrate-handeye": [f for f in env.images if f.startswith("calibration/handeye/")],
        "extract-stripes": frames,
        "triangulate": frames,
        "fuse": frames,  # reads none: for the corruptions anywhere
        "report": frames,
    }[command]
    folders = {
        "check": ["calibration/camera", "calibration/handeye", "calibration/laser_B", "scans/gauge/frames"],
        "calibrate-camera": ["calibration/camera", "calibration"],
        "calibrate-lasers": ["calibration/laser_A", "calibration/laser_B"],
        "calibrate-handeye": ["calibration/handeye"],
        "extract-stripes": ["scans/plate/frames", "scans/plate"],
        "triangulate": ["scans/plate", "scans"],
        "fuse": ["scans/plate", "scans"],
        "report": ["scans/part", "scans", "truth"],
    }[command]
    return images, folders


# --------------------------------------------------------------------------- corruptions

TABLES = ("calibration/handeye/poses.csv", "scans/plate/frames.csv", "scans/gauge/frames.csv")
OUT = "@OUT"  # placeholder: the absolute path of the sentinel beside the capture copy
cell = st.one_of(
    st.text(st.characters(exclude_categories=("Cs",)), max_size=10),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10, 10**12).map(str),
    st.sampled_from(["A", "B", "AB", "off", "", "nan", "1e309", "-0", "000001", "pose_00.png",
                     "../../../sentinel.png", "../sentinel.png", OUT, "0.5", "2"]),
)
leaf = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 70000), st.floats(allow_nan=True),
    st.text(st.characters(exclude_categories=("Cs",)), max_size=10),
    st.sampled_from(["A", "B", "AB", "red", "grey", "freeform", "plane", "sphere", "part.stl",
                     "../sentinel.png", OUT, "symmetric", "chessboard", 8, 12, 16, 3072, 2048, 0]),
    st.sampled_from([["A"], ["B"], ["A", "B"], ["A", "A"], [], ["C"]]),
)
value = st.recursive(leaf, lambda kids: st.lists(kids, max_size=3)
                     | st.dictionaries(st.text(max_size=8), kids, max_size=3), max_leaves=6)
RIG_EXTRA_PATHS = [("frame_rat",), ("lasers",), ("sensor", "channel"), ("sensor", "data_bits"),
                   ("scans", "plate", "nominal"), ("scans", "extra"), ("board", "colour")]
IMAGE_KINDS = ("short_row", "narrow", "transposed", "tiny", "deep", "deep_scaled", "colour",
               "blank", "saturated", "dark", "mirror", "shift", "half", "jpeg_bytes", "tiff_renamed",
               "bmp_renamed", "empty")
EXTRA_NAMES = ("zz.png", "view_99.png", "pose_99.png", "pose_09_laser.png", "pose_00_board.tif",
               "999999.png", ".hidden.png", "notes.txt", "frames.csv.bak", "sub", "poses.csv~")
# values of the right type that pass rig.yaml's check but change what the commands do
RIG_VALID = (
    (("sensor", "bit_depth"), 16), (("sensor", "data_bits"), 6), (("sensor", "data_bits"), 8),
    (("sensor", "channel"), "red"), (("sensor", "channel"), "grey"), (("sensor", "width"), 3071),
    (("sensor", "height"), 2049), (("scan_window", "x"), 208), (("scan_window", "x"), 414),
    (("scan_window", "y"), 0), (("scan_window", "height"), 801), (("scan_window", "width"), 2656),
    (("frame_rate",), 1e-6), (("frame_rate",), 1e9), (("board", "cols"), 14), (("board", "rows"), 15),
    (("board", "spacing"), 4.0), (("board", "spacing"), 1e-3), (("board", "diameter"), 3.7),
    (("board", "circles"), "light"), (("board", "pattern"), "asymmetric"),
    (("board", "pattern"), "chessboard"), (("lasers",), ["A"]), (("lasers",), ["B", "A"]),
    (("lasers",), ["B"]), (("scans", "plate", "artefact"), "freeform"),
    (("scans", "gauge", "height"), 1e-9), (("scans", "ball", "diameter"), 1e6),
)
# changes of a table's cells that keep it well formed: (column, what)
CSV_VALID = (("lasers", "A"), ("lasers", "B"), ("lasers", "AB"), ("lasers", "off"), ("frame", "swap"),
             ("frame", "+1000"), ("time_s", "same"), ("time_s", "back"), ("x", "+1000"), ("z", "-1e6"),
             ("qw", "negate"), ("qw", "identity"), ("image", "swap"), ("x", "all same"))
flips = st.lists(st.tuples(st.integers(0, 10**7), st.integers(0, 255)), max_size=4)
ESCAPES = ("row_rel", "row_abs", "row_deep", "link_abs", "link_rel", "link_dir", "link_table")


def _key_paths(d: dict, prefix: tuple = ()) -> list[tuple]:
    out = []
    for k, v in d.items():
        out.append((*prefix, k))
        if isinstance(v, dict):
            out += _key_paths(v, (*prefix, k))
    return out


def escapes(env: Env, command: str):
    images, folders = _relevant(env, command)
    return st.tuples(st.just("escape"), st.sampled_from(ESCAPES), st.integers(0, 30),
                     st.sampled_from(images), st.sampled_from(folders))


def corruptions(env: Env, command: str):
    """What :func:`_apply` carries out on a capture: one or two corruptions of what the command
    itself decodes (its images' bytes, size, depth, channels, format, content; one of them
    missing or an extra one beside them; a table's columns reordered or extended: most of
    these pass the capture's check and reach the command's own reading), then at times one
    anywhere (rig.yaml, the CSV tables, files missing or extra, a path out): most of these are
    refused when the capture is opened (the reader alone is fuzzed in test_capture_fuzz.py)."""
    images, folders = _relevant(env, command)
    img_bytes, img_kind, extra = _img_bytes, _img_kind, _extra

    def csv_col(hows):
        return st.tuples(st.just("csv_col"), st.sampled_from(TABLES), st.sampled_from(hows),
                         st.integers(0, 9), st.integers(0, 9))

    rig_valid = st.sampled_from(RIG_VALID).map(lambda kv: ("rig_key", kv[0], ("set", kv[1])))
    csv_valid = st.tuples(st.just("csv_valid"), st.sampled_from(TABLES), st.integers(0, 30),
                          st.sampled_from(CSV_VALID))
    deep = st.one_of(
        img_bytes(images), img_kind(images), img_bytes(images), img_kind(images), rig_valid, csv_valid,
        st.tuples(st.just("missing"), st.sampled_from(images)), extra(folders),
        csv_col(["reorder", "extra", "spaces"]),
        st.tuples(st.just("csv_row"), st.sampled_from(TABLES), st.sampled_from(["crlf", "blank"]),
                  st.integers(0, 30), st.integers(0, 30)),
    )
    return st.tuples(st.lists(deep, min_size=1, max_size=2),
                     st.lists(_anywhere(env, command), max_size=1)).map(lambda t: t[0] + t[1])



def _csv_breaks(tables: list, cell: st.SearchStrategy) -> tuple:
    """Strategies breaking a cell, a row or a column of one of ``tables`` (CSV paths)."""
    return (
        st.tuples(st.just("csv_cell"), st.sampled_from(tables), st.integers(0, 30), st.integers(0, 9), cell),
        st.tuples(st.just("csv_row"), st.sampled_from(tables),
                  st.sampled_from(["delete", "duplicate", "swap", "blank", "junk", "cut", "header_only",
                                   "empty", "no_header", "crlf", "bom", "latin1"]),
                  st.integers(0, 30), st.integers(0, 30)),
        st.tuples(st.just("csv_col"), st.sampled_from(tables),
                  st.sampled_from(["drop", "rename", "extra", "reorder", "duplicate", "upper", "spaces"]),
                  st.integers(0, 9), st.integers(0, 9)),
    )

def _anywhere(env: Env, command: str):
    """One corruption anywhere in the capture (rig.yaml, the CSV tables, images, files missing
    or extra, a path out)."""
    rig_paths = _key_paths(yaml.safe_load((env.base / "rig.yaml").read_text())) + RIG_EXTRA_PATHS
    return st.one_of(
        st.tuples(st.just("rig_key"), st.sampled_from(rig_paths),
                  st.just("delete") | value.map(lambda v: ("set", v))),
        st.tuples(st.just("rig_bytes"), st.integers(0, 1200), flips, st.binary(max_size=24)),
        *_csv_breaks(TABLES, cell),
        _img_bytes(env.images), _img_kind(env.images),
        st.tuples(st.just("missing"), st.sampled_from(env.files + env.dirs)),
        _extra(env.dirs),
        escapes(env, command),
    )


def _img_bytes(names):
    return st.tuples(st.just("img_bytes"), st.sampled_from(names), st.integers(0, 10**7), flips,
                     st.binary(max_size=24))


def _img_kind(names):
    return st.tuples(st.just("img_kind"), st.sampled_from(names), st.sampled_from(IMAGE_KINDS))


def _extra(dirs):
    return st.tuples(st.just("extra"), st.sampled_from(dirs), st.sampled_from(EXTRA_NAMES),
                     st.sampled_from(["bytes", "image", "folder", "link_in"]), st.binary(max_size=24))


# fuse and the report: what they decode from the capture is frames.csv, and for the report
# rig.yaml's scans (artefacts, nominal sizes, nominal meshes) and the nominal mesh's bytes
FRAMES_OF = {"fuse": (f"scans/{FUSED}/frames.csv",),
             "report": tuple(f"scans/{s}/frames.csv" for s in REPORTED)}
# frames.csv changes that keep it well formed, beyond CSV_VALID's: frames and times of another scan
FRAMES_VALID = (("frame", "renumber"), ("frame", "renumber"), ("time_s", "+1000"), ("time_s", "-1e6"),
                ("y", "+1000"), ("lasers", "A"), ("lasers", "off"))
DELETE = "delete"
REPORT_RIG = (  # rig.yaml's scans: (key path, "delete" or the value set)
    (("scans", "part", "artefact"), "plane"), (("scans", "part", "artefact"), "sphere"),
    (("scans", "part", "artefact"), "gauge_block"), (("scans", "part", "artefact"), "ball_bar"),
    (("scans", "plate", "artefact"), "freeform"), (("scans", "plate", "artefact"), "sphere"),
    (("scans", "plate", "artefact"), "ball_bar"), (("scans", "plate", "nominal"), "part.stl"),
    (("scans", "part", "nominal"), DELETE), (("scans", "part", "nominal"), "truth/part.ply"),
    (("scans", "part", "nominal"), "PART.stl"), (("scans", "part", "nominal"), "part.STL"),
    (("scans", "part", "nominal"), "./part.stl"), (("scans", "part", "nominal"), "rig.yaml"),
    (("scans", "part", "nominal"), "scans/part/frames.csv"), (("scans", "part", "nominal"), "truth"),
    (("scans", "part", "nominal"), "truth/part_poses.parquet"), (("scans", "part", "nominal"), ""),
    (("scans", "part", "nominal"), 5), (("scans", "part", "nominal"), ["part.stl"]),
    (("scans", "part", "nominal_pose"), [0, 0, 0, 1, 0, 0, 0]),
    (("scans", "part", "nominal_pose"), [1e9, 0, 0, 1, 0, 0, 0]),
    (("scans", "part", "nominal_pose"), [float("nan")] * 7), (("scans", "part", "nominal_pose"), [1, 2]),
    (("scans", "plate"), DELETE), (("scans", "part"), DELETE), (("scans",), DELETE), (("scans",), {}),
    (("scans", "plate", "diameter"), 25.0), (("scans", "ball", "diameter"), 1e-9),
    (("scans", "gauge", "height"), -1.0), (("scans", "extra"), {"artefact": "plane"}),
    (("scans", "plate"), "plane"), (("lasers",), ["A"]), (("lasers",), ["B"]), (("capture_date",), DELETE),
)
REPORT_RIG_PATHS = [("scans", "part", "nominal"), ("scans", "part", "artefact"),
                    ("scans", "plate", "artefact"), ("scans", "part", "nominal_pose"), ("scans", "part"),
                    ("scans",)]
# a nominal mesh's bytes (part.stl, or part.ply that rig.yaml then names)
MESH_KINDS = ("cut", "flips", "tail", "empty", "count", "nan", "flat", "one", "index", "ascii",
              "other_format", "text")
STL_TRIANGLE = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
PRODUCT_ESCAPES = {"fuse": ("frames_abs", "frames_rel", "scan_dir", "scans_dir"),
                   "report": ("nominal_rel", "nominal_abs", "nominal_deep", "mesh_abs", "mesh_rel",
                              "frames_abs", "frames_rel", "scan_dir", "scans_dir", "truth_link", "poses_link",
                              "rig_link")}
MESH_SENTINEL = "sentinel.stl"  # beside the capture copy: a valid mesh, never to be opened


def product_escapes(command: str):
    return st.tuples(st.just("product_escape"), st.sampled_from(PRODUCT_ESCAPES[command]),
                     st.sampled_from(FRAMES_OF[command]))


def product_corruptions(env: Env, command: str):
    """fuse's and the report's corruptions: one or two of what the command decodes from the
    capture (its frames.csv tables' cells, rows, columns, valid values of another scan; for the
    report also rig.yaml's scans and the nominal mesh's bytes, as STL or as PLY), then at times
    one anywhere (:func:`_anywhere`, a path out among them)."""
    tables = FRAMES_OF[command]
    csv = st.one_of(
        st.tuples(st.just("csv_valid"), st.sampled_from(tables), st.integers(0, 30),
                  st.sampled_from(CSV_VALID + FRAMES_VALID)),
        *_csv_breaks(tables, cell),
    )
    deep = csv
    if command == "report":
        rig = st.one_of(
            st.sampled_from(REPORT_RIG).map(
                lambda kv: ("rig_key", kv[0], kv[1] if kv[1] == DELETE else ("set", kv[1]))),
            st.tuples(st.just("rig_key"), st.sampled_from(REPORT_RIG_PATHS), value.map(lambda v: ("set", v))),
        )
        mesh = st.tuples(st.just("mesh"), st.sampled_from(["stl", "ply"]), st.sampled_from(MESH_KINDS),
                         st.integers(0, 200) | st.integers(0, 10**7), flips, st.binary(max_size=24))
        deep = st.one_of(csv, rig, mesh, mesh)
    return st.tuples(st.lists(deep, min_size=1, max_size=2),
                     st.lists(_anywhere(env, command), max_size=1)).map(lambda t: t[0] + t[1])


def _ply_bytes(V: np.ndarray, F: np.ndarray, ascii_: bool = False) -> bytes:
    """A PLY of vertices (float32 x, y, z) and triangles (uchar count, int indices)."""
    fmt = "ascii" if ascii_ else "binary_little_endian"
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
    if ascii_:
        body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in V.tolist())
        body += "".join(f"3 {a} {b} {c}\n" for a, b, c in F.tolist())
        return (head + body).encode()
    faces = np.zeros(len(F), np.dtype([("k", "u1"), ("i", "<i4", 3)]))
    faces["k"], faces["i"] = 3, F
    return head.encode() + np.asarray(V, "<f4").tobytes() + faces.tobytes()


def _stl_bytes(tri: np.ndarray) -> bytes:
    return b"crossline fuzz".ljust(80, b" ") + np.uint32(len(tri)).tobytes() + tri.tobytes()


def _mesh(op: tuple, root: Path, case: Path) -> str | None:
    """A nominal mesh broken: part.stl, or part.ply (the same triangles) that rig.yaml then names."""
    _, fmt, how, n, fl, tail = op
    stl = root / "part.stl"
    if not stl.is_file() or stl.is_symlink():
        return None
    data = stl.read_bytes()
    if len(data) < 84 or (len(data) - 84) % STL_TRIANGLE.itemsize:
        return None  # broken by an earlier corruption
    tri = np.frombuffer(data, STL_TRIANGLE, offset=84).copy()
    if len(tri) == 0 or len(tri) != np.frombuffer(data, "<u4", 1, 80)[0]:
        return None
    V = tri["v"].reshape(-1, 3)
    F = np.arange(len(V)).reshape(-1, 3)
    if fmt == "ply":
        p = root / "part.ply"
        if _apply(("rig_key", ("scans", "part", "nominal"), ("set", "part.ply")), root, case) is None:
            return None
        data = _ply_bytes(V, F)
    else:
        p = stl
    k = n % len(F)
    if how == "cut":
        data = data[: n % (len(data) + 1)]
    elif how == "flips":
        data = bytearray(data)
        for at, v in fl:
            data[at % len(data)] = v
        data = bytes(data)
    elif how == "tail":
        data = data + tail
    elif how == "empty":
        data = b""
    elif how == "count":  # the triangle (face) count says another number than the file holds
        m = (0, 1, len(F) + 1, len(F) - 1, 2**31 - 1)[n % 5]
        data = (data[:80] + np.uint32(m).tobytes() + data[84:] if fmt == "stl" else
                data.replace(f"element face {len(F)}\n".encode(), f"element face {m}\n".encode(), 1))
    elif how in ("nan", "flat", "one", "index"):
        V = V.copy()
        if how == "nan":
            V[3 * k: 3 * k + 3 * (1 + n % 1000)] = (np.nan, np.inf, -np.inf)[n % 3]
        elif how == "flat":
            V[:, n % 3] = 0.0
        elif how == "one":
            V, F = V[3 * k: 3 * k + 3], F[:1]
        elif how == "index" and fmt == "ply":
            F = F.copy()
            F[k] = (len(V), -1, 2**31 - 1)[n % 3]
        tri = tri.copy()[: len(F)]
        tri["v"] = V[F] if how != "index" else tri["v"]
        data = _ply_bytes(V, F) if fmt == "ply" else _stl_bytes(tri)
    elif how == "ascii":
        if fmt == "ply":
            data = _ply_bytes(V[:6], np.array([[0, 1, 2], [3, 4, 5 + n % 3]]), ascii_=True)
        else:
            data = ("solid part\n" + "".join(
                "facet normal 0 0 1\nouter loop\n" + "".join(f"vertex {x!r} {y!r} {z!r}\n" for x, y, z in t)
                + "endloop\nendfacet\n" for t in tri["v"][:3].tolist()) + "endsolid\n").encode()
            data = data[: len(data) - n % 40]
    elif how == "other_format":  # the bytes of the other format under this one's name
        data = _stl_bytes(tri) if fmt == "ply" else _ply_bytes(V, F)
    elif how == "text":
        data = b"not a mesh\n" + tail
    _replace(p, data)
    return f"{p.name} ({fmt}): {how} {n}"


def _product_escape(op: tuple, root: Path, case: Path) -> tuple[str | None, list[str]]:
    """A path out of the capture for fuse and the report: a description and the texts the
    refusal must hold. Links lead to copies of the files beside the capture (a read of one
    would otherwise pass) or to the sentinel mesh."""
    _, how, table = op
    scan = table.split("/")[1]
    outside = case / "outside"
    outside.mkdir(exist_ok=True)
    if how.startswith("nominal_"):
        mesh = case / MESH_SENTINEL
        name = {"nominal_rel": "../sentinel.stl", "nominal_abs": str(mesh),
                "nominal_deep": "truth/../../sentinel.stl"}[how]
        if _apply(("rig_key", ("scans", "part", "nominal"), ("set", name)), root, case) is None:
            return None, []
        why = "is an absolute path" if how == "nominal_abs" else "leads out of its folder"
        return f"rig.yaml scans.part.nominal: {name!r}", ["rig.yaml", "'scans.part.nominal' = '", why]
    if how.startswith("mesh_"):
        p, mesh = root / "part.stl", case / MESH_SENTINEL
        p.unlink()
        p.symlink_to(mesh if how == "mesh_abs" else Path(os.path.relpath(mesh, p.parent)))
        return "part.stl: link to the sentinel mesh", [f"'scans.part.nominal' = 'part.stl' is a symbolic "
                                                      f"link to {mesh}"]
    if how.startswith("frames_") or how.endswith("_link"):
        rel = {"truth_link": "truth.json", "poses_link": "calibration/handeye/poses.csv",
               "rig_link": "rig.yaml"}.get(how, table)
        p = root / rel
        target = outside / rel.replace("/", "_")
        shutil.copyfile(p, target)
        p.unlink()
        p.symlink_to(target if how != "frames_rel" else Path(os.path.relpath(target, p.parent)))
        return f"{rel}: link to a copy beside the capture", [f"{rel}: is a symbolic link to {target}"]
    folder = f"scans/{scan}" if how == "scan_dir" else "scans"
    target = outside / folder.replace("/", "_")
    (root / folder).rename(target)
    (root / folder).symlink_to(target)
    return f"{folder}: linked to {target}", [f"lies behind a symbolic link to {target}/"]


def _replace(p: Path, data: bytes) -> None:
    """New bytes for ``p`` under a new inode: the copy's files are hard links of the base's."""
    if p.is_symlink() or p.is_file():
        p.unlink()
    elif p.is_dir():
        shutil.rmtree(p)
    p.write_bytes(data)


def _csv_rows(p: Path) -> list[list[str]] | None:
    if not p.is_file() or p.is_symlink():
        return None
    return [r.split(",") for r in p.read_text(encoding="utf-8", errors="replace").splitlines()]


def _write_rows(p: Path, rows: list[list[str]]) -> None:
    _replace(p, ("\n".join(",".join(r) for r in rows) + "\n").encode("utf-8", "surrogatepass"))


def _apply(op: tuple, root: Path, case: Path) -> str | None:
    """Carry out one corruption on the capture copy ``root``; a description, or None if it
    found nothing to change (an earlier corruption removed its file)."""
    from crossline.io.images import ImageError, read_image, write_image

    kind = op[0]
    sentinel = case / SENTINEL
    if kind == "rig_key":
        _, path, what = op
        p = root / "rig.yaml"
        if not p.is_file() or p.is_symlink():
            return None
        try:
            data = yaml.safe_load(p.read_text())
        except (yaml.YAMLError, UnicodeDecodeError):
            return None
        node = data
        for k in path[:-1]:
            if not isinstance(node, dict):
                return None
            node = node.setdefault(k, {})
        if not isinstance(node, dict):
            return None
        if what == "delete":
            node.pop(path[-1], None)
        else:
            v = what[1]
            node[path[-1]] = str(sentinel) if v == OUT else v
        _replace(p, yaml.safe_dump(data, sort_keys=False, allow_unicode=True).encode())
        return f"rig.yaml {'.'.join(map(str, path))}: {what}"
    if kind == "rig_bytes":
        _, cut, fl, tail = op
        p = root / "rig.yaml"
        if not p.is_file() or p.is_symlink():
            return None
        data = bytearray(p.read_bytes())
        data = data[: cut % (len(data) + 1)]
        for at, v in fl:
            if data:
                data[at % len(data)] = v
        _replace(p, bytes(data) + tail)
        return f"rig.yaml bytes: cut {cut}, flips {fl}, tail {tail!r}"
    if kind in ("csv_cell", "csv_row", "csv_col"):
        table = op[1]
        p = root / table
        rows = _csv_rows(p)
        if rows is None:
            return None
        body = rows[1:]
        if kind == "csv_cell":
            _, _, r, c, text = op
            if not body:
                return None
            row = body[r % len(body)]
            text = str(sentinel) if text == OUT else text
            if row:
                row[c % len(row)] = text
            _write_rows(p, rows)
            return f"{table} line {r % len(body) + 2} column {c % max(len(row), 1)}: {text!r}"
        if kind == "csv_row":
            _, _, how, i, j = op
            n = len(body)
            i, j = (i % n, j % n) if n else (0, 0)
            if how == "delete" and n:
                del body[i]
            elif how == "duplicate" and n:
                body.insert(i, list(body[i]))
            elif how == "swap" and n:
                body[i], body[j] = body[j], body[i]
            elif how == "blank":
                body.insert(i, [""])
            elif how == "junk":
                body.insert(i, ["junk", "1;2", '"open'])
            elif how == "cut" and n:
                body[i] = body[i][: 1 + j % max(len(body[i]), 1)]
                body = body[: i + 1]
            elif how == "header_only":
                body = []
            elif how == "empty":
                _replace(p, b"")
                return f"{table}: empty"
            elif how == "no_header":
                rows = body
                _write_rows(p, rows)
                return f"{table}: no header"
            elif how in ("crlf", "bom", "latin1"):
                text = "\n".join(",".join(r) for r in rows) + "\n"
                data = {"crlf": text.replace("\n", "\r\n").encode(), "bom": b"\xef\xbb\xbf" + text.encode(),
                        "latin1": text.replace("pose", "pos\xe9").encode("latin-1", "replace")}[how]
                _replace(p, data)
                return f"{table}: {how}"
            _write_rows(p, [rows[0], *body])
            return f"{table}: row {how} {i} {j}"
        _, _, how, i, j = op
        header = rows[0]
        n = len(header)
        i, j = i % n, j % n
        if how == "drop":
            rows = [[c for k, c in enumerate(r) if k != i] for r in rows]
        elif how == "rename":
            header[i] = header[i] + "_"
        elif how == "extra":
            rows = [[*r[:i], "extra" if k == 0 else "1", *r[i:]] for k, r in enumerate(rows)]
        elif how == "reorder":
            rows = [[*r] for r in rows]
            for r in rows:
                if len(r) == n:
                    r[i], r[j] = r[j], r[i]
        elif how == "duplicate":
            rows = [[*r, r[i] if i < len(r) else ""] for r in rows]
        elif how == "upper":
            header[i] = header[i].upper()
        elif how == "spaces":
            header[i] = f"  {header[i]} "
        _write_rows(p, rows)
        return f"{table}: column {how} {i} {j}"
    if kind == "csv_valid":
        _, table, r, (col, what) = op
        p = root / table
        rows = _csv_rows(p)
        if rows is None or len(rows) < 3 or col not in rows[0]:
            return None
        c = rows[0].index(col)
        body = [row for row in rows[1:] if len(row) == len(rows[0])]
        if len(body) < 2:
            return None
        i = r % len(body)
        row, other = body[i], body[(i + 1) % len(body)]
        try:
            if what in ("A", "B", "AB", "off"):
                row[c] = what
            elif what == "swap":
                row[c], other[c] = other[c], row[c]
            elif what == "renumber":  # another integer frame number
                row[c] = str(int(row[c]) + 1000)
            elif what in ("same", "back"):
                row[c] = other[c] if what == "same" else repr(float(other[c]) + 1.0)
            elif what.startswith(("+", "-")):
                row[c] = repr(float(row[c]) + float(what))
            elif what == "negate":
                for q in ("qw", "qx", "qy", "qz"):
                    k = rows[0].index(q)
                    row[k] = repr(-float(row[k]))
            elif what == "identity":
                for q, v in zip(("qw", "qx", "qy", "qz"), ("1", "0", "0", "0"), strict=True):
                    row[rows[0].index(q)] = v
            elif what == "all same":
                for b in body:
                    b[:] = [b[0], *row[1:]] if col != "image" else b
        except (ValueError, IndexError):
            return None
        _write_rows(p, [rows[0], *body])
        return f"{table} line {i + 2}: {col} {what}"
    if kind == "img_bytes":
        _, rel, cut, fl, tail = op
        p = root / rel
        if not p.is_file() or p.is_symlink():
            return None
        data = bytearray(p.read_bytes())
        data = data[: cut % (len(data) + 1)]
        for at, v in fl:
            if data:
                data[at % len(data)] = v
        _replace(p, bytes(data) + tail)
        return f"{rel}: cut at {cut % (len(data) + 1)}, flips {fl}, tail {tail!r}"
    if kind == "img_kind":
        _, rel, how = op
        p = root / rel
        if not p.is_file() or p.is_symlink():
            return None
        if how == "empty":
            _replace(p, b"")
            return f"{rel}: empty file"
        try:
            img = read_image(p)
        except ImageError:  # broken by an earlier corruption
            return None
        new = {
            "short_row": lambda: img[:-1], "narrow": lambda: img[:, :-8], "transposed": lambda: img.T.copy(),
            "tiny": lambda: img[:1, :1].copy(), "deep": lambda: img.astype(np.uint16),
            "deep_scaled": lambda: img.astype(np.uint16) * 257,
            "colour": lambda: np.repeat(img[..., None], 3, axis=2),
            "blank": lambda: np.zeros_like(img), "saturated": lambda: np.full_like(img, 255),
            "dark": lambda: img // 16, "mirror": lambda: img[:, ::-1].copy(),
            "shift": lambda: np.roll(img, (img.shape[0] // 3, img.shape[1] // 3), axis=(0, 1)),
            "half": lambda: np.where(np.arange(img.shape[1]) < img.shape[1] // 2, img, 0).astype(img.dtype),
        }.get(how, lambda: img)()
        p.unlink()
        if how in ("jpeg_bytes", "tiff_renamed", "bmp_renamed"):
            ext = {"jpeg_bytes": ".jpg", "tiff_renamed": ".tif", "bmp_renamed": ".bmp"}[how]
            q = p.with_suffix(ext)
            write_image(q, new)
            if how == "jpeg_bytes":  # JPEG bytes under the PNG's name
                q.rename(p)
            return f"{rel}: {how}"
        write_image(p, new)
        return f"{rel}: {how} {new.dtype} {new.shape}"
    if kind == "missing":
        _, rel = op
        p = root / rel
        if p.is_symlink() or p.is_file():
            p.unlink()
        elif p.is_dir():
            shutil.rmtree(p)
        else:
            return None
        return f"{rel}: removed"
    if kind == "extra":
        _, rel, name, how, data = op
        d = root / rel
        if not d.is_dir() or d.is_symlink():
            return None
        p = d / name
        if p.exists() or p.is_symlink():
            return None
        if how == "bytes":
            p.write_bytes(data)
        elif how == "folder":
            p.mkdir()
        elif how == "image" and p.suffix in (".png", ".tif"):
            write_image(p, np.zeros((2048, 3072), np.uint8))
        else:
            p.symlink_to(root / "calibration/camera/view_00.png")
        return f"{rel}/{name}: extra {how}"
    if kind == "escape":
        return _escape(op, root, case)[0]
    if kind == "product_escape":
        return _product_escape(op, root, case)[0]
    if kind == "mesh":
        return _mesh(op, root, case)
    raise AssertionError(op)


def _escape(op: tuple, root: Path, case: Path) -> tuple[str | None, list[str]]:
    """A name, link or linked folder that leads out of the capture to the sentinel (or to a copy
    of a folder beside the capture): a description and the texts the refusal must hold."""
    _, how, row, image, folder = op
    sentinel = case / SENTINEL
    if how.startswith("row_"):
        rel = "calibration/handeye/poses.csv"
        rows = _csv_rows(root / rel)
        if rows is None or len(rows) < 2 or "image" not in rows[0]:
            return None, []
        k = 1 + row % (len(rows) - 1)
        name = {"row_rel": "../../../sentinel.png", "row_abs": str(sentinel),
                "row_deep": "../handeye/../../../sentinel.png"}[how]
        rows[k][rows[0].index("image")] = name
        _write_rows(root / rel, rows)
        return f"{rel} line {k + 1}: image {name!r}", [f"{rel}, line {k + 1}: image '{name}'"]
    if how in ("link_abs", "link_rel", "link_table"):
        rel = image if how != "link_table" else (*TABLES, "rig.yaml")[row % 4]
        p = root / rel
        if not p.parent.is_dir() or p.parent.is_symlink():
            return None, []
        if p.is_symlink() or p.exists():
            p.unlink()
        p.symlink_to(sentinel if how != "link_rel" else Path(os.path.relpath(sentinel, p.parent)))
        return f"{rel}: link to the sentinel", [f"{rel}: is a symbolic link to {sentinel}"]
    # a whole folder linked to a copy of it beside the capture
    p = root / folder
    if not p.is_dir() or p.is_symlink():
        return None, []
    outside = case / "outside" / folder.replace("/", "_")
    outside.parent.mkdir(exist_ok=True)
    p.rename(outside)
    p.symlink_to(outside)
    return f"{folder}: linked to {outside}", [f"{folder}: is a symbolic link to {outside}"]


# --------------------------------------------------------------------------- running a case

_WATCH: list[tuple[Path, Path, tuple[Path, ...]]] = []  # (capture, case, forbidden) while a command runs
_OUTSIDE: list[str] = []  # files opened outside the capture


def _audit(event: str, args: tuple) -> None:
    if not _WATCH or event != "open" or not isinstance(args[0], str | bytes | os.PathLike):
        return
    path = os.fsdecode(args[0])
    try:
        real = Path(path).resolve()
    except (OSError, RuntimeError):
        return
    root, case, forbidden = _WATCH[-1]
    if real.is_relative_to(case) and not real.is_relative_to(root) and not real.is_relative_to(case / "out"):
        _OUTSIDE.append(str(real))  # beside the capture: the sentinel, a folder linked to
    elif any(real.is_relative_to(f) for f in forbidden):
        _OUTSIDE.append(str(real))  # the base copy or the session's capture behind the links


sys.addaudithook(_audit)

# a path in the capture, relative to it: what a message that names a file of the capture holds
# (or a problem line naming one of its top folders: "  - scans: is a symbolic link ...")
_NAMED = re.compile(r"(?<![\w.-])(rig\.yaml|truth\.json|part\.stl"
                    r"|(?:calibration|scans|truth)/[^\s,:;'\"()]+)|^  - (calibration|scans|truth):", re.M)


def _names_a_file(message: str, root: Path) -> bool:
    return bool(_NAMED.search(message)) or f"{root}/" in message


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.text: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.text.append(logging.Formatter().format(record))


def run_case(env: Env, command: str, ops: list, refusal: list[str] | None = None) -> tuple[int, str]:
    """Break a copy of the capture by ``ops``, run ``command`` on it and check the outcome.
    With ``refusal``, a single escape op whose refusal must hold each of the texts."""
    case = Path(tempfile.mkdtemp(prefix="case-", dir=env.work)).resolve()
    try:
        root, out = case / "cap", case / "out"
        shutil.copytree(env.base, root, copy_function=os.link)
        out.mkdir()
        os.link(env.base / "calibration/handeye/pose_00.png", case / SENTINEL)  # a valid view
        os.link(env.base / "part.stl", case / MESH_SENTINEL)  # a valid mesh
        if refusal is None:
            done = [d for d in (_apply(op, root, case) for op in ops) if d is not None]
        else:
            d, expected = (_escape if ops[0][0] == "escape" else _product_escape)(ops[0], root, case)
            done = [d] if d is not None else []
            refusal[:] = expected
        note(f"corruptions: {done}")
        before = sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))
        argv, art = _argv(command, root, out, env.cal)
        code, err, _ = run_checked(command, argv, art, out, lambda m: _names_a_file(m, root),
                                   watch=(root, case, env.originals))
        after = sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))
        assert after == before, "the command wrote into the capture"
        if refusal is not None and done:
            assert code == 2, f"a path out of the capture was accepted: {done}"
            for text in refusal:
                assert text in err, (text, err)
    finally:
        shutil.rmtree(case, ignore_errors=True)
    assert _snapshot(env.base) == env.snapshot, "a case changed the base capture"
    return code, err


def run_checked(command: str, argv: list[str], art: Path, out: Path, named, watch: tuple | None = None
                ) -> tuple[int, str, str]:
    """Run ``crossline <argv>`` in this process and check the outcome: exit 0 with ``art``
    written and sane (:func:`_read_artefact`), or exit 2 with one ``crossline <command>: error:``
    message for which ``named(message)`` holds and nothing left in ``out``; never another exit
    status, a traceback (on stderr or in the log), or a temporary file left. With ``watch``
    (capture, case folder, forbidden paths), no file is opened outside the capture. Returns the
    exit status, stderr and the log's records."""
    from crossline.cli import main

    err, records = io.StringIO(), _Records()
    logging.getLogger().addHandler(records)
    _OUTSIDE.clear()
    if watch is not None:
        _WATCH.append(watch)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(argv)
    finally:
        if watch is not None:
            _WATCH.pop()
        logging.getLogger().removeHandler(records)
    err = err.getvalue()
    log = "\n".join(records.text)
    if currently_in_test_context():  # a hypothesis case (test_products_fuzz.py's are not)
        note(f"exit {code}: {err}")
    assert code in (0, 2), f"exit {code} (0 or 2 expected): {err}"
    assert "Traceback" not in err and "Traceback" not in log, err + log
    assert not _OUTSIDE, f"opened outside the capture: {sorted(set(_OUTSIDE))}"
    left = sorted(p.name for p in out.iterdir())
    if code == 0:
        assert art.is_file(), f"exit 0 without {art.name}"
        assert not [n for n in left if n.endswith(".tmp")], left
        _read_artefact(command, art)
    else:
        m = re.search(rf"^crossline {command}: error: (.*)", err, re.M | re.S)
        assert m, f"no error message: {err!r}"
        assert named(m.group(1)), f"the message names no file of the input: {err}"
        assert not left, f"a failed run left {left}"
    return code, err, log


# --------------------------------------------------------------------------- the properties

_SCALE = float(os.environ.get("CROSSLINE_FUZZ_SCALE", "1"))
FUZZ = settings(derandomize=True, database=None, deadline=None, print_blob=False,
                phases=[Phase.explicit, Phase.generate],
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much])
CASES = {"check": (12, 4), "calibrate-camera": (6, 3), "calibrate-lasers": (4, 3),
         "calibrate-handeye": (6, 3), "extract-stripes": (10, 4), "triangulate": (10, 4),
         "fuse": (16, 4), "report": (6, 6)}


# cases the fuzz once found wrong, tried first on every run
EXAMPLES = {
    # every arm pose the same: "degenerate hand-eye motion: only 0 of 10 motion pairs rotate by
    # more than 1 deg" named no file (now: calibration/handeye/poses.csv, by run_calibrate_handeye)
    "calibrate-handeye": [[("csv_valid", "calibration/handeye/poses.csv", 0, ("x", "all same"))]],
    # two rows' frame numbers swapped (their times no longer increase with the numbers): "internal
    # error: ValueError: `times` must give one increasing time per frame of `frames`" from the
    # pose refinement (now: _read_frames names frames.csv and the two frames)
    # a cell of frames.csv holding a comma (a row of 11 fields) in two scans: the report read the
    # tables with pandas, took another column for the laser states and drew a legend of no
    # entries: "internal error: ValueError: number sections must be larger than 0" (now: the
    # report checks each frames.csv as the capture's reader does, naming the row)
    "report": [[("csv_cell", "scans/part/frames.csv", 27, 0, "a,b"),
                ("csv_cell", "scans/plate/frames.csv", 0, 4, "a,b")],
               # a nominal mesh in one plane (every x = 0): "internal error: RuntimeError: QH6013
               # qhull input error ..." from Open3D's normal orientation in the coarse alignment
               # (now: nominal_align._fpfh says the surface is flat; no comparison, exit 0)
               [("mesh", "stl", "flat", 9, [], b"")]],
    "fuse": [[("csv_valid", "scans/plate/frames.csv", 0, ("frame", "swap"))],
             [("csv_valid", "scans/plate/frames.csv", 5, ("frame", "renumber"))]],
}


def _n(command: str, which: int) -> int:
    return max(1, int(CASES[command][which] * _SCALE))


def _fuzz(command: str):
    """A test running ``command`` on randomly broken captures."""

    def test(env: Env, request) -> None:
        if command in PRODUCTS:
            request.getfixturevalue("products")
        make = product_corruptions if command in PRODUCTS else corruptions

        @seed(zlib.crc32(command.encode()))
        @settings(FUZZ, max_examples=_n(command, 0))
        @given(make(env, command))
        def cases(ops: list) -> None:
            run_case(env, command, ops)

        for ops in EXAMPLES.get(command, []):
            cases = example(ops)(cases)
        cases()

    test.__name__ = f"test_{command.replace('-', '_')}_on_broken_captures"
    test.__doc__ = f"crossline {command} on {CASES[command][0]} randomly broken captures."
    return test


def _paths_out(command: str):
    """A test running ``command`` on captures with one path out of them: refused, naming the
    row or the link, and the sentinel never opened."""

    def test(env: Env, request) -> None:
        if command in PRODUCTS:
            request.getfixturevalue("products")

        @seed(zlib.crc32(f"{command} out".encode()))
        @settings(FUZZ, max_examples=_n(command, 1))
        @given(product_escapes(command) if command in PRODUCTS else escapes(env, command))
        def cases(op: tuple) -> None:
            run_case(env, command, [op], refusal=[])

        cases()

    test.__name__ = f"test_{command.replace('-', '_')}_refuses_paths_out"
    test.__doc__ = f"crossline {command}: {CASES[command][1]} paths out of the capture, each refused."
    return test


for _command in CASES:
    for _make in (_fuzz, _paths_out):
        _test = _make(_command)
        globals()[_test.__name__] = _test


def test_fuse_frames_table_without_a_frame_of_the_points(env: Env, products: Path) -> None:
    """The last row of frames.csv renumbered (frame 23 -> 1023): the points' frame 23 is not in
    the table, and fuse's refusal must name the table."""
    @settings(FUZZ, max_examples=1)
    @given(st.just([("csv_valid", "scans/plate/frames.csv", 23, ("frame", "renumber"))]))
    def case(ops: list) -> None:
        run_case(env, "fuse", ops)

    case()


def test_the_watch_sees_reads_beside_the_capture(env: Env) -> None:
    """The watcher itself: a read inside the capture passes; one through a link to the
    sentinel beside it, and one of the base copy behind the hard links, are caught."""
    case = Path(tempfile.mkdtemp(prefix="case-", dir=env.work)).resolve()
    (case / "cap").mkdir()
    (case / "cap" / "in.txt").write_text("x")
    (case / SENTINEL).write_text("x")
    (case / "cap" / "link").symlink_to(case / SENTINEL)
    _OUTSIDE.clear()
    _WATCH.append((case / "cap", case, env.originals))
    try:
        (case / "cap" / "in.txt").read_text()
        inside = list(_OUTSIDE)
        (case / "cap" / "link").read_text()
        (env.base / "rig.yaml").read_text()
    finally:
        _WATCH.pop()
        shutil.rmtree(case)
    assert inside == []
    assert _OUTSIDE == [str(case / SENTINEL), str((env.base / "rig.yaml").resolve())]

"""The command line: checked and 'auto'-or-value options parse and refuse bad values with a clear message."""

import pytest

from crossline.cli import build_parser


def _parse(*argv):
    return build_parser().parse_args(list(argv))


TRI = ["triangulate", "CAP", "s", "--stripes", "s.parquet", "--camera", "c.json",
       "--lasers", "l.json", "--handeye", "h.json", "--out", "p.parquet"]


def test_auto_or_value_options_parse():
    assert _parse(*TRI).max_frame_gap is None
    assert _parse(*TRI, "--max-frame-gap", "AUTO").max_frame_gap is None
    assert _parse(*TRI, "--max-frame-gap", "4").max_frame_gap == 4
    ex = ["extract-stripes", "CAP", "s", "--out", "s.parquet"]
    assert _parse(*ex).relative_noise is None
    assert _parse(*ex, "--relative-noise", "0.15").relative_noise == 0.15
    assert _parse(*ex).fit_across is True and _parse(*ex, "--fit-across", "false").fit_across is False


FUSE = ["fuse", "p.parquet", "--out", "c.ply"]
EXTRACT = ["extract-stripes", "CAP", "s", "--out", "x"]


def test_fuse_arm_options_parse():
    a = _parse(*FUSE, "--arm-precision-rad", "auto", "--arm-smooth-fraction", "0", "--arm-corr-time-s", "0.5")
    assert a.arm_precision_rad is None and a.arm_smooth_fraction == 0.0 and a.arm_corr_time_s == 0.5
    assert _parse(*FUSE, "--arm-precision-rad", "1e-4").arm_precision_rad == 1e-4
    a = _parse(*FUSE, "--arm-precision-mm", "auto", "--handeye", "h.json")
    assert a.arm_precision_mm is None and str(a.handeye) == "h.json"  # None: auto, as run() passes it


@pytest.mark.parametrize("argv, opt, value, expected", [
    (TRI, "--max-frame-gap", "0", "expected 'auto' or a positive integer, got '0'"),
    (TRI, "--max-frame-gap", "2.5", "expected 'auto' or a positive integer, got '2.5'"),
    (EXTRACT, "--relative-noise", "1.5", "expected 'auto' or a number in (0, 1), got '1.5'"),
    (EXTRACT, "--relative-noise", "lots", "expected 'auto' or a number in (0, 1), got 'lots'"),
    (FUSE, "--arm-precision-rad", "none", "expected 'auto' or a number > 0, got 'none'"),
    (FUSE, "--arm-smooth-fraction", "1.5", "expected a number in [0, 1], got '1.5'"),
    (FUSE, "--arm-corr-time-s", "0", "expected a number > 0, got '0'"),
    (FUSE, "--arm-corr-time-s", "auto", "expected a number > 0, got 'auto'"),
])
def test_checked_options_refuse_bad_values(capsys, argv, opt, value, expected):
    with pytest.raises(SystemExit) as e:
        _parse(*argv, opt, value)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert opt in err and expected in err


def test_board_option_parses_every_pattern():
    from crossline.board import Board

    sim = ["simulate", "OUT"]
    assert _parse(*sim).board is None
    assert _parse(*sim, "--board", "chessboard:12x9:4").board == Board("chessboard", 12, 9, 4.0)
    assert _parse(*sim, "--board", "asymmetric:7x13:2.5:1.5:light").board == Board(
        "asymmetric", 7, 13, 2.5, 1.5, "light")
    assert _parse(*sim, "--board", "symmetric:15X11:3.75:1.875").board.circles == "dark"


@pytest.mark.parametrize("spec, expected", [
    ("chessboard:12x9", "expected pattern:COLSxROWS:spacing"),
    ("chessboard:12by9:4", "expected pattern:COLSxROWS:spacing"),
    ("chessboard:12x9:4:2", "a chessboard has no circle diameter"),
    ("symmetric:5x4:3", "a circle grid needs its circle diameter"),
    ("hexagonal:5x4:3:1", "board pattern must be one of"),
    ("symmetric:5x4:3:4", "circle diameter must be > 0 and smaller than the spacing"),
    ("symmetric:5x4:3:1:grey", "board circles must be 'dark' or 'light'"),
])
def test_board_option_refuses_bad_specs(capsys, spec, expected):
    with pytest.raises(SystemExit) as e:
        _parse("simulate", "OUT", "--board", spec)
    assert e.value.code == 2
    assert expected in capsys.readouterr().err


# the one deliberate difference: the fuse command alone has no frames.csv to refine with
# unless it is given --frames, so it defaults to the paper (poses as reported); the workflow
# passes both
CLI_DEFAULT_DIFFERS = {("fuse", "refine_poses")}


@pytest.mark.parametrize("command, section", [
    ("calibrate-camera", "camera"), ("calibrate-lasers", "lasers"),
    ("calibrate-handeye", "handeye"), ("extract-stripes", "stripes"),
    ("triangulate", "points"), ("fuse", "fuse"),
])
def test_command_defaults_are_the_workflow_s(command, section):
    """Each stage run by hand behaves as in the workflow: its defaults are the schema's."""
    import argparse
    from pathlib import Path

    import yaml

    schema = yaml.safe_load((Path(__file__).resolve().parents[1] / "workflow" / "schemas"
                             / "config.schema.yaml").read_text())
    keys = schema["properties"][section]["properties"]
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    opts = {a.dest: a.default for a in sub.choices[command]._actions}
    compared = 0
    for key, spec in keys.items():
        if key not in opts or (command, key) in CLI_DEFAULT_DIFFERS:
            continue
        want = None if spec.get("default") == "auto" else spec.get("default")
        assert opts[key] == want, (command, key, opts[key], want)
        compared += 1
    assert compared >= 1


# ----------------------------------------------------------------------------- no traceback, ever


@pytest.fixture(scope="module")
def odd(tmp_path_factory, quick_capture):
    """Odd and broken inputs for every command, made once: folders, calibration files, tables."""
    import json
    import os

    import numpy as np
    import pandas as pd
    import yaml

    from crossline.camera import Camera
    from crossline.io.images import write_png
    from tests.broken import break_capture

    t = tmp_path_factory.mktemp("odd")
    f = {"good": quick_capture, "empty": t / "empty", "out": t / "out"}
    f["empty"].mkdir()
    f["out"].mkdir()
    K = np.array([[5000.0, 0, 1535.5], [0, 5000.0, 1023.5], [0, 0, 1]])
    Camera(K, np.zeros(5), (3072, 2048)).save(t / "camera.json")
    f["camera"] = t / "camera.json"
    cam = json.loads(f["camera"].read_text())
    cam["K"][0][0] = float("nan")
    (t / "nan_camera.json").write_text(json.dumps(cam))
    f["nan_camera"] = t / "nan_camera.json"
    f["parallel"] = t / "parallel.json"  # two planes that never cross
    f["parallel"].write_text(json.dumps({"A": {"normal": [0, 0, 1.0], "d": -150.0},
                                         "B": {"normal": [0, 0, 1.0], "d": -160.0}}))
    f["one_laser"] = t / "one_laser.json"
    f["one_laser"].write_text(json.dumps({"A": {"normal": [0, 0.6, 0.8], "d": -120.0}}))
    f["handeye"] = t / "handeye.json"
    f["handeye"].write_text(json.dumps({"T_tool_cam": np.eye(4).tolist()}))
    f["junk"] = t / "junk.parquet"
    f["junk"].write_bytes(b"not a parquet file")
    f["nan_points"] = t / "nan_points.parquet"
    pd.DataFrame({"frame": [0, 1], "laser": ["A", "A"], "x": [np.nan, np.nan], "y": [0.0, 0.0],
                  "z": [0.0, 0.0]}).to_parquet(f["nan_points"])
    for fault in ("nan_pose", "wrong_size", "nan_frame_pose", "wrong_size_view", "laser_views_blank",
                  "board_views_blank"):
        f[fault] = break_capture(quick_capture, t / fault, fault)
    # stripe chunks of two scans (2 frames each) and a points file of scan 'plate'
    from crossline.scan.stripes import run_extract_stripes

    f["chunk_plate"], f["chunk_gauge"] = t / "plate-0.parquet", t / "gauge-1.parquet"
    run_extract_stripes(quick_capture, "plate", f["chunk_plate"], chunk=(0, 12))
    run_extract_stripes(quick_capture, "gauge", f["chunk_gauge"], chunk=(1, 12))
    import pyarrow as pa
    import pyarrow.parquet as pq

    n = 24  # the quick capture's frames per scan
    z = np.zeros(n)
    pts = pa.table({"frame": np.arange(n), "laser": ["A"] * n, "x": z, "y": z, "z": z, "x_cam": z,
                    "y_cam": z, "z_cam": z + 150.0})
    f["plate_points"] = t / "plate_points.parquet"
    pq.write_table(pts.replace_schema_metadata({b"crossline": json.dumps({"scan": "plate", "frames": n})}),
                   f["plate_points"])
    f["gauge_frames"] = quick_capture / "scans/gauge/frames.csv"
    # fused clouds that are not: a vertex at nan, a body shorter than its header says
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty double x\n"
              "property double y\nproperty double z\nend_header\n")
    xyz = np.arange(9.0).reshape(3, 3)
    xyz[1, 0] = np.nan
    f["nan_ply"], f["short_ply"] = t / "nan.ply", t / "short.ply"
    f["nan_ply"].write_bytes(header.format(3).encode() + xyz.tobytes())
    f["short_ply"].write_bytes(header.format(100).encode() + xyz.tobytes())
    # every view unusable: eight grey frames of the sensor's size, no board in any
    blank = t / "blank"
    (blank / "calibration/camera").mkdir(parents=True)
    rig = yaml.safe_load((quick_capture / "rig.yaml").read_text())
    rig.pop("scans")
    (blank / "rig.yaml").write_text(yaml.safe_dump(rig))
    write_png(t / "grey.png", np.full((2048, 3072), 128, np.uint8))
    for i in range(8):
        os.link(t / "grey.png", blank / f"calibration/camera/view_{i:02d}.png")
    f["blank"] = blank
    return f


def _cli(capsys, argv):
    """Run ``crossline argv`` in this process: (exit code, stderr). An escaping exception fails."""
    from crossline.cli import main

    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def _out(f, name):
    return str(f["out"] / name)


# (command line, the text the error must hold, the file it must name); exit code 2 for each
BROKEN = {
    "check empty folder": (["check", "{empty}"], "is empty", "{empty}"),
    "camera empty folder": (["calibrate-camera", "{empty}", "--out", "@c.json"], "is empty", "{empty}"),
    "lasers empty folder": (["calibrate-lasers", "{empty}", "--camera", "{camera}", "--out", "@l.json"],
                            "is empty", "{empty}"),
    "handeye empty folder": (["calibrate-handeye", "{empty}", "--camera", "{camera}", "--out",
                              "@h.json"], "is empty", "{empty}"),
    "stripes empty folder": (["extract-stripes", "{empty}", "plate", "--out", "@s.parquet"],
                             "is empty", "{empty}"),
    "triangulate empty folder": (["triangulate", "{empty}", "plate", "--stripes", "{junk}", "--camera",
                                  "{camera}", "--lasers", "{parallel}", "--handeye", "{handeye}",
                                  "--out", "@p.parquet"], "is empty", "{empty}"),
    "report empty folder": (["report", "{empty}", "--interim", "{empty}", "--processed", "{empty}",
                             "--pdf", "@r.pdf", "--metrics", "@m.json"], "no rig.yaml", "{empty}"),
    "certificate empty folder": (["certificate", "{empty}", "--camera", "{camera}", "--pdf", "@c.pdf",
                                  "--json", "@c.json"], "no rig.yaml", "{empty}"),
    "check NaN pose": (["check", "{nan_pose}"], "'y' = nan is not a finite pose value",
                       "calibration/handeye/poses.csv, line 4"),
    "handeye NaN pose": (["calibrate-handeye", "{nan_pose}", "--camera", "{camera}", "--out", "@h.json"],
                         "'y' = nan is not a finite pose value", "calibration/handeye/poses.csv"),
    "check frame of another size": (["check", "{wrong_size}"], "image is 2658x792 px",
                                    "scans/part/frames/000002.png"),
    "stripes frame of another size": (["extract-stripes", "{wrong_size}", "part", "--chunk", "0/8",
                                       "--out", "@s.parquet"], "image is 2658x792 px",
                                      "scans/part/frames/000002.png"),
    "camera all views unusable": (["calibrate-camera", "{blank}", "--out", "@c.json"],
                                  "usable views", "calibration/camera/view_07.png"),
    "handeye no views": (["calibrate-handeye", "{blank}", "--camera", "{camera}", "--out", "@h.json"],
                         "hand-eye calibration needs at least", "hand-eye"),
    "triangulate one laser on a two-laser scan": (
        ["triangulate", "{good}", "plate", "--stripes", "{junk}", "--camera", "{camera}", "--lasers",
         "{one_laser}", "--handeye", "{handeye}", "--out", "@p.parquet"], "laser", "{one_laser}"),
    "triangulate NaN camera": (["triangulate", "{good}", "plate", "--stripes", "{junk}", "--camera",
                                "{nan_camera}", "--lasers", "{parallel}", "--handeye", "{handeye}",
                                "--out", "@p.parquet"], "non-finite", "{nan_camera}"),
    "triangulate stripes not parquet": (["triangulate", "{good}", "plate", "--stripes", "{junk}",
                                         "--camera", "{camera}", "--lasers", "{parallel}",
                                         "--handeye", "{handeye}", "--out", "@p.parquet"],
                                        "cannot be read as parquet", "{junk}"),
    "lasers NaN camera": (["calibrate-lasers", "{good}", "--camera", "{nan_camera}", "--out", "@l.json"],
                          "non-finite", "{nan_camera}"),
    "lasers camera not JSON": (["calibrate-lasers", "{good}", "--camera", "{junk}", "--out", "@l.json"],
                               "not a camera model", "{junk}"),
    "certificate NaN camera": (["certificate", "{good}", "--camera", "{nan_camera}", "--pdf", "@c.pdf",
                                "--json", "@c.json"], "non-finite", "{nan_camera}"),
    "gather not parquet": (["gather-stripes", "{junk}", "--out", "@g.parquet"], "not a stripe chunk",
                           "{junk}"),
    "fuse not parquet": (["fuse", "{junk}", "--out", "@f.ply"], "cannot be read as parquet", "{junk}"),
    "fuse NaN points": (["fuse", "{nan_points}", "--out", "@f.ply"], "finite", "{nan_points}"),
    "fuse missing file": (["fuse", "@none.parquet", "--out", "@f.ply"], "not found", "@none.parquet"),
    # NaN frame poses: every stage that reads the scan's frames.csv names the row
    "check NaN frame pose": (["check", "{nan_frame_pose}"], "'x' = nan is not a finite pose value",
                             "scans/plate/frames.csv, line 4"),
    "stripes NaN frame pose": (["extract-stripes", "{nan_frame_pose}", "plate", "--chunk", "0/12", "--out",
                                "@s.parquet"], "'x' = nan is not a finite pose value",
                               "scans/plate/frames.csv, line 4"),
    "triangulate NaN frame pose": (["triangulate", "{nan_frame_pose}", "plate", "--stripes", "{chunk_plate}",
                                    "--camera", "{camera}", "--lasers", "{parallel}", "--handeye",
                                    "{handeye}", "--out", "@p.parquet"],
                                   "'x' = nan is not a finite pose value", "scans/plate/frames.csv, line 4"),
    "fuse NaN frame pose": (["fuse", "{plate_points}", "--refine-poses", "true", "--frames",
                             "{nan_frame_pose}/scans/plate/frames.csv", "--out", "@f.ply"],
                            "'x' = nan is not a finite pose value",
                            ("{nan_frame_pose}", "scans/plate/frames.csv, line 4")),
    # a calibration view of another size: camera and hand-eye stop, a laser pose is skipped
    "camera view of another size": (["calibrate-camera", "{wrong_size_view}", "--out", "@c.json"],
                                    "image is 3072x2040 px, expected 3072x2048 px",
                                    "calibration/camera/view_03.png"),
    "lasers views of another size": (["calibrate-lasers", "{wrong_size_view}", "--camera", "{camera}",
                                      "--out", "@l.json"], "image is 3072x2040 px, expected 3072x2048 px",
                                     ("calibration/laser_A/pose_00_laser.png",
                                      "calibration/laser_B/pose_02_laser.png")),
    "handeye view of another size": (["calibrate-handeye", "{wrong_size_view}", "--camera", "{camera}",
                                      "--out", "@h.json"], "image is 3072x2040 px, expected 3072x2048 px",
                                     "calibration/handeye/pose_02.png"),
    # laser views: none usable (no stripe on A's, no board in B's), no board in any lasers-off view
    "lasers no laser view usable": (["calibrate-lasers", "{laser_views_blank}", "--camera", "{camera}",
                                     "--out", "@l.json"], "no laser stripe on the board",
                                    ("laser A: 0 usable poses of 3", "calibration/laser_A/pose_00_laser.png",
                                     "laser B: 0 usable poses of 3")),
    "lasers board in no lasers-off view": (
        ["calibrate-lasers", "{board_views_blank}", "--camera", "{camera}", "--out", "@l.json"],
        "board not found", "calibration/laser_A/pose_00_board.png"),
    # files of another scan, or of another kind
    "gather chunks of two scans": (["gather-stripes", "{chunk_plate}", "{chunk_gauge}", "--out",
                                    "@g.parquet"], "scan 'gauge' differs from",
                                   ("{chunk_gauge}", "{chunk_plate}")),
    "triangulate stripes of another scan": (["triangulate", "{good}", "plate", "--stripes", "{chunk_gauge}",
                                             "--camera", "{camera}", "--lasers", "{parallel}", "--handeye",
                                             "{handeye}", "--out", "@p.parquet"],
                                            "holds scan 'gauge'", "{chunk_gauge}"),
    "fuse a stripes file": (["fuse", "{chunk_plate}", "--out", "@f.ply"], "a stripes file", "{chunk_plate}"),
    "fuse frames of another scan": (["fuse", "{plate_points}", "--refine-poses", "true", "--frames",
                                     "{gauge_frames}", "--out", "@f.ply"], "the frames table of scan 'gauge'",
                                    ("{gauge_frames}", "{plate_points}")),
    "export-cloud not a PLY": (["export-cloud", "{junk}", "--out", "@x.e57"], "not a PLY file", "{junk}"),
    "export-cloud missing file": (["export-cloud", "@none.ply", "--out", "@x.e57"], "not found",
                                  "@none.ply"),
    "export-cloud NaN vertex": (["export-cloud", "{nan_ply}", "--out", "@x.e57"],
                                "vertex 1 (of 3) has non-finite coordinates", "{nan_ply}"),
    "export-cloud truncated": (["export-cloud", "{short_ply}", "--out", "@x.e57"],
                               "truncated: the header declares 100 vertices", "{short_ply}"),
    "certificate handeye not JSON": (["certificate", "{good}", "--camera", "{camera}", "--handeye", "{junk}",
                                      "--pdf", "@c.pdf", "--json", "@c.json"],
                                     "not a handeye calibration file", "{junk}"),
    "certificate handeye without X": (["certificate", "{good}", "--camera", "{camera}", "--handeye",
                                       "{parallel}", "--pdf", "@c.pdf", "--json", "@c.json"],
                                      "expected 'T_tool_cam', a finite 4x4 matrix", "{parallel}"),
    "certificate lasers without planes": (["certificate", "{good}", "--camera", "{camera}", "--lasers",
                                           "{handeye}", "--pdf", "@c.pdf", "--json", "@c.json"],
                                          "expected the plane of laser A", "{handeye}"),
    "simulate unknown preset": (["simulate", "@sim", "--preset", "nonsense"], "unknown preset",
                                "nonsense"),
    "simulate into a full folder": (["simulate", "{out}", "--quick"], "not empty", "{out}"),
}


def _fill(f, text: str) -> str:
    if text.startswith("@"):
        return _out(f, text[1:])
    return text.format(**{k: str(v) for k, v in f.items()})


def _case(entry):
    return entry.values[0] if hasattr(entry, "values") else entry


def test_every_command_has_a_broken_case():
    """The matrix covers every command of the CLI."""
    from crossline.cli import COMMANDS

    assert {_case(e)[0][0] for e in BROKEN.values()} == set(COMMANDS)


@pytest.mark.parametrize("case", [pytest.param(k, marks=e.marks) if hasattr(e, "marks") else k
                                  for k, e in BROKEN.items()])
def test_every_command_names_the_fault_without_traceback(odd, capsys, case):
    """Exit 2, the fault said and every file it concerns named; nothing written."""
    argv, message, names = _case(BROKEN[case])
    (odd["out"] / "keep").touch()  # the simulate case needs a folder that is not empty
    code, err = _cli(capsys, [_fill(odd, a) for a in argv])
    assert code == 2, err
    assert message in err, err
    for name in (names,) if isinstance(names, str) else names:
        assert _fill(odd, name) in err, (name, err)
    assert not any(p.name != "keep" for p in odd["out"].iterdir()), "a failed stage left a file"


@pytest.mark.parametrize("lasers", ["parallel", "one_laser"])
def test_certificate_of_odd_planes_is_written(odd, capsys, lasers):
    """Parallel planes, or one laser alone: the certificate says what it found, no failure."""
    import json

    out = odd["out"].parent / f"cert-{lasers}"
    out.mkdir(exist_ok=True)
    code, err = _cli(capsys, ["certificate", odd["good"], "--camera", odd["camera"], "--lasers",
                              odd[lasers], "--pdf", out / "c.pdf", "--json", out / "c.json"])
    assert code == 0, err
    cert = json.loads((out / "c.json").read_text())
    ids = {r["id"]: r for r in cert["checks"]}
    if lasers == "parallel":
        assert ids["angle_AB_deg"]["value"] == pytest.approx(0.0, abs=1e-9)
    else:
        assert "laser_A_rms_mm" in ids and not any(k.startswith("laser_B") for k in ids)
        assert "angle_AB_deg" not in ids


@pytest.mark.parametrize("lasers, handeye", [("parallel", "handeye"), ("one_laser", "parallel")])
def test_report_of_odd_calibrations_is_written(odd, capsys, caplog, lasers, handeye):
    """The report on a two-laser capture with parallel planes, or with laser A's plane alone and
    a handeye.json that holds no hand-eye (exit 3 before: KeyError 'T_tool_cam'): written, each
    section as found; a file that is not its calibration is named and left out."""
    import json
    import shutil

    root = odd["out"].parent / f"report-{lasers}"
    cal = root / "interim/calibration"
    cal.mkdir(parents=True, exist_ok=True)
    for name, key in (("camera", "camera"), ("lasers", lasers), ("handeye", handeye)):
        shutil.copy(odd[key], cal / f"{name}.json")
    code, err = _cli(capsys, ["report", odd["good"], "--interim", root / "interim", "--processed",
                              root / "interim", "--pdf", root / "r.pdf", "--metrics", root / "m.json"])
    assert code == 0, err
    calib = json.loads((root / "m.json").read_text())["calibration"]
    if lasers == "parallel":
        assert calib["lasers"]["angle_AB_deg"] == pytest.approx(0.0, abs=1e-9)
        assert "handeye" in calib
    else:
        assert set(calib["lasers"]) == {"A"} and "handeye" not in calib
        assert f"{cal / 'handeye.json'}: not a handeye calibration" in caplog.text


def test_a_bug_is_one_line_not_a_traceback(capsys, monkeypatch, tmp_path):
    """An exception no stage expected: exit 3, one line naming its type, no traceback."""
    import crossline.report.certificate as cert

    def broken(*args, **kwargs):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(cert, "run_certificate", broken)
    code, err = _cli(capsys, ["certificate", tmp_path, "--camera", tmp_path / "c.json", "--pdf",
                              tmp_path / "c.pdf", "--json", tmp_path / "c.json"])
    assert code == 3
    assert "internal error: ZeroDivisionError: division by zero" in err

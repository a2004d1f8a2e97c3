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
    f["nan_pose"] = break_capture(quick_capture, t / "nan_pose", "nan_pose")
    f["wrong_size"] = break_capture(quick_capture, t / "wrong_size", "wrong_size")
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
                                        "not a stripes file", "{junk}"),
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
    "simulate unknown preset": (["simulate", "@sim", "--preset", "nonsense"], "unknown preset",
                                "nonsense"),
    "simulate into a full folder": (["simulate", "{out}", "--quick"], "not empty", "{out}"),
}


def _fill(f, text: str) -> str:
    if text.startswith("@"):
        return _out(f, text[1:])
    return text.format(**{k: str(v) for k, v in f.items()})


@pytest.mark.parametrize("case", list(BROKEN))
def test_every_command_names_the_fault_without_traceback(odd, capsys, case):
    argv, message, names = BROKEN[case]
    (odd["out"] / "keep").touch()  # the simulate case needs a folder that is not empty
    code, err = _cli(capsys, [_fill(odd, a) for a in argv])
    assert code == 2, err
    assert message in err and _fill(odd, names) in err, err
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

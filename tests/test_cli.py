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

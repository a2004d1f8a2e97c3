"""The command line: 'auto'-or-value options parse and refuse bad values with a clear message."""

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


@pytest.mark.parametrize("opt, value, expected", [
    ("--max-frame-gap", "0", "expected 'auto' or a positive integer, got '0'"),
    ("--max-frame-gap", "2.5", "expected 'auto' or a positive integer, got '2.5'"),
    ("--relative-noise", "1.5", "expected 'auto' or a number in (0, 1), got '1.5'"),
    ("--relative-noise", "lots", "expected 'auto' or a number in (0, 1), got 'lots'"),
])
def test_auto_or_value_options_refuse_bad_values(capsys, opt, value, expected):
    argv = TRI if opt == "--max-frame-gap" else ["extract-stripes", "CAP", "s", "--out", "x"]
    with pytest.raises(SystemExit) as e:
        _parse(*argv, opt, value)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert opt in err and expected in err

"""Capture reading and validation: every bad input gets an error naming file, line and expectation."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from crossline.cli import main
from crossline.io.capture import (
    CaptureError,
    check_capture,
    format_summary,
    laser_pattern,
    open_capture,
    read_rig,
    truth_file,
)
from crossline.io.images import ImageError, png_info, read_image, write_png

SENSOR = (64, 48)
WINDOW = {"x": 8, "y": 10, "width": 40, "height": 16}
RIG = {
    "format": "crossline-capture/1",
    "sensor": {"width": SENSOR[0], "height": SENSOR[1], "bit_depth": 8},
    "scan_window": dict(WINDOW),
    "frame_rate": 80,
    "board": {"pattern": "symmetric", "cols": 5, "rows": 4, "spacing": 3.75, "diameter": 1.875,
              "circles": "dark"},
    "scans": {"plate": {"artefact": "plane"}, "gauge": {"artefact": "gauge_block", "height": 20.0}},
}
FRAMES_HEADER = "frame,time_s,lasers,x,y,z,qw,qx,qy,qz\n"


def _img(h: int, w: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (h, w), dtype=np.uint8)


def make_capture(root: Path, n_frames: int = 6) -> Path:
    """A tiny but complete capture folder (not physically meaningful: for validation only)."""
    (root / "calibration" / "camera").mkdir(parents=True)
    (root / "rig.yaml").write_text(yaml.safe_dump(RIG, sort_keys=False))
    w, h = SENSOR
    for i in range(3):
        write_png(root / "calibration" / "camera" / f"view_{i:02d}.png", _img(h, w, i))
    for laser in "AB":
        for i in range(2):
            d = root / "calibration" / f"laser_{laser}"
            write_png(d / f"pose{i}_board.png", _img(h, w, 10 + i))
            write_png(d / f"pose{i}_laser.png", _img(h, w, 20 + i))
    he = root / "calibration" / "handeye"
    rows = ["image,x,y,z,qw,qx,qy,qz"]
    for i in range(3):
        write_png(he / f"pose_{i:02d}.png", _img(h, w, 30 + i))
        rows.append(f"pose_{i:02d}.png,{100 + i},{20.5},{300},1,0,0,0")
    (he / "poses.csv").write_text("\n".join(rows) + "\n")
    for scan in ("plate", "gauge"):
        d = root / "scans" / scan
        lines = [FRAMES_HEADER.strip()]
        states = ["A", "B", "AB"]
        for f in range(n_frames):
            write_png(d / "frames" / f"{f:06d}.png", _img(WINDOW["height"], WINDOW["width"], f))
            q = np.array([0.9, 0.1, 0.3, 0.2])
            q /= np.linalg.norm(q)
            lines.append(f"{f},{f / 80:.6f},{states[f % 3]},{f * 0.4},{1.5},{150},"
                         + ",".join(f"{v:.12f}" for v in q))
        (d / "frames.csv").write_text("\n".join(lines) + "\n")
    return root


@pytest.fixture
def capture(tmp_path: Path) -> Path:
    return make_capture(tmp_path / "cap")


def problems_of(root: Path, images: bool = True) -> str:
    with pytest.raises(CaptureError) as info:
        check_capture(root, images=images)
    return str(info.value)


def edit_csv_line(path: Path, line: int, new: str | None) -> None:
    lines = path.read_text().splitlines()
    if new is None:
        del lines[line - 1]
    else:
        lines[line - 1] = new
    path.write_text("\n".join(lines) + "\n")


def edit_rig(root: Path, fn) -> None:
    data = yaml.safe_load((root / "rig.yaml").read_text())
    fn(data)
    (root / "rig.yaml").write_text(yaml.safe_dump(data, sort_keys=False))


# --------------------------------------------------------------------------- good capture


def test_good_capture_summary(capture: Path) -> None:
    s = check_capture(capture)
    assert s["views"] == {"camera": 3, "laser_A": 2, "laser_B": 2, "handeye": 3}
    assert s["scans"]["plate"]["frames"] == 6
    assert s["scans"]["plate"]["pattern"] == ["A", "B", "AB"]
    assert s["scans"]["plate"]["pattern_breaks"] == 0
    assert s["scans"]["gauge"]["nominal"] == {"height": 20.0}
    assert s["scans"]["plate"]["duration_s"] == pytest.approx(5 / 80, abs=1e-6)
    text = format_summary(s)
    assert "scan window  40x16 px at (8, 10)" in text
    assert "pattern A/B/AB" in text


def test_open_capture_types(capture: Path) -> None:
    cap = open_capture(capture)
    scan = cap.scans["plate"]
    assert scan.T_base_tool.shape == (6, 4, 4)
    np.testing.assert_allclose(scan.T_base_tool[2, :3, 3], [0.8, 1.5, 150])
    R = scan.T_base_tool[0, :3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert list(scan.lasers) == ["A", "B", "AB", "A", "B", "AB"]
    assert cap.handeye_T_base_tool.shape == (3, 4, 4)
    assert [v.pose for v in cap.laser_views["A"]] == ["pose0", "pose1"]
    assert cap.rig.board.object_points().shape == (20, 3)
    assert cap.rig.scan_window.offset == (8, 10)
    assert cap.truth_path is None


def test_check_cli(capture: Path, tmp_path: Path, capsys) -> None:
    assert main(["check", str(capture), "--json", str(tmp_path / "s.json")]) == 0
    assert "capture cap: OK" in capsys.readouterr().out
    assert (tmp_path / "s.json").is_file()
    shutil.rmtree(capture / "scans" / "plate" / "frames")
    assert main(["check", str(capture)]) == 2
    err = capsys.readouterr().err
    assert "scans/plate/frames.csv, line 2: frame 0 has no image frames/000000.png" in err


# --------------------------------------------------------------------------- rig.yaml


def test_missing_rig_key(capture: Path) -> None:
    edit_rig(capture, lambda d: d.pop("scan_window"))
    assert "rig.yaml: missing key 'scan_window'" in problems_of(capture)


def test_misspelt_rig_key(capture: Path) -> None:
    edit_rig(capture, lambda d: d.__setitem__("frame_rat", d.pop("frame_rate")))
    msg = problems_of(capture)
    assert "unknown key 'frame_rat' (misspelt 'frame_rate'?)" in msg
    assert "missing key 'frame_rate'" in msg


def test_misspelt_nested_key(capture: Path) -> None:
    edit_rig(capture, lambda d: d["board"].__setitem__("spacng", d["board"].pop("spacing")))
    msg = problems_of(capture)
    assert "unknown key 'board.spacng' (misspelt 'board.spacing'?)" in msg


def test_rig_wrong_type(capture: Path) -> None:
    edit_rig(capture, lambda d: d["sensor"].__setitem__("width", "wide"))
    assert "'sensor.width' must be an integer, got 'wide'" in problems_of(capture)


def test_rig_bad_pattern_and_artefact(capture: Path) -> None:
    def f(d):
        d["board"]["pattern"] = "hexagonal"
        d["scans"]["gauge"]["artefact"] = "cube"

    edit_rig(capture, f)
    msg = problems_of(capture)
    assert "'board.pattern' must be one of ['symmetric', 'asymmetric', 'chessboard']" in msg
    assert "'scans.gauge.artefact' must be one of" in msg


def test_rig_missing_nominal(capture: Path) -> None:
    edit_rig(capture, lambda d: d["scans"]["gauge"].pop("height"))
    assert "missing key 'scans.gauge.height' (a gauge_block needs its nominal height)" in problems_of(
        capture
    )


def test_rig_window_outside_sensor(capture: Path) -> None:
    edit_rig(capture, lambda d: d["scan_window"].__setitem__("x", 40))
    assert "does not fit the 64x48 sensor" in problems_of(capture)


def test_rig_not_yaml(capture: Path) -> None:
    (capture / "rig.yaml").write_text("sensor: [unclosed\n")
    assert "rig.yaml: not valid YAML" in problems_of(capture)


def test_rig_yaml_alias_bomb(capture: Path) -> None:
    """Aliases that make a small rig.yaml a huge tree: refused quickly, the message bounded."""
    import time

    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 9)]
    text = (capture / "rig.yaml").read_text()
    text = text.replace("sensor:", "sensor: *a8\nsensr:")
    (capture / "rig.yaml").write_text("\n".join(lines) + "\n" + text)
    t = time.perf_counter()
    msg = problems_of(capture)
    assert time.perf_counter() - t < 5 and len(msg) < 5000
    assert "'sensor' must be a mapping" in msg


def test_read_rig_collects_all_problems(capture: Path) -> None:
    def f(d):
        d.pop("frame_rate")
        d["sensor"]["bit_depth"] = 12
        d["board"]["cols"] = 1.5

    edit_rig(capture, f)
    with pytest.raises(CaptureError) as info:
        read_rig(capture / "rig.yaml")
    assert len(info.value.problems) == 3


def test_empty_capture(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    assert "is empty; expected rig.yaml, calibration/ and scans/" in problems_of(tmp_path / "empty")


# --------------------------------------------------------------------------- frames.csv


FRAMES = "scans/plate/frames.csv"


def test_row_without_image(capture: Path) -> None:
    (capture / "scans/plate/frames/000003.png").unlink()
    assert f"{FRAMES}, line 5: frame 3 has no image frames/000003.png" in problems_of(capture)


def test_row_fault_and_missing_image_both_listed(capture: Path) -> None:
    """A faulty row does not hide another row's missing image (every problem is listed)."""
    lines = (capture / FRAMES).read_text().splitlines()
    lines[3] = "two" + lines[3][1:]
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    (capture / "scans/plate/frames/000003.png").unlink()
    problems = problems_of(capture)
    assert f"{FRAMES}, line 4: 'frame' = 'two' is not an integer" in problems
    assert f"{FRAMES}, line 5: frame 3 has no image frames/000003.png" in problems


def test_read_frames_table_alone(capture: Path) -> None:
    """The frames table on its own (the fuse stage's reader): the rows, or each fault named."""
    from crossline.io.capture import CaptureError, read_frames_table

    t = read_frames_table(capture / FRAMES)
    sc = open_capture(capture).scans["plate"]
    assert np.array_equal(t.frames, sc.frames) and np.allclose(t.T_base_tool, sc.T_base_tool)
    lines = (capture / FRAMES).read_text().splitlines()
    lines[3] = "two" + lines[3][1:]
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    with pytest.raises(CaptureError, match=f"{FRAMES}, line 4: 'frame' = 'two'") as e:
        read_frames_table(capture / FRAMES)
    assert str(e.value).startswith(f"capture {capture}:")


def test_image_without_row(capture: Path) -> None:
    edit_csv_line(capture / FRAMES, 7, None)
    assert f"scans/plate/frames/000005.png: has no row in {FRAMES}" in problems_of(capture)


def test_duplicate_frame(capture: Path) -> None:
    lines = (capture / FRAMES).read_text().splitlines()
    lines[3] = lines[3].replace("2,", "1,", 1)
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    assert f"{FRAMES}, line 4: frame 1 is duplicated (first on line 3)" in problems_of(capture)


def test_time_backwards(capture: Path) -> None:
    lines = (capture / FRAMES).read_text().splitlines()
    f = lines[4].split(",")
    f[1] = "0.001"
    lines[4] = ",".join(f)
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    assert f"{FRAMES}, line 5: time goes backwards or stands still" in problems_of(capture)


def test_unknown_laser_state(capture: Path) -> None:
    lines = (capture / FRAMES).read_text().splitlines()
    lines[2] = lines[2].replace(",B,", ",C,")
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    msg = problems_of(capture)
    assert f"{FRAMES}, line 3: unknown laser state 'C'; expected one of A, B, AB, off" in msg


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_non_finite_pose(capture: Path, value: str) -> None:
    lines = (capture / FRAMES).read_text().splitlines()
    f = lines[2].split(",")
    f[5] = value
    lines[2] = ",".join(f)
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    assert f"{FRAMES}, line 3: 'z' = {value} is not a finite pose value" in problems_of(capture)


def test_non_unit_quaternion(capture: Path) -> None:
    lines = (capture / FRAMES).read_text().splitlines()
    f = lines[1].split(",")
    f[6:10] = ["1", "0.1", "0", "0"]
    lines[1] = ",".join(f)
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    msg = problems_of(capture)
    assert f"{FRAMES}, line 2: quaternion (qw, qx, qy, qz) has length 1.004988, expected 1" in msg


def test_truncated_frames_csv(capture: Path) -> None:
    text = (capture / FRAMES).read_text()
    (capture / FRAMES).write_text(text[: len(text) - 40])
    msg = problems_of(capture)
    assert f"{FRAMES}, line 7: has" in msg and "truncated or malformed row" in msg


def test_missing_column(capture: Path) -> None:
    lines = (capture / FRAMES).read_text().splitlines()
    lines = [",".join(x.split(",")[:2] + x.split(",")[3:]) for x in lines]
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    assert f"{FRAMES}, line 1: missing column(s) ['lasers']" in problems_of(capture)


def test_not_a_number(capture: Path) -> None:
    lines = (capture / FRAMES).read_text().splitlines()
    lines[3] = "two" + lines[3][1:]
    (capture / FRAMES).write_text("\n".join(lines) + "\n")
    assert f"{FRAMES}, line 4: 'frame' = 'two' is not an integer" in problems_of(capture)


def test_scan_not_in_rig(capture: Path) -> None:
    shutil.copytree(capture / "scans/plate", capture / "scans/extra")
    assert "scans/extra: is not described under 'scans:' in rig.yaml" in problems_of(capture)


def test_rig_scan_without_folder(capture: Path) -> None:
    shutil.rmtree(capture / "scans/gauge")
    assert "rig.yaml: scan 'gauge' has no folder scans/gauge" in problems_of(capture)


# --------------------------------------------------------------------------- hand-eye poses


POSES = "calibration/handeye/poses.csv"


def test_poses_fewer_rows_than_images(capture: Path) -> None:
    edit_csv_line(capture / POSES, 4, None)
    msg = problems_of(capture)
    assert "calibration/handeye/pose_02.png: has no row in calibration/handeye/poses.csv" in msg
    assert f"{POSES}: has 2 pose rows for 3 hand-eye images" in msg


def test_poses_row_without_image(capture: Path) -> None:
    (capture / "calibration/handeye/pose_01.png").unlink()
    msg = problems_of(capture)
    assert f"{POSES}, line 3: image 'pose_01.png' has no file calibration/handeye/pose_01.png" in msg


def test_poses_nan(capture: Path) -> None:
    edit_csv_line(capture / POSES, 2, "pose_00.png,nan,0,0,1,0,0,0")
    assert f"{POSES}, line 2: 'x' = nan is not a finite pose value" in problems_of(capture)


def test_laser_pose_without_partner(capture: Path) -> None:
    (capture / "calibration/laser_B/pose1_laser.png").unlink()
    msg = problems_of(capture)
    assert "calibration/laser_B: pose 'pose1' has pose1_board.png but no pose1_laser.png" in msg
    assert "calibration/laser_B: has 1 pose(s) with a laser image; the laser plane needs at least 2" in msg


# --------------------------------------------------------------------------- images


def test_image_wrong_size_calibration(capture: Path) -> None:
    write_png(capture / "calibration/camera/view_01.png", _img(40, 64, 0))
    msg = problems_of(capture)
    assert "calibration/camera/view_01.png: image is 64x40 px, expected the sensor 64x48 px" in msg


def test_image_wrong_size_frame(capture: Path) -> None:
    write_png(capture / "scans/gauge/frames/000002.png", _img(48, 64, 0))
    msg = problems_of(capture)
    assert "scans/gauge/frames/000002.png: image is 64x48 px, expected the scan window 40x16 px" in msg


def test_truncated_png(capture: Path) -> None:
    p = capture / "scans/plate/frames/000004.png"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    msg = problems_of(capture)
    assert "scans/plate/frames/000004.png: truncated PNG" in msg
    with pytest.raises(ImageError, match=r"000004\.png: unreadable or truncated image"):
        read_image(p)


def test_corrupt_png(capture: Path) -> None:
    p = capture / "calibration/camera/view_02.png"
    data = bytearray(p.read_bytes())
    data[60] ^= 0xFF
    p.write_bytes(bytes(data))
    assert "calibration/camera/view_02.png: corrupt PNG (CRC mismatch" in problems_of(capture)


def test_not_png(capture: Path) -> None:
    (capture / "calibration/camera/view_00.png").write_text("hello")
    msg = problems_of(capture)
    assert "calibration/camera/view_00.png: not a PNG, TIFF, BMP or JPEG image" in msg


def test_colour_image_is_allowed(capture: Path) -> None:
    """Colour images are part of the contract now (sensor.channel, or auto where absent)."""
    import cv2

    cv2.imwrite(str(capture / "calibration/camera/view_00.png"), np.zeros((48, 64, 3), np.uint8))
    assert check_capture(capture)["views"]["camera"] == 3


def test_png_roundtrip_16bit(tmp_path: Path) -> None:
    img = np.random.default_rng(0).integers(0, 65535, (30, 50), dtype=np.uint16)
    write_png(tmp_path / "a.png", img)
    assert png_info(tmp_path / "a.png").bit_depth == 16
    np.testing.assert_array_equal(read_image(tmp_path / "a.png", (30, 50)), img)
    with pytest.raises(ImageError, match=r"a.png: image is 50x30 px, expected 40x30 px"):
        read_image(tmp_path / "a.png", (30, 40))


# --------------------------------------------------------------------------- pattern


def test_laser_pattern_breaks() -> None:
    s = ["A", "B", "AB"] * 10
    s[7] = "off"
    p = laser_pattern(s)
    assert p["period"] == ["A", "B", "AB"]
    assert p["breaks"] == [7]
    p = laser_pattern(["A", "B", "AB", "AB"] * 5)
    assert p["period"] == ["A", "B", "AB", "AB"]
    assert laser_pattern(["A"] * 9)["period"] == ["A"]
    # a long period (A, B and seven AB frames) is found, and with it the labelling's frame gap
    long = ["A", "B"] + ["AB"] * 7
    p = laser_pattern(long * 6)
    assert p["period"] == long and p["breaks"] == []
    from crossline.scan.labels import reference_gap

    assert reference_gap(p["period"]) == 8


# --------------------------------------------------------------------------- rig.yaml: new keys


def test_rig_defaults_keep_old_construction() -> None:
    """New fields come last with defaults: older constructions still work."""
    from crossline.io.capture import Rig, ScanSpec, Sensor

    s = Sensor(64, 48, 8)
    assert (s.data_bits, s.channel) == (None, None)
    assert ScanSpec("p", "plane").mesh is None
    rig = read_rig(make_capture_rig_only())
    assert rig.lasers == ("A", "B") and rig.sensor.data_bits is None and rig.sensor.channel is None
    assert Rig(s, rig.scan_window, 80.0, rig.board, {}).lasers == ("A", "B")


def make_capture_rig_only() -> Path:
    import tempfile

    d = Path(tempfile.mkdtemp(prefix="crossline-rig-"))
    (d / "rig.yaml").write_text(yaml.safe_dump(RIG, sort_keys=False))
    return d / "rig.yaml"


def test_rig_new_keys_read(capture: Path) -> None:
    def f(d):
        d["sensor"].update(data_bits=8, channel="red")
        d["lasers"] = ["B", "A"]

    edit_rig(capture, f)
    rig = read_rig(capture / "rig.yaml")
    assert rig.lasers == ("A", "B") and rig.sensor.data_bits == 8 and rig.sensor.channel == "red"
    s = check_capture(capture)
    assert s["sensor"]["data_bits"] == 8 and s["sensor"]["channel"] == "red"
    assert s["lasers"] == ["A", "B"]
    assert "8-bit (8 data bits), 80 frames/s, red channel" in format_summary(s)


@pytest.mark.parametrize(("key", "value", "expected"), [
    ("lasers", ["A", "A"], "'lasers' must be a list of distinct laser names from ['A', 'B']"),
    ("lasers", ["C"], "got ['C']"),
    ("lasers", "A", "got 'A'"),
    ("lasers", [], "got []"),
    ("data_bits", 12, "'sensor.data_bits' = 12 exceeds 'sensor.bit_depth' = 8"),
    ("data_bits", 9, "'sensor.data_bits' must be one of [8, 10, 12, 14, 16], got 9"),
    ("data_bits", "twelve", "'sensor.data_bits' must be an integer, got 'twelve'"),
    ("channel", "purple", "'sensor.channel' must be one of ['grey', 'red', 'green', 'blue'], got 'purple'"),
])
def test_rig_new_keys_refused(capture: Path, key: str, value, expected: str) -> None:
    edit_rig(capture, lambda d: (d if key == "lasers" else d["sensor"]).__setitem__(key, value))
    msg = problems_of(capture)
    assert expected in msg
    if key != "data_bits" or value != "twelve":  # the new keys' problems carry their line
        assert "rig.yaml, line " in msg


def test_rig_without_scans(capture: Path) -> None:
    shutil.rmtree(capture / "scans")
    edit_rig(capture, lambda d: d.pop("scans"))
    s = check_capture(capture)
    assert s["scans"] == {} and s["stages"]["scans"] == {"allowed": False,
                                                         "why": "rig.yaml describes no scans"}
    edit_rig(capture, lambda d: d.__setitem__("scans", {}))
    assert check_capture(capture)["scans"] == {}


# --------------------------------------------------------------------------- partial captures


def one_laser(capture: Path) -> None:
    """The capture as a single-line rig: lasers [A], every scan frame A."""
    shutil.rmtree(capture / "calibration/laser_B")
    edit_rig(capture, lambda d: d.__setitem__("lasers", ["A"]))
    for scan in ("plate", "gauge"):
        p = capture / f"scans/{scan}/frames.csv"
        p.write_text(p.read_text().replace(",AB,", ",A,").replace(",B,", ",A,"))


def test_one_laser_rig(capture: Path) -> None:
    one_laser(capture)
    cap = open_capture(capture)
    assert cap.rig.lasers == ("A",) and set(cap.laser_views) == {"A"}
    s = check_capture(capture)
    assert s["views"] == {"camera": 3, "laser_A": 2, "handeye": 3}
    assert all(v["allowed"] for v in s["stages"].values())
    assert s["scans"]["plate"]["pattern"] == ["A"]


def test_one_laser_rig_refuses_other_laser(capture: Path) -> None:
    one_laser(capture)
    edit_csv_line(capture / FRAMES, 3, "1,0.0125,AB,0.4,1.5,150,1,0,0,0")
    shutil.copytree(capture / "calibration/laser_A", capture / "calibration/laser_B")
    msg = problems_of(capture)
    assert (f"{FRAMES}, line 3: laser state 'AB' names laser B, which the rig lacks "
            f"(rig.yaml lasers: [A])") in msg
    assert "calibration/laser_B: rig.yaml lasers: [A] but calibration/laser_B exists" in msg


def test_missing_folders_are_no_problem(capture: Path) -> None:
    """Deliberate change: a capture without handeye/ (or any other part) opens; the stages say
    what it allows."""
    shutil.rmtree(capture / "calibration/handeye")
    s = check_capture(capture)
    assert s["views"]["handeye"] == 0
    st = s["stages"]
    assert st["calibrate_camera"]["allowed"] and st["calibrate_lasers"]["allowed"]
    assert st["calibrate_handeye"] == {"allowed": False,
                                       "why": "no calibration/handeye views with arm poses"}
    assert st["scans"]["why"] == "needs calibrate_handeye (no calibration/handeye views with arm poses)"
    text = format_summary(s)
    assert "stages       allows calibrate_camera, calibrate_lasers" in text
    assert "not calibrate_handeye: no calibration/handeye views with arm poses" in text


def test_camera_views_only(capture: Path) -> None:
    for d in ("calibration/laser_A", "calibration/laser_B", "calibration/handeye", "scans"):
        shutil.rmtree(capture / d)
    (capture / "calibration/handeye").mkdir()  # an empty folder is as good as none
    from crossline.io.capture import allowed_stages

    why = allowed_stages(capture)
    assert why["calibrate_camera"] is None
    assert why["calibrate_lasers"] == "no calibration/laser_A views; no calibration/laser_B views"
    assert why["calibrate_handeye"] == "no calibration/handeye views with arm poses"
    assert why["scans"] == "no scans/ folder"
    assert check_capture(capture)["views"] == {"camera": 3, "laser_A": 0, "laser_B": 0, "handeye": 0}


def test_camera_from_other_sets(capture: Path) -> None:
    """Without camera/, the camera calibrates on the laser and hand-eye sets' lasers-off views."""
    from crossline.io.capture import allowed_stages

    shutil.rmtree(capture / "calibration/camera")
    assert all(w is None for w in allowed_stages(capture).values())
    shutil.rmtree(capture / "calibration/handeye")
    for p in (capture / "calibration").glob("laser_*/*_board.png"):
        p.unlink()
    why = allowed_stages(capture)
    assert why["calibrate_camera"].startswith("no calibration/camera views")
    assert why["calibrate_lasers"] == "needs calibrate_camera"


def test_broken_folders_still_are(capture: Path) -> None:
    (capture / POSES).unlink()
    shutil.rmtree(capture / "calibration/laser_A")
    (capture / "calibration/laser_A").mkdir()
    write_png(capture / "calibration/laser_A/p0_laser.png", _img(48, 64, 0))
    msg = problems_of(capture)
    assert f"{POSES}: missing: the arm pose of every hand-eye image is needed" in msg
    assert "calibration/laser_A: has 1 pose(s) with a laser image; the laser plane needs at least 2" in msg


def test_handeye_few_poses_and_header_only(capture: Path) -> None:
    from crossline.io.capture import allowed_stages

    for i in (1, 2):
        edit_csv_line(capture / POSES, 3, None)
        (capture / f"calibration/handeye/pose_{i:02d}.png").unlink()
    assert allowed_stages(capture)["calibrate_handeye"] == (
        "calibration/handeye has 1 view(s) with arm poses; the hand-eye calibration needs at least 3")
    (capture / POSES).write_text("image,x,y,z,qw,qx,qy,qz\n")
    assert f"{POSES}: has 0 pose rows for 1 hand-eye images" in problems_of(capture)


def test_laser_always_on(capture: Path) -> None:
    """Poses with a laser image only: the board is to be found despite the stripe."""
    for p in (capture / "calibration/laser_A").glob("*_board.png"):
        p.unlink()
    cap = open_capture(capture)
    assert [v.board_image for v in cap.laser_views["A"]] == [None, None]
    assert all(v.board_image is not None for v in cap.laser_views["B"])
    s = check_capture(capture)
    assert s["laser_views_without_board"] == {"laser_A": 2, "laser_B": 0}
    assert "laser always on (no lasers-off twin): laser_A 2 pose(s)" in format_summary(s)


def test_unknown_laser_folder(capture: Path) -> None:
    (capture / "calibration/laser_C").mkdir()
    assert "calibration/laser_C: unknown laser 'C'" in problems_of(capture)


# --------------------------------------------------------------------------- nominal mesh


def _freeform(capture: Path, nominal) -> None:
    edit_rig(capture, lambda d: d["scans"].__setitem__("plate", {"artefact": "freeform",
                                                                "nominal": nominal}))


def test_nominal_mesh(capture: Path) -> None:
    (capture / "nominal").mkdir()
    (capture / "nominal/part.STL").write_text("solid part\nendsolid part\n")
    _freeform(capture, "nominal/part.STL")
    assert read_rig(capture / "rig.yaml").scans["plate"].mesh == "nominal/part.STL"
    s = check_capture(capture)
    assert s["scans"]["plate"]["mesh"] == "nominal/part.STL"
    assert "freeform (mesh nominal/part.STL)" in format_summary(s)


@pytest.mark.parametrize(("nominal", "expected"), [
    ("part.stl", "'scans.plate.nominal' = 'part.stl' has no file in the capture"),
    ("part.step", "'scans.plate.nominal' = 'part.step' must be a mesh file (.stl, .ply, .obj)"),
    ("../evil.stl", "'scans.plate.nominal' = '../evil.stl' leads out of its folder ('..')"),
    ("/etc/passwd", "'scans.plate.nominal' = '/etc/passwd' is an absolute path"),
    (12, "'scans.plate.nominal' must be a mesh file's path relative to the capture"),
])
def test_nominal_mesh_refused(capture: Path, nominal, expected: str) -> None:
    (capture.parent / "evil.stl").write_text("solid evil\n")
    _freeform(capture, nominal)
    msg = problems_of(capture)
    assert expected in msg
    lines = (capture / "rig.yaml").read_text().splitlines()
    line = next(i for i, t in enumerate(lines, 1) if t.strip().startswith("nominal:"))
    assert f"rig.yaml, line {line}: 'scans.plate.nominal'" in msg


def test_nominal_mesh_symlink_outside(capture: Path, tmp_path: Path) -> None:
    (tmp_path / "outside.stl").write_text("solid evil\n")
    (capture / "part.stl").symlink_to(tmp_path / "outside.stl")
    _freeform(capture, "part.stl")
    msg = problems_of(capture)
    assert "'scans.plate.nominal' = 'part.stl' is a symbolic link to" in msg
    assert "outside the capture" in msg


def test_nominal_on_other_artefact(capture: Path) -> None:
    edit_rig(capture, lambda d: d["scans"]["gauge"].__setitem__("nominal", "gauge.stl"))
    assert "'scans.gauge.nominal' names a mesh, which only a freeform takes" in problems_of(capture)


# --------------------------------------------------------------------------- paths inside the capture


def test_poses_csv_name_outside(capture: Path, tmp_path: Path) -> None:
    """Issue 23.1: '..', absolute paths and links out are refused with file, line and reason."""
    write_png(tmp_path / "evil.png", _img(48, 64, 0))
    edit_csv_line(capture / POSES, 2, "../../evil.png,100,20.5,300,1,0,0,0")
    edit_csv_line(capture / POSES, 3, "/etc/passwd,100,20.5,300,1,0,0,0")
    msg = problems_of(capture)
    assert f"{POSES}, line 2: image '../../evil.png' leads out of its folder ('..')" in msg
    assert f"{POSES}, line 3: image '/etc/passwd' is an absolute path" in msg


def test_symlink_outside_refused(capture: Path, tmp_path: Path) -> None:
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    write_png(outside / "evil.png", _img(48, 64, 0))
    he = capture / "calibration/handeye"
    (he / "pose_01.png").unlink()
    (he / "pose_01.png").symlink_to(outside / "evil.png")
    (capture / "calibration/camera/view_03.png").symlink_to(Path("/tmp"))
    frame = capture / "scans/plate/frames/000002.png"
    frame.unlink()
    frame.symlink_to(outside / "evil.png")
    msg = problems_of(capture)
    evil = outside / "evil.png"
    assert f"calibration/handeye/pose_01.png: is a symbolic link to {evil}, outside the capture" in msg
    assert f"{POSES}, line 3: image 'pose_01.png' is a symbolic link to" in msg
    assert "calibration/camera/view_03.png: is a symbolic link to /tmp, outside the capture" in msg
    assert "scans/plate/frames/000002.png: is a symbolic link to" in msg


def test_folder_symlink_outside_refused(capture: Path, tmp_path: Path) -> None:
    shutil.move(capture / "calibration/camera", tmp_path / "camera")
    (capture / "calibration/camera").symlink_to(tmp_path / "camera")
    assert f"calibration/camera: is a symbolic link to {tmp_path / 'camera'}, outside the capture" in (
        problems_of(capture))


def test_symlinks_inside_are_fine(capture: Path) -> None:
    shutil.move(capture / "calibration/camera", capture / "camera_views")
    (capture / "calibration/camera").symlink_to(Path("../camera_views"))
    assert check_capture(capture)["views"]["camera"] == 3


def test_rig_yaml_symlink_outside(capture: Path, tmp_path: Path) -> None:
    shutil.move(capture / "rig.yaml", tmp_path / "rig.yaml")
    (capture / "rig.yaml").symlink_to(tmp_path / "rig.yaml")
    assert "rig.yaml: is a symbolic link to" in problems_of(capture)


def test_scan_name_outside(capture: Path) -> None:
    edit_rig(capture, lambda d: d["scans"].__setitem__("../../x", {"artefact": "plane"}))
    assert "scan name '../../x' leads out of its folder" in problems_of(capture)


def _truth(capture: Path, scans: dict) -> None:
    """A simulated capture's truth.json with these ``scans`` entries (their file names)."""
    (capture / "truth.json").write_text(json.dumps({"format": "crossline-truth/1", "scans": scans},
                                                   indent=2))


def test_truth_json_names_outside(capture: Path, tmp_path: Path, capsys) -> None:
    """Issue 23.1: the files truth.json names ('..', an absolute path, a symbolic link out)
    are refused by check and by the report's reader, naming truth.json, the key and why."""
    (tmp_path / "evil.ply").write_text("ply\n")
    (capture / "truth").mkdir()
    (capture / "truth/gauge_centrelines.parquet").symlink_to(tmp_path / "evil.ply")
    scans = {"plate": {"mesh": "../evil.ply", "centrelines": "/etc/passwd",
                       "poses": "truth/plate_poses.parquet"},  # inside (if missing): fine
             "gauge": {"centrelines": "truth/gauge_centrelines.parquet", "height": 20.0}}
    _truth(capture, scans)
    expected = [
        "truth.json: 'scans.plate.mesh' = '../evil.ply' leads out of its folder ('..'); every "
        "file of a capture lies inside it",
        "truth.json: 'scans.plate.centrelines' = '/etc/passwd' is an absolute path; names are "
        "relative to the capture folder, inside it",
        "truth.json: 'scans.gauge.centrelines' = 'truth/gauge_centrelines.parquet' is a symbolic "
        f"link to {tmp_path / 'evil.ply'}, outside the capture; every file of a capture lies "
        "inside its folder",
    ]
    with pytest.raises(CaptureError) as info:
        open_capture(capture)
    assert [str(p) for p in info.value.problems] == expected
    assert main(["check", str(capture)]) == 2
    err = capsys.readouterr().err
    assert all(e in err for e in expected) and "3 problems" in err
    for (scan, key), e in zip([("plate", "mesh"), ("plate", "centrelines"), ("gauge", "centrelines")],
                              expected, strict=True):
        with pytest.raises(CaptureError) as info:
            truth_file(capture, scan, scans[scan], key)
        assert [str(p) for p in info.value.problems] == [e]
    assert truth_file(capture, "plate", scans["plate"], "poses") == capture / "truth/plate_poses.parquet"


def test_truth_json_names_inside(capture: Path) -> None:
    """Good names (as the simulator writes them) change nothing; nor do other keys, a name
    that is not there yet, a symbolic link inside, or a truth.json that is not readable JSON
    (the report leaves its validation out)."""
    (capture / "truth").mkdir()
    (capture / "truth/part.ply").write_text("ply\n")
    (capture / "truth/link.ply").symlink_to(Path("part.ply"))
    scans = {"plate": {"mesh": "truth/part.ply", "centrelines": "truth/plate_centrelines.parquet",
                       "plane_base": [0, 0, 1, 0]},
             "gauge": {"mesh": "truth/link.ply"}, "other": "not a mapping"}
    _truth(capture, scans)
    s = check_capture(capture)
    assert s["simulated"] and open_capture(capture).truth_path == capture / "truth.json"
    assert truth_file(capture, "plate", scans["plate"], "mesh") == capture / "truth/part.ply"
    assert truth_file(capture, "gauge", scans["gauge"], "mesh") == capture / "truth/link.ply"
    (capture / "truth.json").write_text('{"scans": {"plate": {"mesh": "../evil.ply"')
    assert check_capture(capture)["simulated"]


def test_truth_json_symlink_outside(capture: Path, tmp_path: Path) -> None:
    """truth.json itself leading outside is refused, and not read."""
    (tmp_path / "truth.json").write_text(json.dumps({"scans": {"plate": {"mesh": "../x.ply"}}}))
    (capture / "truth.json").symlink_to(tmp_path / "truth.json")
    msg = problems_of(capture)
    assert f"truth.json: is a symbolic link to {tmp_path / 'truth.json'}, outside the capture" in msg
    assert "scans.plate.mesh" not in msg


# --------------------------------------------------------------------------- image formats


def _colour(h: int, w: int) -> np.ndarray:
    """An (H, W, 3) image in the order red, green, blue, each channel distinct."""
    rng = np.random.default_rng(5)
    return np.stack([rng.integers(0, 80, (h, w)), rng.integers(90, 170, (h, w)),
                     rng.integers(180, 255, (h, w))], axis=-1).astype(np.uint8)


def test_read_image_channels_and_order(tmp_path: Path) -> None:
    import cv2

    from crossline.io.images import read_image_channels, write_image

    rgb = _colour(20, 30)
    for ext in (".png", ".tif", ".bmp"):
        p = tmp_path / f"c{ext}"
        write_image(p, rgb)
        np.testing.assert_array_equal(read_image(p, (20, 30), channel="red"), rgb[:, :, 0])
        np.testing.assert_array_equal(read_image(p, channel="green"), rgb[:, :, 1])
        np.testing.assert_array_equal(read_image(p, channel="blue"), rgb[:, :, 2])
        lum = cv2.cvtColor(np.ascontiguousarray(rgb[:, :, ::-1]), cv2.COLOR_BGR2GRAY)
        np.testing.assert_array_equal(read_image(p), lum)
        np.testing.assert_array_equal(read_image(p, channel="grey"), lum)
        np.testing.assert_array_equal(read_image_channels(p), rgb)
    grey = _img(20, 30, 1)
    write_image(tmp_path / "g.bmp", grey)
    np.testing.assert_array_equal(read_image(tmp_path / "g.bmp", channel="red"), grey)
    assert read_image_channels(tmp_path / "g.bmp").shape == (20, 30, 1)
    # 16-bit colour TIFF: never scaled
    rgb16 = rgb.astype(np.uint16) * 257 + 3
    write_image(tmp_path / "c16.tiff", rgb16)
    out = read_image(tmp_path / "c16.tiff", channel="blue")
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, rgb16[:, :, 2])
    with pytest.raises(ValueError, match="channel must be one of"):
        read_image(tmp_path / "g.bmp", channel="infrared")


def test_image_info_formats(tmp_path: Path) -> None:
    from crossline.io.images import image_info, write_image

    cases = {"a.png": (_img(20, 30, 0), 8, 1, "PNG"), "b.jpg": (_colour(20, 30), 8, 3, "JPEG"),
             "c.TIF": (_img(20, 30, 0).astype(np.uint16), 16, 1, "TIFF"),
             "d.bmp": (_colour(20, 30), 8, 3, "BMP"), "e.jpeg": (_img(20, 30, 0), 8, 1, "JPEG")}
    for name, (img, bits, ch, fmt) in cases.items():
        write_image(tmp_path / name, img)
        info = image_info(tmp_path / name)
        got = (info.width, info.height, info.bit_depth, info.channels, info.format)
        assert got == (30, 20, bits, ch, fmt)


def _png_header_claiming(w: int, h: int) -> bytes:
    import struct
    import zlib

    def chunk(t: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + t + body + struct.pack(">I", zlib.crc32(t + body))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 10))
            + chunk(b"IEND", b""))


def _tiff_claiming(w: int, h: int, data_len: int, strip_bytes: int) -> bytes:
    """A little-endian grey 8-bit TIFF header claiming w x h, with data_len bytes of pixels."""
    import struct

    tags = [(256, 4, w), (257, 4, h), (258, 3, 8), (259, 3, 1), (262, 3, 1), (273, 4, 8),
            (277, 3, 1), (278, 4, h), (279, 4, strip_bytes)]
    ifd_at = 8 + data_len
    out = b"II*\0" + struct.pack("<I", ifd_at) + b"\x80" * data_len + struct.pack("<H", len(tags))
    for tag, typ, val in tags:
        out += struct.pack("<HHI", tag, typ, 1) + (struct.pack("<HH", val, 0) if typ == 3
                                                    else struct.pack("<I", val))
    return out + b"\0\0\0\0"


def test_huge_headers_refused_before_allocation(tmp_path: Path) -> None:
    from crossline.io.images import image_info

    (tmp_path / "big.png").write_bytes(_png_header_claiming(60000, 60000))
    (tmp_path / "big.tif").write_bytes(_tiff_claiming(12000, 12000, 16, 12000 * 12000))
    (tmp_path / "huge.tif").write_bytes(_tiff_claiming(60000, 60000, 16, 60000 * 60000))
    for name in ("big.png", "big.tif", "huge.tif"):
        for fn in (image_info, read_image):
            with pytest.raises(ImageError, match=rf"{name}: header claims .*100 MP"):
                fn(tmp_path / name)
    (tmp_path / "ok.tif").write_bytes(_tiff_claiming(4, 4, 16, 16))
    assert image_info(tmp_path / "ok.tif").width == 4
    assert read_image(tmp_path / "ok.tif").shape == (4, 4)


def test_truncated_other_formats(tmp_path: Path) -> None:
    from crossline.io.images import image_info, write_image

    (tmp_path / "t.tif").write_bytes(_tiff_claiming(40, 40, 16, 1600))
    write_image(tmp_path / "t.jpg", _colour(200, 300))
    write_image(tmp_path / "t.bmp", _colour(20, 30))
    for name in ("t.jpg", "t.bmp"):
        data = (tmp_path / name).read_bytes()
        (tmp_path / name).write_bytes(data[: len(data) * 2 // 3])
    for name, fmt in (("t.tif", "TIFF"), ("t.jpg", "JPEG"), ("t.bmp", "BMP")):
        for fn in (image_info, read_image):
            with pytest.raises(ImageError, match=rf"{name}: truncated {fmt}"):
                fn(tmp_path / name)


def test_capture_in_other_formats(capture: Path) -> None:
    """Calibration views and scan frames as JPEG, TIFF and BMP, any extension case."""
    from crossline.io.images import write_image

    cam = capture / "calibration/camera"
    for i, ext in enumerate((".jpg", ".TIF", ".bmp")):
        (cam / f"view_{i:02d}.png").unlink()
        write_image(cam / f"view_{i:02d}{ext}", _colour(48, 64) if i == 0 else _img(48, 64, i))
    d = capture / "calibration/laser_A"
    (d / "pose0_laser.png").unlink()
    write_image(d / "pose0_laser.jpeg", _img(48, 64, 0))
    frames = capture / "scans/plate/frames"
    for p in sorted(frames.glob("*.png")):
        img = read_image(p)
        p.unlink()
        write_image(p.with_suffix(".tiff"), img)
    cap = open_capture(capture)
    assert [p.name for p in cap.camera_images] == ["view_00.jpg", "view_01.TIF", "view_02.bmp"]
    assert cap.laser_views["A"][0].laser_image.name == "pose0_laser.jpeg"
    sc = cap.scans["plate"]
    assert sc.frame_path(3) == frames / "000003.tiff" and all(p.is_file() for p in sc.frame_paths)
    s = check_capture(capture)
    assert s["image_formats"] == {"BMP": 1, "JPEG": 2, "PNG": 16, "TIFF": 7}
    assert s["scans"]["plate"]["frame_format"] == "tiff"
    write_png(frames / "000004.png", _img(16, 40, 0))
    assert "scans/plate/frames: frames have several extensions (.png, .tiff)" in problems_of(capture)


def test_bit_depth_against_rig(capture: Path) -> None:
    from crossline.io.images import write_image

    (capture / "calibration/camera/view_00.png").unlink()
    write_image(capture / "calibration/camera/view_00.jpg", _img(48, 64, 0))
    edit_rig(capture, lambda d: d["sensor"].__setitem__("bit_depth", 16))
    msg = problems_of(capture)
    assert ("calibration/camera/view_00.jpg: JPEG image has 8-bit samples, expected 16 "
            "(rig.yaml sensor.bit_depth)") in msg
    assert "calibration/camera/view_01.png: PNG image has 8-bit samples, expected 16" in msg


def test_foreign_laser_states_one_problem_per_state(capture: Path) -> None:
    """A two-laser scan under a one-laser rig.yaml: one problem per state, not one per row."""
    edit_rig(capture, lambda d: d.__setitem__("lasers", ["A"]))
    shutil.rmtree(capture / "calibration/laser_B")
    with pytest.raises(CaptureError) as info:
        open_capture(capture)
    msg = str(info.value)
    assert (f"{FRAMES}, line 3: laser state 'B' names laser B, which the rig lacks (rig.yaml "
            f"lasers: [A]) (and 1 more row(s): lines 6)") in msg
    assert f"{FRAMES}, line 4: laser state 'AB' names laser B" in msg
    assert len(info.value.problems) == 4  # two states in each of two scans


def test_nominal_pose_is_the_parts_placement(capture: Path) -> None:
    (capture / "part.stl").write_text("solid part\nendsolid part\n")
    c, s_ = float(np.cos(np.radians(15.0))), float(np.sin(np.radians(15.0)))
    edit_rig(capture, lambda d: d["scans"].__setitem__("plate", {
        "artefact": "freeform", "nominal": "part.stl",
        "nominal_pose": [600.0, 60.0, -2.5, c, 0.0, 0.0, s_]}))
    T = read_rig(capture / "rig.yaml").scans["plate"].T_base_nominal
    # a turn of 30 degrees about z, then the shift (quaternion (cos 15°, 0, 0, sin 15°))
    assert np.allclose(T[:3, 3], [600.0, 60.0, -2.5])
    assert np.isclose(np.degrees(np.arctan2(T[1, 0], T[0, 0])), 30.0)
    assert read_rig(capture / "rig.yaml").scans["gauge"].T_base_nominal is None
    s = check_capture(capture)
    assert s["scans"]["plate"]["nominal_pose"] == [600.0, 60.0, -2.5, c, 0.0, 0.0, s_]
    assert "freeform (mesh part.stl, placed by nominal_pose)" in format_summary(s)


@pytest.mark.parametrize(("pose", "mesh", "expected"), [
    ([1, 2, 3, 1, 0, 0], "part.stl", "'scans.plate.nominal_pose' must be [x, y, z, qw, qx, qy, qz]"),
    ([1, 2, 3, 1, 0, 0, ".nan"], "part.stl", "'scans.plate.nominal_pose' must be [x, y, z, qw, qx, qy, qz]"),
    ([1, 2, 3, 1, 0, 0, True], "part.stl", "'scans.plate.nominal_pose' must be [x, y, z, qw, qx, qy, qz]"),
    ([1, 2, 3, 0.9, 0, 0, 0], "part.stl", "quaternion [0.9, 0, 0, 0] has length 0.900000; expected 1"),
    ([1, 2, 3, 1, 0, 0, 0], None, "'scans.plate.nominal_pose' places a nominal mesh: only a freeform"),
])
def test_nominal_pose_refused(capture: Path, pose, mesh, expected: str) -> None:
    (capture / "part.stl").write_text("solid part\nendsolid part\n")
    pose = [float("nan") if v == ".nan" else v for v in pose]
    spec = {"artefact": "freeform", "nominal_pose": pose} | ({"nominal": mesh} if mesh else {})
    edit_rig(capture, lambda d: d["scans"].__setitem__("plate", spec))
    msg = problems_of(capture)
    assert expected in msg
    lines = (capture / "rig.yaml").read_text().splitlines()
    line = next(i for i, t in enumerate(lines, 1) if t.strip().startswith("nominal_pose:"))
    assert f"rig.yaml, line {line}: 'scans.plate.nominal_pose'" in msg

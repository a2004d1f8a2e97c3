"""Capture reading and validation: every bad input gets an error naming file, line and expectation."""

from __future__ import annotations

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

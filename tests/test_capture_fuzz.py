"""Random bytes and random rows fed to the capture readers: only clean, named errors come out."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crossline.io.capture import CaptureError, check_capture, open_capture, read_rig
from crossline.io.images import ImageError, png_info, read_image
from tests.test_capture import make_capture

_TEMPLATE: Path | None = None


def template() -> Path:
    global _TEMPLATE
    if _TEMPLATE is None:
        root = Path(tempfile.mkdtemp(prefix="crossline-fuzz-"))
        atexit.register(shutil.rmtree, root, True)
        _TEMPLATE = make_capture(root / "cap", 4)
    return _TEMPLATE


def fresh_copy() -> Path:
    dst = Path(tempfile.mkdtemp(prefix="crossline-fuzz-")) / "cap"
    shutil.copytree(template(), dst)
    return dst


FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
cell = st.one_of(
    st.text(max_size=12),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10, 10**12).map(str),
    st.sampled_from(["A", "B", "AB", "off", "", "nan", "1e309", "-0", "000001"]),
)


@FUZZ
@given(st.binary(max_size=2000))
def test_rig_yaml_random_bytes(data: bytes) -> None:
    root = fresh_copy()
    (root / "rig.yaml").write_bytes(data)
    try:
        read_rig(root / "rig.yaml")
    except CaptureError as exc:
        assert "rig.yaml" in str(exc)
    finally:
        shutil.rmtree(root.parent)


@FUZZ
@given(st.lists(st.lists(cell, min_size=0, max_size=12), max_size=8))
def test_frames_csv_random_rows(rows: list[list[str]]) -> None:
    root = fresh_copy()
    path = root / "scans" / "plate" / "frames.csv"
    header = path.read_text().splitlines()[0]
    body = "\n".join(",".join(c.replace("\n", " ").replace("\r", " ") for c in r) for r in rows)
    path.write_text(header + "\n" + body + "\n")
    try:
        open_capture(root)
    except CaptureError as exc:
        assert "scans/plate/frames.csv" in str(exc)
    finally:
        shutil.rmtree(root.parent)


@FUZZ
@given(st.binary(max_size=3000))
def test_poses_csv_random_bytes(data: bytes) -> None:
    root = fresh_copy()
    (root / "calibration" / "handeye" / "poses.csv").write_bytes(data)
    try:
        open_capture(root)
    except CaptureError as exc:
        assert "calibration/handeye" in str(exc)
    finally:
        shutil.rmtree(root.parent)


@FUZZ
@given(st.binary(max_size=400), st.integers(0, 200))
def test_png_random_bytes(data: bytes, cut: int) -> None:
    root = fresh_copy()
    p = root / "scans" / "gauge" / "frames" / "000001.png"
    good = p.read_bytes()
    p.write_bytes(good[:cut] + data)
    try:
        for fn in (png_info, read_image):
            try:
                fn(p)
            except ImageError as exc:
                assert "000001.png" in str(exc)
        try:
            check_capture(root)
        except CaptureError as exc:
            assert "000001.png" in str(exc)
    finally:
        shutil.rmtree(root.parent)

"""Captures as untrusted input (issue 23.2): random corruptions of rig.yaml (bytes, keys, types),
of the CSV tables (rows, columns, names), of image bytes and header sizes, and missing and extra
files (symbolic links out included) give either a correct result or a :class:`CaptureError`
whose every problem names a file of the capture; never another exception, and never a read of
a file outside the capture (every ``open`` is watched through an audit hook).

Cases tried (hypothesis ``max_examples``): 11 properties; 60 examples each for rig.yaml bytes,
poses.csv bytes, frame bytes and missing/extra files, 80 each for rig.yaml keys and types,
frames.csv rows, column orders, poses.csv names, image bytes in every format, PNG header
sizes and the file names in truth.json: 800 captures in all, about 10 s of CPU (20-30 s wall
on 2 shared, loaded cores).
``CROSSLINE_FUZZ_SCALE=N`` multiplies the cases.
"""

from __future__ import annotations

import atexit
import json
import os
import shutil
import struct
import sys
import tempfile
import zlib
from pathlib import Path, PurePosixPath

import numpy as np
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crossline.io.capture import (
    TRUTH_FILE_KEYS,
    CaptureError,
    check_capture,
    open_capture,
    read_rig,
    truth_file,
)
from crossline.io.images import ImageError, image_info, png_info, read_image, write_image
from tests.test_capture import RIG, make_capture

_TEMPLATE: Path | None = None
_BAIT: Path | None = None
_WATCH: list[Path] = []  # while non-empty: the capture whose reads are being watched
_OUTSIDE: list[str] = []  # files opened outside it


def _audit(event: str, args: tuple) -> None:
    if not _WATCH or event != "open" or not isinstance(args[0], str | bytes | os.PathLike):
        return
    path = os.fsdecode(args[0])
    if path.endswith((".py", ".pyc", ".so", ".pth", ".json")) and "site-packages" in path:
        return  # a lazy import
    try:
        real = Path(path).resolve()
    except (OSError, RuntimeError):
        return
    root = _WATCH[-1]
    if real.is_relative_to(root.parent) and not real.is_relative_to(root):
        _OUTSIDE.append(str(real))  # a sibling of the capture: the bait, or anything else there
    elif real == Path("/etc/passwd") or (_BAIT is not None and real.is_relative_to(_BAIT)):
        _OUTSIDE.append(str(real))


sys.addaudithook(_audit)


def template() -> Path:
    """A small complete capture (one freeform scan with a nominal mesh), made once."""
    global _TEMPLATE, _BAIT
    if _TEMPLATE is None:
        # in memory where the machine has it: hundreds of small copies, no disk traffic
        shm = Path("/dev/shm")
        base = Path(tempfile.mkdtemp(prefix="crossline-fuzz-",
                                     dir=shm if shm.is_dir() and os.access(shm, os.W_OK) else None))
        atexit.register(shutil.rmtree, base, True)
        _BAIT = base / "bait"
        _BAIT.mkdir()
        write_image(_BAIT / "evil.png", np.zeros((48, 64), np.uint8))
        (_BAIT / "evil.stl").write_text("solid evil\nendsolid evil\n")
        _TEMPLATE = make_capture(base / "tmpl" / "cap", 4)
        (_TEMPLATE / "part.stl").write_text("solid part\nendsolid part\n")
        data = yaml.safe_load((_TEMPLATE / "rig.yaml").read_text())
        data["scans"]["plate"] = {"artefact": "freeform", "nominal": "part.stl"}
        data["lasers"] = ["A", "B"]
        data["sensor"]["data_bits"] = 8
        (_TEMPLATE / "rig.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return _TEMPLATE


def fresh_copy() -> Path:
    template()
    dst = Path(tempfile.mkdtemp(prefix="crossline-fuzz-", dir=_BAIT.parent)) / "cap"
    shutil.copytree(template(), dst, symlinks=True)
    return dst


class watched:
    """Copy of the template whose every file opened while inside is checked to be in it."""

    def __enter__(self) -> Path:
        self.root = fresh_copy()
        _OUTSIDE.clear()
        _WATCH.append(self.root.resolve())
        return self.root

    def __exit__(self, *exc) -> None:
        _WATCH.pop()
        shutil.rmtree(self.root.parent, ignore_errors=True)
        assert not _OUTSIDE, f"read outside the capture: {_OUTSIDE}"


def assert_named(exc: CaptureError, *expected: str) -> None:
    """Every problem names a file of the capture (relative, no '..') and says something; with
    ``expected``, at least one problem names a file starting with one of them."""
    assert exc.problems
    for p in exc.problems:
        assert p.file and p.message.strip()
        if p.file != str(exc.root):
            assert not PurePosixPath(p.file).is_absolute() and ".." not in PurePosixPath(p.file).parts
    if expected:
        assert any(p.file.startswith(expected) for p in exc.problems), str(exc)


def assert_refused_or_read(root: Path, p: Path, readers: tuple = (),
                           refusals: tuple = (ImageError,)) -> list:
    """Each reader decodes the damaged file ``p`` (an image by default) or refuses it naming
    it, with one of ``refusals``; the capture check passes or names it. Returns what the
    readers decoded."""
    out = []
    for fn in readers or (image_info, read_image):
        try:
            out.append((fn, fn(p)))
        except refusals as exc:
            assert p.name in str(exc)
    try:
        check_capture(root)
    except CaptureError as exc:
        assert_named(exc, p.relative_to(root).as_posix())
    return out


# CROSSLINE_FUZZ_SCALE=10 multiplies every property's cases (a longer hunt, off the suite)
_SCALE = float(os.environ.get("CROSSLINE_FUZZ_SCALE", "1"))
FUZZ = settings(max_examples=int(60 * _SCALE), deadline=None,
                suppress_health_check=[HealthCheck.too_slow])
MORE = settings(FUZZ, max_examples=int(80 * _SCALE))
cell = st.one_of(
    st.text(max_size=12),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10, 10**12).map(str),
    st.sampled_from(["A", "B", "AB", "off", "", "nan", "1e309", "-0", "000001"]),
)
# names a capture's file might give: good ones, ways out, odd ones
name = st.one_of(
    st.sampled_from(["pose_00.png", "pose_01.png", "pose_02.png", "../bait/evil.png",
                     "../../bait/evil.png", "/etc/passwd", "sub/pose_00.png", "..", ".",
                     "pose_00.PNG", "C:\\evil.png", "\\\\server\\share\\x.png", "part.stl",
                     "../bait/evil.stl", "poses.csv", ""]),
    st.text(max_size=16).filter(lambda s: "\n" not in s and "\r" not in s),
)
leaf = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 70000), st.floats(allow_nan=True), st.text(max_size=10),
    st.sampled_from(["A", "B", "AB", "red", "grey", "freeform", "plane", "sphere", "part.stl",
                     "../bait/evil.stl", "/etc/passwd", "symmetric", "chessboard", 8, 12, 16]),
    st.sampled_from([["A"], ["B"], ["A", "B"], ["A", "A"], [], ["C"]]),
)
value = st.recursive(leaf, lambda kids: st.lists(kids, max_size=3)
                     | st.dictionaries(st.text(max_size=8), kids, max_size=3), max_leaves=6)


def _key_paths(d: dict, prefix: tuple = ()) -> list[tuple]:
    out = []
    for k, v in d.items():
        out.append((*prefix, k))
        if isinstance(v, dict):
            out += _key_paths(v, (*prefix, k))
    return out


RIG_TEMPLATE = {**RIG, "lasers": ["A", "B"], "scans": {**RIG["scans"], "plate": {
    "artefact": "freeform", "nominal": "part.stl"}}}
RIG_TEMPLATE["sensor"] = {**RIG["sensor"], "data_bits": 8, "channel": "grey"}
RIG_PATHS = [*_key_paths(RIG_TEMPLATE), ("scans", "ball"), ("sensor", "channel"), ("lasers",),
             ("scans", "plate", "nominal"), ("board", "diameter")]
edit = st.tuples(st.sampled_from(["delete", "set"]), st.sampled_from(RIG_PATHS), value)


# --------------------------------------------------------------------------- rig.yaml


@FUZZ
@given(st.binary(max_size=2000))
def test_rig_yaml_random_bytes(data: bytes) -> None:
    with watched() as root:
        (root / "rig.yaml").write_bytes(data)
        try:
            read_rig(root / "rig.yaml")
        except CaptureError as exc:
            assert_named(exc, "rig.yaml")


@MORE
@given(st.lists(edit, min_size=1, max_size=4))
def test_rig_yaml_keys_and_types(edits: list) -> None:
    """Keys deleted or set to values of any type; check_capture either passes or names files."""
    import copy

    data = copy.deepcopy(RIG_TEMPLATE)
    for op, path, v in edits:
        node = data
        for k in path[:-1]:
            if not isinstance(node, dict):
                break
            node = node.setdefault(k, {}) if op == "set" else node.get(k, {})
        else:
            if isinstance(node, dict):
                if op == "delete":
                    node.pop(path[-1], None)
                else:
                    node[path[-1]] = v
    with watched() as root:
        (root / "rig.yaml").write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True),
                                       encoding="utf-8")
        try:
            summary = check_capture(root)
        except CaptureError as exc:
            assert_named(exc)
            return
        rig = read_rig(root / "rig.yaml")
        assert summary["lasers"] == list(rig.lasers) and set(rig.lasers) <= {"A", "B"}
        assert {k for k in summary["views"] if k.startswith("laser_")} == {f"laser_{x}" for x in rig.lasers}
        mesh = rig.scans["plate"].mesh if "plate" in rig.scans else None
        assert mesh is None or (root / mesh).resolve().is_relative_to(root.resolve())


# --------------------------------------------------------------------------- CSV tables


@MORE
@given(st.lists(st.lists(cell, min_size=0, max_size=12), max_size=8))
def test_frames_csv_random_rows(rows: list[list[str]]) -> None:
    with watched() as root:
        path = root / "scans" / "gauge" / "frames.csv"
        header = path.read_text().splitlines()[0]
        body = "\n".join(",".join(c.replace("\n", " ").replace("\r", " ") for c in r) for r in rows)
        path.write_text(header + "\n" + body + "\n", encoding="utf-8")
        try:
            open_capture(root)
        except CaptureError as exc:
            assert_named(exc, "scans/gauge/frames.csv", "scans/gauge/frames/")


@MORE
@given(st.permutations(list(range(10))), st.integers(0, 10), st.booleans(), st.sampled_from(
    ["scans/gauge/frames.csv", "calibration/handeye/poses.csv"]))
def test_csv_column_order(order: list[int], drop: int, extra: bool, table: str) -> None:
    """Columns in any order read the same table; a missing column is named, an extra one ignored."""
    with watched() as root:
        good = open_capture(root)
        path = root / table
        rows = [r.split(",") for r in path.read_text().splitlines()]
        n = len(rows[0])
        keep = [i for i in order if i < n and i != drop]
        out = [[r[i] for i in keep] + (["x"] if extra else []) for r in rows]
        if extra:
            out[0][-1] = "comment"
        path.write_text("\n".join(",".join(r) for r in out) + "\n")
        try:
            cap = open_capture(root)
        except CaptureError as exc:
            assert drop < n, str(exc)  # only a dropped column is a fault
            assert_named(exc, table)
            assert any(p.line == 1 and "missing column" in p.message for p in exc.problems)
            return
        assert drop >= n
        if table.startswith("scans"):
            a, b = good.scans["gauge"], cap.scans["gauge"]
            assert np.array_equal(a.frames, b.frames) and list(a.lasers) == list(b.lasers)
            assert np.array_equal(a.T_base_tool, b.T_base_tool)
        else:
            assert good.handeye_images == cap.handeye_images
            assert np.array_equal(good.handeye_T_base_tool, cap.handeye_T_base_tool)


@FUZZ
@given(st.binary(max_size=3000))
def test_poses_csv_random_bytes(data: bytes) -> None:
    with watched() as root:
        (root / "calibration" / "handeye" / "poses.csv").write_bytes(data)
        try:
            open_capture(root)
        except CaptureError as exc:
            assert_named(exc, "calibration/handeye")


@MORE
@given(st.lists(name, min_size=0, max_size=5))
def test_poses_csv_names(names: list[str]) -> None:
    """Image names anywhere (out of the capture, absolute, in subfolders): named with their line."""
    with watched() as root:
        rows = ["image,x,y,z,qw,qx,qy,qz"] + [f"{n.replace(',', ';')},1,2,3,1,0,0,0" for n in names]
        (root / "calibration/handeye/poses.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
        try:
            cap = open_capture(root)
        except CaptureError as exc:
            assert_named(exc, "calibration/handeye")
            return
        assert sorted(n for n in names) == ["pose_00.png", "pose_01.png", "pose_02.png"]
        assert all(p.resolve().is_relative_to(root.resolve()) for p in cap.handeye_images)


# --------------------------------------------------------------------------- images


@FUZZ
@given(st.binary(max_size=400), st.integers(0, 200))
def test_png_random_bytes(data: bytes, cut: int) -> None:
    with watched() as root:
        p = root / "scans" / "gauge" / "frames" / "000001.png"
        good = p.read_bytes()
        p.write_bytes(good[:cut] + data)
        assert_refused_or_read(root, p, (png_info, image_info, read_image))


@MORE
@given(st.sampled_from([".png", ".jpg", ".tif", ".bmp"]), st.booleans(), st.integers(0, 10**6),
       st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=6),
       st.binary(max_size=64))
def test_image_bytes_every_format(ext: str, colour: bool, cut: int, flips: list, tail: bytes) -> None:
    """A calibration view in any format, cut short, bytes changed, bytes appended."""
    with watched() as root:
        old = root / "calibration/camera/view_01.png"
        img = np.random.default_rng(1).integers(0, 255, (48, 64, 3) if colour else (48, 64), np.uint8)
        old.unlink()
        p = old.with_suffix(ext)
        write_image(p, img)
        data = bytearray(p.read_bytes())
        data = data[: max(1, cut % (len(data) + 1))]
        for at, v in flips:
            data[at % len(data)] = v
        p.write_bytes(bytes(data) + tail)
        for fn, out in assert_refused_or_read(root, p):
            if fn is read_image:
                assert out.ndim == 2 and out.dtype in (np.uint8, np.uint16)


def _png(w: int, h: int, depth: int, colour: int, idat: bytes) -> bytes:
    def chunk(t: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + t + body + struct.pack(">I", zlib.crc32(t + body))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, 0))
            + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


@MORE
@given(st.integers(0, 2**32 - 1) | st.integers(0, 100), st.integers(0, 2**32 - 1) | st.integers(0, 100),
       st.sampled_from([1, 2, 4, 8, 16, 3, 0]), st.sampled_from([0, 2, 3, 4, 6, 5]),
       st.binary(max_size=64).map(zlib.compress))
def test_png_header_sizes(w: int, h: int, depth: int, colour: int, idat: bytes) -> None:
    """Valid-CRC headers claiming any size and bit depth: refused or decoded, never allocated."""
    with watched() as root:
        p = root / "scans/plate/frames/000002.png"
        p.write_bytes(_png(w, h, depth, colour, idat))
        assert_refused_or_read(root, p)


# --------------------------------------------------------------------------- missing and extra files


def _files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))


FILES = None


def template_files() -> list[str]:
    global FILES
    if FILES is None:
        FILES = _files(template())
    return FILES


extra_name = st.text(st.characters(blacklist_characters="/\x00", blacklist_categories=("Cs",)),
                     min_size=1, max_size=10).filter(lambda s: s not in (".", ".."))
extra = st.tuples(st.integers(0, 10**6), extra_name,
                  st.sampled_from(["", ".png", ".jpg", ".tif", ".csv", ".PNG", "_laser.png", "_board.png"]),
                  st.sampled_from(["bytes", "link_bait", "link_tmp", "link_inside", "folder"]),
                  st.binary(max_size=64))


@FUZZ
@given(st.lists(st.integers(0, 10**6), max_size=4), st.lists(extra, max_size=3))
def test_missing_and_extra_files(missing: list[int], extras: list) -> None:
    """Files and folders deleted, files, folders and symbolic links (out and in) added."""
    files = template_files()
    with watched() as root:
        for i in missing:
            p = root / files[i % len(files)]
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            elif p.exists() or p.is_symlink():
                p.unlink()
        for i, stem, ext, kind, data in extras:
            folder = root / files[i % len(files)]
            folder = folder if folder.is_dir() else folder.parent
            if not folder.is_dir():
                continue
            p = folder / (stem + ext)
            if p.exists() or p.is_symlink() or len(p.name.encode()) > 200:
                continue
            if kind == "bytes":
                p.write_bytes(data)
            elif kind == "folder":
                p.mkdir()
            elif kind == "link_bait":
                p.symlink_to(_BAIT / "evil.png")
            elif kind == "link_tmp":
                p.symlink_to(Path("/tmp"))
            else:
                p.symlink_to(root / "calibration/camera/view_00.png")
        try:
            summary = check_capture(root)
        except CaptureError as exc:
            assert_named(exc)
            return
        assert set(summary["stages"]) == {"calibrate_camera", "calibrate_lasers", "calibrate_handeye",
                                          "scans"}


# --------------------------------------------------------------------------- truth.json's file names


truth_name = st.one_of(
    name, leaf,
    st.sampled_from(["truth/part.ply", "truth/out.ply", "truth/tmp", "truth/tmp/passwd", "truth",
                     "truth/../rig.yaml", "truth/a/../../../bait/evil.stl", "rig.yaml",
                     "truth/missing.parquet", "./truth/part.ply", "truth//part.ply"]),
)


@MORE
@given(st.lists(st.tuples(st.sampled_from(["plate", "gauge", "part", "../x"]),
                          st.sampled_from(TRUTH_FILE_KEYS), truth_name), max_size=4))
def test_truth_json_names(entries: list) -> None:
    """Names anywhere in truth.json's file keys (out of the capture, absolute, through symbolic
    links out, not strings): the check names truth.json, or the report's reader gets a path
    inside the capture and reads it; either both refuse or neither does."""
    scans: dict[str, dict] = {}
    for scan, key, v in entries:
        scans.setdefault(scan, {})[key] = v
    with watched() as root:
        (root / "truth").mkdir()
        (root / "truth/part.ply").write_text("ply\n")
        (root / "truth/out.ply").symlink_to(_BAIT / "evil.stl")
        (root / "truth/tmp").symlink_to(Path("/etc"))
        (root / "truth.json").write_text(json.dumps({"format": "crossline-truth/1", "scans": scans}))

        def read_named(p: Path) -> list[bytes]:
            """What the report does with each name: the path truth_file gives, then the file."""
            out = []
            for scan, entry in json.loads(p.read_text())["scans"].items():
                for key in entry:
                    f = truth_file(root, scan, entry, key)
                    assert f.resolve().is_relative_to(root.resolve()), f
                    if f.is_file():
                        out.append(f.read_bytes())
            return out

        read = assert_refused_or_read(root, root / "truth.json", (read_named,), (CaptureError,))
        try:
            open_capture(root)
            refused = False
        except CaptureError as exc:
            assert_named(exc, "truth.json")
            assert all(p.file == "truth.json" and p.message.startswith("'scans.")
                       for p in exc.problems), str(exc)
            refused = True
        assert refused == (not read)


def test_watch_sees_reads_outside() -> None:
    """The watcher itself: a read of the bait next to the capture is caught."""
    import pytest

    with pytest.raises(AssertionError, match="read outside the capture"):
        with watched():
            (_BAIT / "evil.png").read_bytes()

"""Captures as untrusted input, through the command line (issue 23.2): every stage that reads
a capture is run, in this process as ``crossline <command> ...`` (:func:`crossline.cli.main`),
on copies of the quick capture that hypothesis has broken at random: rig.yaml keys deleted or
set to values of any type and its bytes cut or changed; CSV cells, rows and columns of
``poses.csv`` and ``frames.csv`` changed, deleted, duplicated, swapped, renamed, reordered;
image bytes cut, changed or appended, images of another size, bit depth, channel count or
format; files and folders missing, extra files, folders and links; and names, links and
linked folders that lead out of the capture to a sentinel file beside it.

For every case: exit 0 with the artefact written and readable (and sane), or exit 2 with one
``crossline <command>: error: ...`` message that names a file of the capture; never exit 3
(a bug), never a traceback (on stderr or in the log), never an artefact, a side file or a
temporary ``.<name>.*.tmp`` left behind by a failed run, never a file written into the
capture, and never a file opened outside the capture (every ``open`` is watched through an
audit hook; the sentinel is a valid board image, so a read of it would otherwise pass).
Paths out of the capture must be refused, naming the row of poses.csv or the link.

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
=================================  ==================  ====================  ========

70 cases in all (48 random, 21 paths out, 1 case found once and kept), about 40 s of one
core (most of it the calibrations that pass). ``CROSSLINE_FUZZ_SCALE=N`` multiplies the
random and path-out cases (a longer hunt, off the suite: N = 4 for the camera and lasers, 8
for hand-eye, 30 for the others found the case below and nothing else).
The capture fuzzed is the quick capture of conftest.py without laser pose_02 and hand-eye
views 05-07 (a calibration that passes then decodes fewer images); the commands get the
rig's true calibrations from truth.json, triangulate the stripes of the unbroken capture.
The capture reader alone is fuzzed much harder (800 cases) in test_capture_fuzz.py.

Found: calibrate-handeye on arm poses that do not rotate (every row of poses.csv the same)
said "degenerate hand-eye motion: only 0 of 10 motion pairs rotate ..." without naming a
file; run_calibrate_handeye now names calibration/handeye/poses.csv (and calibration/handeye
when too few views show the board).
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
from hypothesis import HealthCheck, Phase, example, given, note, seed, settings
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
    from crossline.camera import Camera
    from crossline.cli import main
    from crossline.io.atomic import write_json
    from crossline.laser import LaserPlanes

    work = tmp_path_factory.mktemp("cli-fuzz")
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
    write_json(cal / "handeye.json", {"T_tool_cam": truth["T_tool_cam"], "method": "truth"})
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(["extract-stripes", str(base), "plate", "--out", str(cal / "stripes.parquet")])
    assert code == 0, err.getvalue()
    return Env(work, base, cal, (quick_capture.resolve(), base.resolve()))


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
    }[command]
    folders = {
        "check": ["calibration/camera", "calibration/handeye", "calibration/laser_B", "scans/gauge/frames"],
        "calibrate-camera": ["calibration/camera", "calibration"],
        "calibrate-lasers": ["calibration/laser_A", "calibration/laser_B"],
        "calibrate-handeye": ["calibration/handeye"],
        "extract-stripes": ["scans/plate/frames", "scans/plate"],
        "triangulate": ["scans/plate", "scans"],
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
    rig_paths = _key_paths(yaml.safe_load((env.base / "rig.yaml").read_text())) + RIG_EXTRA_PATHS

    def img_bytes(names):
        return st.tuples(st.just("img_bytes"), st.sampled_from(names), st.integers(0, 10**7), flips,
                         st.binary(max_size=24))

    def img_kind(names):
        return st.tuples(st.just("img_kind"), st.sampled_from(names), st.sampled_from(IMAGE_KINDS))

    def extra(dirs):
        return st.tuples(st.just("extra"), st.sampled_from(dirs), st.sampled_from(EXTRA_NAMES),
                         st.sampled_from(["bytes", "image", "folder", "link_in"]), st.binary(max_size=24))

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
    anywhere = st.one_of(
        st.tuples(st.just("rig_key"), st.sampled_from(rig_paths),
                  st.just("delete") | value.map(lambda v: ("set", v))),
        st.tuples(st.just("rig_bytes"), st.integers(0, 1200), flips, st.binary(max_size=24)),
        st.tuples(st.just("csv_cell"), st.sampled_from(TABLES), st.integers(0, 30), st.integers(0, 9), cell),
        st.tuples(st.just("csv_row"), st.sampled_from(TABLES),
                  st.sampled_from(["delete", "duplicate", "swap", "blank", "junk", "cut", "header_only",
                                   "empty", "no_header", "crlf", "bom", "latin1"]),
                  st.integers(0, 30), st.integers(0, 30)),
        csv_col(["drop", "rename", "extra", "reorder", "duplicate", "upper", "spaces"]),
        img_bytes(env.images), img_kind(env.images),
        st.tuples(st.just("missing"), st.sampled_from(env.files + env.dirs)),
        extra(env.dirs),
        escapes(env, command),
    )
    return st.tuples(st.lists(deep, min_size=1, max_size=2), st.lists(anywhere, max_size=1)).map(
        lambda t: t[0] + t[1])


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
    from crossline.cli import main

    case = Path(tempfile.mkdtemp(prefix="case-", dir=env.work)).resolve()
    try:
        root, out = case / "cap", case / "out"
        shutil.copytree(env.base, root, copy_function=os.link)
        out.mkdir()
        os.link(env.base / "calibration/handeye/pose_00.png", case / SENTINEL)  # a valid view
        if refusal is None:
            done = [d for d in (_apply(op, root, case) for op in ops) if d is not None]
        else:
            d, expected = _escape(ops[0], root, case)
            done = [d] if d is not None else []
            refusal[:] = expected
        note(f"corruptions: {done}")
        before = sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))
        argv, art = _argv(command, root, out, env.cal)
        err, records = io.StringIO(), _Records()
        logging.getLogger().addHandler(records)
        _OUTSIDE.clear()
        _WATCH.append((root, case, env.originals))
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                code = main(argv)
        finally:
            _WATCH.pop()
            logging.getLogger().removeHandler(records)
        err = err.getvalue()
        log = "\n".join(records.text)
        note(f"exit {code}: {err}")
        assert code in (0, 2), f"exit {code} (0 or 2 expected): {err}"
        assert "Traceback" not in err and "Traceback" not in log, err + log
        assert not _OUTSIDE, f"opened outside the capture: {sorted(set(_OUTSIDE))}"
        after = sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))
        assert after == before, "the command wrote into the capture"
        left = sorted(p.name for p in out.iterdir())
        if code == 0:
            assert art.is_file(), f"exit 0 without {art.name}"
            assert not [n for n in left if n.endswith(".tmp")], left
            _read_artefact(command, art)
        else:
            m = re.search(rf"^crossline {command}: error: (.*)", err, re.M | re.S)
            assert m, f"no error message: {err!r}"
            assert _names_a_file(m.group(1), root), f"the message names no file of the capture: {err}"
            assert not left, f"a failed run left {left}"
        if refusal is not None and done:
            assert code == 2, f"a path out of the capture was accepted: {done}"
            for text in refusal:
                assert text in err, (text, err)
    finally:
        shutil.rmtree(case, ignore_errors=True)
    assert _snapshot(env.base) == env.snapshot, "a case changed the base capture"
    return code, err


# --------------------------------------------------------------------------- the properties

_SCALE = float(os.environ.get("CROSSLINE_FUZZ_SCALE", "1"))
FUZZ = settings(derandomize=True, database=None, deadline=None, print_blob=False,
                phases=[Phase.explicit, Phase.generate],
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much])
CASES = {"check": (12, 4), "calibrate-camera": (6, 3), "calibrate-lasers": (4, 3),
         "calibrate-handeye": (6, 3), "extract-stripes": (10, 4), "triangulate": (10, 4)}


# cases the fuzz once found wrong, tried first on every run
EXAMPLES = {
    # every arm pose the same: "degenerate hand-eye motion: only 0 of 10 motion pairs rotate by
    # more than 1 deg" named no file (now: calibration/handeye/poses.csv, by run_calibrate_handeye)
    "calibrate-handeye": [[("csv_valid", "calibration/handeye/poses.csv", 0, ("x", "all same"))]],
}


def _n(command: str, which: int) -> int:
    return max(1, int(CASES[command][which] * _SCALE))


def _fuzz(command: str):
    """A test running ``command`` on randomly broken captures."""

    def test(env: Env) -> None:
        @seed(zlib.crc32(command.encode()))
        @settings(FUZZ, max_examples=_n(command, 0))
        @given(corruptions(env, command))
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

    def test(env: Env) -> None:
        @seed(zlib.crc32(f"{command} out".encode()))
        @settings(FUZZ, max_examples=_n(command, 1))
        @given(escapes(env, command))
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

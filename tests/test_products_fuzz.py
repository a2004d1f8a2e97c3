"""The stages' products as untrusted input, through the command line (issue 23.2): what a
user's disk or an interrupted copy can leave of a calibration JSON, a stripes or points
parquet, a fused cloud or the arm's draws, given to the commands that read it, as the
workflow's rules give it (workflow/rules/scan.smk, fuse.smk, report.smk, export.smk).
test_cli_fuzz.py breaks the captures; this module breaks the products and checks the same
contract with its runner (:func:`tests.test_cli_fuzz.run_checked`): exit 0 with the artefact
written and sane, or exit 2 with one ``crossline <command>: error: ...`` message that names
the broken file; never exit 3 (a bug), never a traceback, never a temporary or partial
artefact left behind, never a change to the capture.

The products are made once for the module from test_cli_fuzz.py's capture (the quick capture,
its true calibrations, the plate's stripes): the plate's points, and its cloud, fuse
statistics and arm draws as fuse.smk writes them; and, under other/, the gauge's points and
arm draws (its frames numbered as the plate's), which some cases put in the plate's place. Each
case breaks one or two of them in a copy (hard links; the broken file rewritten) and runs one
command:

==============================  ==========  =====================================================
product                         command     cases
==============================  ==========  =====================================================
calibration/camera.json         triangulate 6: cut, no K, K with text, K NaN, fx 0, image_size of 1
calibration/lasers.json         triangulate 8: cut, A a text, normal of 2, normal not unit, d inf,
                                            no plane B, B the plane of A (as it is, and as -n, -d)
calibration/handeye.json        triangulate 5: cut, 3x4, NaN, scaled (not rigid), mirrored
stripes/<scan>.parquet          triangulate 7: cut, no column u, u as text, NaN centres, no rows,
                                            rows out of frame order, metadata not an object
points/<scan>.parquet           fuse        9: cut, no x, no frame, x_cam NaN, no rows, metadata
                                            not an object, x as text, frame as text, the gauge's
calibrations, points, cloud,    report      5 runs, 2 faults each (measured, the faults named in
arm draws, side files                       the log): dist of 4 + fuse statistics of texts; no
                                            plane B + points' side file of texts; T mirrored +
                                            points' frame as text; hand-eye method a list + arm
                                            draws NaN; arm draws cut + points cut. 7 refusals: the
                                            cloud with NaN vertices, x read as float, its vertex
                                            count; the gauge's points, the gauge's arm draws, arm
                                            draws of half the frames, of frames not in frames.csv
<scan>.ply                      export-     2: cut, NaN vertices
                                cloud
==============================  ==========  =====================================================

49 explicit cases (no hypothesis: each kind of damage once, the same on every run), about 9 s
of one core (products made once included; the report's runs most of it, its Monte Carlo cut
to 2 draws on 2000 points as in test_cli_fuzz.py). Not covered: gather-stripes' chunks (its
reader is crossline/scan/stripes.py's), the certificate (it shares the report's calibration
check), a fused cloud of another scan (a PLY says nothing of its scan: only its frames are
checked, against the arm draws'), two laser planes parallel but apart (not one plane:
lasers.json's reader takes them).

Found (each fixed in the reader): triangulate exited 3 on a camera.json whose image_size was
one number, a lasers.json plane that was a text, a stripes file without a column or whose
metadata was a list; it wrote NaN points (exit 0) from a focal length of 0 or an infinite d,
and took a non-unit normal, a scaled or mirrored T_tool_cam, text or NaN centres and rows out
of frame order (labelled wrong). fuse exited 3 on NaN camera-frame coordinates ('SVD did not
converge') and on metadata that was a list, and fused a file without 'frame' as if every point
were of frame 0. The report exited 3 on a camera.json of 4 distortion coefficients, a mirrored
T, a hand-eye method that was a list, a lasers.json without the rig's plane B, a cloud with
NaN vertices or a property of another type, a cut arm-draws file and side files of texts; and
drew NaN arm draws. Then (the four cases left open): triangulate took a lasers.json whose
plane B was plane A's; fuse cast a points file's x or frame stored as text to numbers, and the
report its frames; the report measured the unfused points in place of a damaged cloud (only
its log naming the cloud), and took the gauge's points and arm draws for the plate's (each
scan's frames are numbered 0..23: only the points' metadata and the draws' flange positions
tell them apart).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from tests.test_cli_fuzz import FUSED, _argv, _fuse_argv, _snapshot, build_env, run_checked

OTHER = "gauge"  # the scan whose points and arm draws stand in for the plate's in some cases

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("products_fuzz")]

CALIBRATIONS = ("camera.json", "lasers.json", "handeye.json")


class Made:
    """The unbroken products: ``cal`` (calibrations and the plate's stripes, as
    test_cli_fuzz.py's ``_argv`` reads them), ``interim`` and ``processed`` as the workflow
    lays them out, beside the capture ``base``."""

    def __init__(self, work: Path, base: Path, products: Path):
        self.work, self.base, self.products = work, base, products
        self.snapshot = _snapshot(base)


@pytest.fixture(scope="module")
def made(quick_capture: Path, tmp_path_factory) -> Made:
    from crossline.cli import main

    env = build_env(quick_capture, tmp_path_factory.mktemp("products-fuzz"))
    products = env.work / "products"
    cal, points, processed = products / "cal", products / "interim" / "points", products / "processed"
    shutil.copytree(env.cal, cal)
    points.mkdir(parents=True)
    processed.mkdir()
    (products / "interim" / "calibration").mkdir()
    for name in CALIBRATIONS:
        os.link(cal / name, products / "interim" / "calibration" / name)
    scan = env.base / "scans" / FUSED
    argv, _ = _argv("triangulate", env.base, points, cal)
    argv[argv.index("--out") + 1] = str(points / f"{FUSED}.parquet")
    assert main(argv) == 0
    assert main([str(a) for a in _fuse_argv(
        points / f"{FUSED}.parquet", scan / "frames.csv", processed / f"{FUSED}.ply",
        processed / f"{FUSED}.fuse.json", cal / "handeye.json", arm=processed / f"{FUSED}.arm.npz")]) == 0
    (processed / f"{FUSED}.stl").unlink(missing_ok=True)
    # another scan's points and arm draws (gauge: its 24 frames numbered as plate's), beside them
    other = products / "other"
    other.mkdir()
    assert main(["extract-stripes", str(env.base), OTHER, "--out", str(other / "stripes.parquet")]) == 0
    argv, _ = _argv("triangulate", env.base, other, cal)
    argv[argv.index(FUSED)] = OTHER
    argv[argv.index("--stripes") + 1] = str(other / "stripes.parquet")
    argv[argv.index("--out") + 1] = str(other / f"{OTHER}.parquet")
    assert main(argv) == 0
    assert main([str(a) for a in _fuse_argv(
        other / f"{OTHER}.parquet", env.base / "scans" / OTHER / "frames.csv", other / f"{OTHER}.ply",
        other / f"{OTHER}.fuse.json", cal / "handeye.json", arm=other / f"{OTHER}.arm.npz")]) == 0
    return Made(env.work, env.base, products)


# --------------------------------------------------------------------------- breaking a file


def _write(p: Path, data: bytes | str) -> None:
    """New contents under a new inode: the case's files are hard links of the products."""
    p.unlink()
    p.write_bytes(data.encode() if isinstance(data, str) else data)


def cut(fraction: float) -> Callable[[Path], None]:
    def f(p: Path) -> None:
        data = p.read_bytes()
        _write(p, data[: int(len(data) * fraction)])
    return f


def edit_json(change: Callable[[dict], object]) -> Callable[[Path], None]:
    def f(p: Path) -> None:
        _write(p, json.dumps(change(json.loads(p.read_text()))))
    return f


def edit_table(change: Callable) -> Callable[[Path], None]:
    """A parquet rewritten by ``change(table)``, its crossline metadata kept."""
    def f(p: Path) -> None:
        import pyarrow.parquet as pq

        meta = pq.ParquetFile(p).metadata.metadata
        t = pq.read_table(p).replace_schema_metadata({b"crossline": meta[b"crossline"]})
        p.unlink()
        pq.write_table(change(t), p)
    return f


def column(name: str, values: Callable) -> Callable:
    """``change`` of :func:`edit_table`: column ``name`` replaced by ``values(column as numpy)``."""
    def change(t):
        import pyarrow as pa

        return t.set_column(t.schema.get_field_index(name), name, pa.array(values(t[name].to_numpy())))
    return change


def metadata(value: bytes) -> Callable:
    return lambda t: t.replace_schema_metadata({b"crossline": value})


def every(k: int, value: float) -> Callable:
    def values(a: np.ndarray) -> np.ndarray:
        a = a.astype(np.float64)
        a[::k] = value
        return a
    return values


def edit_npz(change: Callable[[dict], dict]) -> Callable[[Path], None]:
    def f(p: Path) -> None:
        with np.load(p) as z:
            arrays = change(dict(z))
        p.unlink()
        with open(p, "wb") as fh:
            np.savez(fh, **arrays)
    return f


def another(rel: str) -> Callable[[Path], None]:
    """The file replaced by the case's ``rel`` (another scan's product, under other/)."""
    def f(p: Path) -> None:
        root = next(q for q in p.parents if (q / "other").is_dir())
        _write(p, (root / rel).read_bytes())
    return f


def arm_frames(change: Callable[[dict], dict]) -> Callable[[Path], None]:
    """The arm draws' arrays of their frames (frames, origins, scaled) changed together."""
    return edit_npz(lambda z: {**z, **change({k: z[k] for k in ("frames", "origins", "scaled")})})


def edit_bytes(old: bytes, new: bytes) -> Callable[[Path], None]:
    def f(p: Path) -> None:
        data = p.read_bytes()
        assert old in data, old
        _write(p, data.replace(old, new, 1))
    return f


def ply_nan(p: Path) -> None:
    """Every tenth vertex of the cloud with a NaN x, every seventh an infinite normal."""
    from crossline.io.ply import _PLY_FIELDS

    data = p.read_bytes()
    start = data.index(b"end_header\n") + len(b"end_header\n")
    rows = np.frombuffer(data, dtype=_PLY_FIELDS, offset=start).copy()
    rows["x"][::10] = np.nan
    rows["nx"][::7] = np.inf
    _write(p, data[:start] + rows.tobytes())


def _K(d: dict, i: int, j: int, v) -> dict:
    K = [list(r) for r in d["K"]]
    K[i][j] = v
    return {**d, "K": K}


def _plane(data: dict, laser: str, **kv) -> dict:
    return {**data, laser: {**data[laser], **kv}}


def _T(d: dict, change: Callable[[np.ndarray], None]) -> dict:
    T = np.array(d["T_tool_cam"])
    change(T)
    return {**d, "T_tool_cam": T.tolist()}


def _scale(T: np.ndarray) -> None:
    T[:3, :3] *= 1.1


def _mirror(T: np.ndarray) -> None:
    T[:3, 0] *= -1


def _nan(T: np.ndarray) -> None:
    T[0, 3] = np.nan


C, L, H = (f"cal/{n}" for n in CALIBRATIONS)
S, P = "cal/stripes.parquet", f"interim/points/{FUSED}.parquet"
Y, A = f"processed/{FUSED}.ply", f"processed/{FUSED}.arm.npz"
FJ, PJ = f"processed/{FUSED}.fuse.json", f"interim/points/{FUSED}.json"
OP, OA = f"other/{OTHER}.parquet", f"other/{OTHER}.arm.npz"


def _turned(plane: dict, nudge: float) -> dict:
    """The same plane written as -n, -d (d moved by ``nudge`` mm)."""
    return {**plane, "normal": [-x for x in plane["normal"]], "d": -plane["d"] + nudge}

# (command, [(file, how it is broken), ...][, a text its refusal must hold]) by case name
CASES: dict[str, tuple] = {
    "camera cut": ("triangulate", [(C, cut(0.5))]),
    "camera without K": ("triangulate", [(C, edit_json(lambda d: {k: v for k, v in d.items() if k != "K"}))]),
    "camera K with text": ("triangulate", [(C, edit_json(lambda d: _K(d, 0, 2, "1536.0 px")))]),
    "camera K NaN": ("triangulate", [(C, edit_json(lambda d: _K(d, 1, 1, float("nan"))))]),
    "camera fx 0": ("triangulate", [(C, edit_json(lambda d: _K(d, 0, 0, 0.0)))], "'K'"),
    "camera image_size of 1": ("triangulate", [(C, edit_json(lambda d: {**d, "image_size": [3072]}))],
                               "'image_size'"),
    "lasers cut": ("triangulate", [(L, cut(0.5))]),
    "lasers A a text": ("triangulate", [(L, edit_json(lambda d: {**d, "A": "plane A"}))], "laser A"),
    "lasers normal of 2": ("triangulate", [(L, edit_json(
        lambda d: _plane(d, "A", normal=d["A"]["normal"][:2])))], "'normal'"),
    "lasers normal not unit": ("triangulate", [(L, edit_json(
        lambda d: _plane(d, "B", normal=[2 * x for x in d["B"]["normal"]])))], "'normal'"),
    "lasers d inf": ("triangulate", [(L, edit_json(lambda d: _plane(d, "A", d=float("inf"))))], "'d'"),
    "lasers without B": ("triangulate", [(L, edit_json(lambda d: {k: v for k, v in d.items() if k != "B"}))]),
    "lasers B the plane of A": ("triangulate", [(L, edit_json(lambda d: {**d, "B": d["A"]}))],
                                "laser B", "one plane"),
    "lasers B the plane of A turned": ("triangulate", [(L, edit_json(
        lambda d: {**d, "B": _turned(d["A"], 1e-9)}))], "laser B", "one plane"),
    "handeye cut": ("triangulate", [(H, cut(0.5))]),
    "handeye T 3x4": ("triangulate", [(H, edit_json(lambda d: {**d, "T_tool_cam": d["T_tool_cam"][:3]}))]),
    "handeye T NaN": ("triangulate", [(H, edit_json(lambda d: _T(d, _nan)))]),
    "handeye T scaled": ("triangulate", [(H, edit_json(lambda d: _T(d, _scale)))], "'T_tool_cam'"),
    "handeye T mirrored": ("triangulate", [(H, edit_json(lambda d: _T(d, _mirror)))], "'T_tool_cam'"),
    "stripes cut": ("triangulate", [(S, cut(0.9))]),
    "stripes without u": ("triangulate", [(S, edit_table(lambda t: t.drop_columns(["u"])))], "'u'"),
    "stripes u as text": ("triangulate", [(S, edit_table(column("u", lambda a: a.astype(str))))], "'u'"),
    "stripes NaN centres": ("triangulate", [(S, edit_table(column("v", every(50, np.nan))))], "'v'"),
    "stripes no rows": ("triangulate", [(S, edit_table(lambda t: t.slice(0, 0)))]),
    "stripes out of frame order": ("triangulate", [(S, edit_table(
        lambda t: t.take(np.arange(len(t))[::-1])))], "order"),
    "stripes metadata a list": ("triangulate", [(S, edit_table(metadata(b"[1]")))]),
    "points cut": ("fuse", [(P, cut(0.9))]),
    "points without x": ("fuse", [(P, edit_table(lambda t: t.drop_columns(["x"])))]),
    "points without frame": ("fuse", [(P, edit_table(lambda t: t.drop_columns(["frame"])))], "'frame'"),
    "points x_cam NaN": ("fuse", [(P, edit_table(column("x_cam", every(3, np.nan))))]),
    "points no rows": ("fuse", [(P, edit_table(lambda t: t.slice(0, 0)))]),
    "points metadata a list": ("fuse", [(P, edit_table(metadata(b"[1]")))]),
    "points x as text": ("fuse", [(P, edit_table(column("x", lambda a: a.astype(str))))], "'x'",
                         "expected numbers"),
    "points frame as text": ("fuse", [(P, edit_table(column("frame", lambda a: a.astype(str))))],
                             "'frame'", "expected whole numbers"),
    "points of another scan": ("fuse", [(P, another(OP))], f"scan {OTHER!r}"),
    "report: dist of 4, fuse statistics of texts": ("report", [
        (C, edit_json(lambda d: {**d, "dist": d["dist"][:4]})),
        (FJ, edit_json(lambda d: {k: "?" for k in d}))]),
    "report: no plane B, points' side file of texts": ("report", [
        (L, edit_json(lambda d: {k: v for k, v in d.items() if k != "B"})),
        (PJ, edit_json(lambda d: {k: "?" for k in d}))]),
    "report: T mirrored, points' frame as text": ("report", [
        (H, edit_json(lambda d: _T(d, _mirror))), (P, edit_table(column("frame", lambda a: a.astype(str))))]),
    "report: method a list, arm draws NaN": ("report", [
        (H, edit_json(lambda d: {**d, "method": ["refined"]})),
        (A, edit_npz(lambda z: {**z, "sigmas": np.full(6, np.nan)}))]),
    "report: arm draws cut, points cut": ("report", [(A, cut(0.5)), (P, cut(0.5))]),
    "report: NaN vertices": ("report", [(Y, ply_nan)], "plate.ply", "non-finite"),
    "report: x read as float": ("report", [(Y, edit_bytes(b"property double x\n", b"property float x\n"))],
                                "plate.ply", "cannot be read"),
    "report: vertex count": ("report", [(Y, edit_bytes(b"element vertex ", b"element vertex 1"))],
                             "plate.ply", "truncated"),
    "report: points of another scan": ("report", [(P, another(OP))], f"scan {OTHER!r}", "frames.csv"),
    "report: arm draws of another scan": ("report", [(A, another(OA))], "plate.arm.npz", "frames.csv",
                                          "flange positions"),
    "report: arm draws of half the frames": ("report", [(A, arm_frames(
        lambda z: {k: v[..., :12, :] if k == "scaled" else v[:12] for k, v in z.items()}))],
                                             "plate.arm.npz", "plate.ply", "no draws for frame"),
    "report: arm draws of frames not in the table": ("report", [(A, arm_frames(
        lambda z: {**z, "frames": z["frames"] + 100}))], "plate.arm.npz", "frames.csv", "not rows"),
    "export-cloud: cut": ("export-cloud", [(Y, cut(0.5))]),
    "export-cloud: NaN vertices": ("export-cloud", [(Y, ply_nan)]),
}


@pytest.mark.parametrize("name", CASES)
def test_broken_product(made: Made, name: str) -> None:
    """One or two products broken, the command that reads them run on the unbroken capture;
    where the case gives a text, it must be refused (exit 2) with a message holding it. A
    report that goes on without a broken product names it in its log."""
    command, breaks, *refusal = CASES[name]
    case = Path(tempfile.mkdtemp(prefix="case-", dir=made.work)).resolve()
    try:
        shutil.copytree(made.products, case, copy_function=os.link, dirs_exist_ok=True)
        broken = []
        for rel, how in breaks:
            how(case / rel)
            broken.append(case / rel)
            if rel.startswith("cal/") and rel.endswith(".json"):  # the report reads interim's copy
                dup = case / "interim" / "calibration" / Path(rel).name
                dup.unlink()
                os.link(case / rel, dup)
                broken.append(dup)
        out = case / "out"
        out.mkdir()
        if command == "export-cloud":
            argv, art = ["export-cloud", str(case / Y), "--out", str(out / "plate.e57")], out / "plate.e57"
        else:
            argv, art = _argv(command, made.base, out, case / "cal")
        code, err, log = run_checked(command, argv, art, out, lambda m: any(str(p) in m for p in broken))
        for text in refusal:
            assert code == 2 and text in err, f"refused with {text!r} expected: exit {code}, {err}"
        if command == "report" and code == 0:  # it goes on without them, saying which and why
            assert all(p.name in log for p in broken), f"a broken product not named: {log}"
    finally:
        shutil.rmtree(case, ignore_errors=True)
    assert _snapshot(made.base) == made.snapshot, "a case changed the capture"

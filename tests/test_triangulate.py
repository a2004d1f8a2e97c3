"""Triangulation: round trip through the camera model, frames, and the scan stages end to end."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from crossline.camera import Camera
from crossline.errors import StageError
from crossline.geometry import transform_from_pose
from crossline.laser import LaserPlane, LaserPlanes
from crossline.scan.stripes import gather_stripes, read_stripes_meta, run_extract_stripes
from crossline.scan.triangulate import read_points_meta, run_triangulate, to_base, triangulate
from crossline.sim import write_true_calibration
from tests import scan_synth as S


def test_round_trip_on_both_planes():
    cam = Camera(np.array([[5000.0, 0, 1530.0], [0, 5010.0, 1020.0], [0, 0, 1]]),
                 np.array([-0.12, 0.25, 3e-4, -2e-4, -0.1]), (3072, 2048))
    planes = LaserPlanes(LaserPlane(np.array([0.0, 0.8, 0.6]), -90.0),
                         LaserPlane(np.array([0.7, 0.0, 0.71]), -107.0))
    rng = np.random.default_rng(0)
    for laser in ("A", "B"):
        pl = planes[laser]
        # points on the plane in front of the camera
        xy = rng.uniform(-25, 25, (2000, 2))
        n = pl.normal
        z = -(pl.d + n[0] * xy[:, 0] + n[1] * xy[:, 1]) / n[2]
        p = np.c_[xy, z]
        assert np.all(z > 50)
        uv = cam.project(p)
        back = triangulate(cam, planes, uv, np.full(len(uv), laser))
        assert np.max(np.linalg.norm(back - p, axis=1)) <= 1e-6


def test_to_base_per_point():
    rng = np.random.default_rng(2)
    T = np.stack([S.T_base_tool(i, 5) for i in range(5)])
    p = rng.normal(size=(5, 3)) * 10
    out = to_base(p, T, S.T_TOOL_CAM)
    for i in range(5):
        exp = (T[i] @ S.T_TOOL_CAM @ np.r_[p[i], 1.0])[:3]
        np.testing.assert_allclose(out[i], exp, atol=1e-12)


@pytest.mark.parametrize("index", [[0, 0, 1, 1, 1, 3, 4, 4], [4, 0, 1, 4, 1, 0, 3, 1], [2], []])
def test_to_base_per_frame_index(index):
    """One pose per frame and an index (sorted or not, frames skipped) = the per-point poses."""
    rng = np.random.default_rng(3)
    T = np.stack([S.T_base_tool(i, 5) for i in range(5)])
    idx = np.array(index, dtype=np.int64)
    p = rng.normal(size=(idx.size, 3)) * 10
    out = to_base(p, T, S.T_TOOL_CAM, idx)
    assert out.shape == (idx.size, 3)
    np.testing.assert_allclose(out, to_base(p, T[idx], S.T_TOOL_CAM).reshape(-1, 3), atol=1e-12)
    with pytest.raises(ValueError, match="index"):  # one index per point, or nothing moves
        to_base(np.zeros((idx.size + 1, 3)), T, S.T_TOOL_CAM, idx)


# ----------------------------------------------------------------------------- stages


@pytest.fixture(scope="module")
def analytic(tmp_path_factory) -> tuple[Path, dict, tuple[Path, Path, Path]]:
    root = tmp_path_factory.mktemp("analytic")
    truth = S.make_capture(root / "cap", n_frames=21, seed=3)
    cal = S.write_calibration(root / "cal")
    return root / "cap", truth, cal


def centre_errors(stripes: pd.DataFrame, truth: dict) -> tuple[np.ndarray, np.ndarray]:
    """|v - nearest true stripe| of every unflagged centre, and the A-B separation there."""
    errs, seps = [], []
    for f, g in stripes.groupby("frame"):
        tv = truth["v"][int(f)]
        cols = g["u"].to_numpy().astype(int) - S.WINDOW[0]
        D = np.abs(np.stack([tv["A"][cols], tv["B"][cols]]) - g["v"].to_numpy())
        ok = (g["flags"].to_numpy() & 3) == 0
        errs.append(D.min(0)[ok])
        seps.append(np.abs(tv["A"][cols] - tv["B"][cols])[ok])
    return np.concatenate(errs), np.concatenate(seps)


@pytest.mark.parametrize("extractor", ["grey_centre", "steger"])
def test_stages_end_to_end_on_analytic_capture(analytic, tmp_path, extractor):
    cap, truth, (cj, lj, hj) = analytic
    st = tmp_path / "stripes.parquet"
    meta = run_extract_stripes(cap, "plate", st, extractor=extractor, sigma=1.5, threads=2)
    assert meta["counts"]["frames"] == 21 and meta["counts"]["centres"] > 21 * 500
    s = pd.read_parquet(st)
    # full-sensor pixels: the window offset is added
    assert s["u"].min() >= S.WINDOW[0] and s["v"].min() >= S.WINDOW[1]
    assert list(s.columns[:4]) == ["frame", "lasers", "u", "v"]
    e, sep = centre_errors(s, truth)
    away = sep > 15
    assert np.sqrt(np.mean(e[away] ** 2)) < 0.06
    pts = tmp_path / "points.parquet"
    pm = run_triangulate(cap, "plate", st, cj, lj, hj, pts)
    p = pd.read_parquet(pts)
    assert set(p["laser"]) == {"A", "B"}
    d = p[["x", "y", "z"]].to_numpy() @ S.PLATE[:3] + S.PLATE[3]
    assert np.sqrt(np.mean(d**2)) < 0.02  # mm; ~0.17 mm/px on this small rig
    side = json.loads((tmp_path / "points.json").read_text())
    assert side == read_points_meta(pts) == pm
    c = pm["counts"]
    assert c["centres_in"] == meta["counts"]["centres"]
    assert "labelled_by_order" not in c  # A and B frames there: the paper's rule, as before
    dropped = sum(c["dropped"].values())
    trimmed = sum(c["trimmed"].values())
    assert c["labelled"]["A"] + c["labelled"]["B"] + dropped == c["centres_in"]
    assert c["labelled"]["A"] + c["labelled"]["B"] == len(p) + trimmed
    # only <= 8 px at each trace end go: per A, B, AB period 2 + 2 + 8 ends (the crossing
    # cuts both AB stripes), at most 9 centres each
    assert 0 < c["trimmed"]["stripe_end"] <= 7 * 12 * 9
    # 7 periods of A, B, AB: the AB frames give two stripes
    # (points of A frames, trimmed alike, are the single-line reference)
    single = (p["lasers"] == "A").sum() / c["frames"]["A"]
    assert 1.25 < pm["points_per_frame"] / single < 1.34


@pytest.mark.parametrize("fit_across", [True, False])
def test_gaussian_stage_records_fit_across_and_is_on_the_lines(analytic, tmp_path, fit_across):
    cap, truth, _ = analytic
    st = tmp_path / "stripes.parquet"
    meta = run_extract_stripes(cap, "plate", st, extractor="gaussian", fit_across=fit_across, threads=2)
    assert meta["params"]["fit_across"] is fit_across and read_stripes_meta(st) == meta
    e, sep = centre_errors(pd.read_parquet(st), truth)
    assert np.sqrt(np.mean(e[sep > 15] ** 2)) < 0.06


def test_chunks_gather_to_the_unsplit_file(analytic, tmp_path):
    cap, _, _ = analytic
    whole = tmp_path / "whole.parquet"
    run_extract_stripes(cap, "plate", whole, threads=1)
    parts = []
    for i in range(3):
        parts.append(tmp_path / f"part{i}.parquet")
        run_extract_stripes(cap, "plate", parts[-1], chunk=(i, 3), threads=2)
    gathered = tmp_path / "gathered.parquet"
    gather_stripes(parts[::-1], gathered)  # any order of arguments
    assert whole.read_bytes() == gathered.read_bytes()
    pd.testing.assert_frame_equal(pd.read_parquet(whole), pd.read_parquet(gathered))
    assert read_stripes_meta(whole) == read_stripes_meta(gathered)
    with pytest.raises(StageError, match="missing or repeated"):
        gather_stripes([parts[0], parts[2]], tmp_path / "bad.parquet")
    assert not (tmp_path / "bad.parquet").exists()


def test_two_threads_give_the_same_bytes(analytic, tmp_path):
    cap, _, _ = analytic
    a, b = tmp_path / "a.parquet", tmp_path / "b.parquet"
    run_extract_stripes(cap, "plate", a, threads=1, decoder="opencv")
    run_extract_stripes(cap, "plate", b, threads=2, decoder="auto")
    assert a.read_bytes() == b.read_bytes()


def test_corrupt_frame_names_the_file(analytic, tmp_path):
    cap, _, _ = analytic
    bad = tmp_path / "cap"
    shutil.copytree(cap, bad)
    f = bad / "scans" / "plate" / "frames" / "000007.png"
    f.write_bytes(f.read_bytes()[:500])
    out = tmp_path / "s.parquet"
    with pytest.raises(StageError, match=r"scan plate: .*000007\.png"):
        run_extract_stripes(bad, "plate", out, threads=2)
    assert not out.exists() and not list(tmp_path.glob(".s.parquet*"))


def test_scan_without_stripes_is_an_error(tmp_path):
    S.make_capture(tmp_path / "cap", n_frames=4, states=["off"] * 4)
    out = tmp_path / "s.parquet"
    with pytest.raises(StageError, match="no stripe found in any of its 4 frames"):
        run_extract_stripes(tmp_path / "cap", "plate", out)
    assert not out.exists()


def test_no_a_frame_is_labelled_by_the_order_of_the_cross(tmp_path):
    """Without A frames the AB frames are labelled from the calibration; each label is right."""
    truth = S.make_capture(tmp_path / "cap", n_frames=6, states=["B", "AB"] * 3)
    cj, lj, hj = S.write_calibration(tmp_path / "cal")
    st = tmp_path / "s.parquet"
    run_extract_stripes(tmp_path / "cap", "plate", st)
    out = tmp_path / "p.parquet"
    meta = run_triangulate(tmp_path / "cap", "plate", st, cj, lj, hj, out)
    assert meta["counts"]["labelled_by_order"]["frames"] == 3
    p = pd.read_parquet(out)
    ab = p[p["lasers"] == "AB"]
    assert set(ab["laser"].astype(str)) == {"A", "B"}
    for laser, g in ab.groupby(ab["laser"].astype(str)):
        cols = g["u"].to_numpy().astype(int) - S.WINDOW[0]
        own = np.array([truth["v"][int(f)][laser][c] for f, c in zip(g["frame"], cols, strict=True)])
        assert np.abs(g["v"].to_numpy() - own).max() < 1.0, laser


def test_ab_frames_with_one_laser_plane_are_an_error_and_write_nothing(tmp_path):
    S.make_capture(tmp_path / "cap", n_frames=6, states=["B", "AB"] * 3)
    cj, lj, hj = S.write_calibration(tmp_path / "cal")
    st = tmp_path / "s.parquet"
    run_extract_stripes(tmp_path / "cap", "plate", st)
    planes = json.loads(Path(lj).read_text())
    # parallel planes 5 mm apart: no crossing line, no order (one plane is refused as it is read)
    planes["B"] = {**planes["A"], "d": planes["A"]["d"] + 5.0}
    Path(lj).write_text(json.dumps(planes))
    out = tmp_path / "p.parquet"
    with pytest.raises(StageError, match="scan plate: has AB frames but no A frame"):
        run_triangulate(tmp_path / "cap", "plate", st, cj, lj, hj, out)
    assert not out.exists()


def test_sixteen_bit_capture(tmp_path):
    truth = S.make_capture(tmp_path / "cap", n_frames=3, bit_depth=16)
    st = tmp_path / "s.parquet"
    run_extract_stripes(tmp_path / "cap", "plate", st)
    e, sep = centre_errors(pd.read_parquet(st), truth)
    assert np.sqrt(np.mean(e[sep > 15] ** 2)) < 0.06


# ----------------------------------------------------------------------------- simulator


@pytest.mark.slow
def test_quick_capture_end_to_end(quick_capture, tmp_path):
    """Stripes -> points on a rendered capture, scored with the TRUE calibration."""
    truth = json.loads((quick_capture / "truth.json").read_text())
    cal = write_true_calibration(quick_capture, tmp_path / "cal")
    scan = "plate" if "plate" in truth["scans"] else next(iter(truth["scans"]))
    st, pts = tmp_path / "s.parquet", tmp_path / "p.parquet"
    run_extract_stripes(quick_capture, scan, st, threads=2)
    run_triangulate(quick_capture, scan, st, *cal, pts)
    p = pd.read_parquet(pts)
    t = pd.read_parquet(quick_capture / truth["scans"][scan]["centrelines"])
    t = t[t["visible"]]
    # each labelled centre against the true centre line of its laser, frame and column
    m = p.assign(ui=np.round(p["u"]).astype(np.int64)).merge(
        t[["frame", "laser", "u", "v"]].rename(columns={"u": "ui", "v": "v_true"}),
        on=["frame", "laser", "ui"])
    e = (m["v"] - m["v_true"]).abs().groupby([m["frame"], m["ui"], m["laser"]]).min()
    assert len(e) > 0.95 * len(p)
    assert (e > 3).mean() < 0.001  # no stripe centre far from its true line: labels are right
    # speckle (contrast 0.15) limits a single column to ~0.14 px; end trimming removed the
    # cut-off cross-sections at stripe ends, which were off by up to 2 px
    assert np.sqrt(np.mean(e**2)) < 0.2
    # issue 4: <= 0.01 mm with the true calibration; the true arm poses too, so that only
    # extraction is scored (24 frames of 5.8 um/axis arm noise alone add ~0.01 mm)
    plane = np.array(truth["scans"][scan]["plane_base"])
    tp = pd.read_parquet(quick_capture / truth["scans"][scan]["poses"]).set_index("frame")
    sel = tp.loc[p["frame"].to_numpy()]
    T = transform_from_pose(sel[["x", "y", "z"]].to_numpy(), sel[["qw", "qx", "qy", "qz"]].to_numpy())
    pb = to_base(p[["x_cam", "y_cam", "z_cam"]].to_numpy(), T, np.array(truth["T_tool_cam"]))
    d = pb @ plane[:3] + plane[3]
    assert np.sqrt(np.mean(d**2)) <= 0.01


def _normal_errors(points: pd.DataFrame, centrelines: pd.DataFrame) -> np.ndarray:
    """Distance of each labelled centre to its laser's true centre line, normal to that line, px."""
    t = centrelines[centrelines["visible"]].sort_values(["frame", "laser", "u"])
    # the true line's slope dv/du at each column, from its neighbours in the same frame
    g = t.groupby(["frame", "laser"])
    slope = ((g["v"].shift(-1) - g["v"].shift(1)) / (g["u"].shift(-1) - g["u"].shift(1)))
    t = t.assign(slope=slope)
    t = t[(g["u"].shift(-1) - g["u"].shift(1)) == 2]  # both neighbours there: a clean slope
    m = points.assign(ui=np.round(points["u"]).astype(np.int64)).merge(
        t[["frame", "laser", "u", "v", "slope"]].rename(columns={"u": "ui", "v": "v_true"}),
        on=["frame", "laser", "ui"])
    return ((m["v"] - m["v_true"]) / np.sqrt(1.0 + m["slope"] ** 2)).to_numpy()


@pytest.mark.slow
@pytest.mark.parametrize("rig", ["quick_capture", "quick_capture_compact"])
def test_workflow_centre_lines_meet_the_centre_target(rig, request, tmp_path):
    """Issue 4: centres <= 0.05 px RMS from the true centre line, with the workflow's settings.

    Speckle limits one column to ~0.06 px normal to the line (bench_scan.py); the workflow's
    smoothing along the stripe (config.yaml points.smooth_px) is what brings it under 0.05 px.
    """
    import yaml

    capture = request.getfixturevalue(rig)
    cfg = yaml.safe_load((Path(__file__).resolve().parents[1] / "config.yaml").read_text())
    truth = json.loads((capture / "truth.json").read_text())
    cal = write_true_calibration(capture, tmp_path / "cal")
    st = tmp_path / "s.parquet"
    run_extract_stripes(capture, "plate", st, extractor=cfg["stripes"]["extractor"], threads=2)
    tl = pd.read_parquet(capture / truth["scans"]["plate"]["centrelines"])
    # away from the crossing: the other laser's true line more than 15 px off in the column
    other = tl[tl["visible"]].assign(laser=lambda d: d["laser"].map({"A": "B", "B": "A"}))
    rms = {}
    for win in (1, cfg["points"]["smooth_px"]):
        pts = tmp_path / f"p{win}.parquet"
        run_triangulate(capture, "plate", st, *cal, pts, smooth_px=win)
        p = pd.read_parquet(pts)
        near = p.assign(ui=np.round(p["u"]).astype(np.int64)).merge(
            other[["frame", "laser", "u", "v"]].rename(columns={"u": "ui", "v": "v_other"}),
            on=["frame", "laser", "ui"], how="left")
        away = p[~((near["v"] - near["v_other"]).abs() < 15.0).to_numpy()]
        e = _normal_errors(away, tl)
        assert e.size > 0.9 * len(away) and e.size > 5000
        rms[win] = float(np.sqrt(np.mean(e**2)))
    assert rms[cfg["points"]["smooth_px"]] <= 0.05, rms
    assert rms[cfg["points"]["smooth_px"]] < 0.9 * rms[1], rms  # the smoothing does the work


def test_near_vertical_stripe_is_labelled_and_triangulated(tmp_path):
    """Random rig 30 crosses a near-vertical stripe (laser A, 96 deg) with a near-horizontal
    one: A's centres are profiled along the image rows, and are linked, trimmed, smoothed
    and matched to their references down the rows. Before, every one of them was lost (no
    A point at all) and the gauge, seen by B's parallel stripes alone, measured 30 um high
    with the arm's reported poses. Here with the true calibration and poses: both lasers'
    points lie on the true faces, and the block's height is right."""
    from crossline.report.gauge_block import measure_gauge_block
    from crossline.report.scan_truth import surface_distances
    from tests.test_sheet_curvature import _true_capture

    cap, cal, truth = _true_capture(tmp_path, 30, ["gauge"])
    stripes = tmp_path / "gauge.stripes.parquet"
    run_extract_stripes(cap, "gauge", stripes, extractor="gaussian", threshold=0.10)
    pts = tmp_path / "gauge.parquet"
    meta = run_triangulate(cap, "gauge", stripes, *cal, pts, smooth_px=7)
    p = pd.read_parquet(pts)
    n = p.groupby("laser").size()
    assert n["A"] > 0.4 * n["B"], n.to_dict()
    assert (p.loc[p.laser == "A", "axis"] == 1).mean() > 0.95  # profiled along the rows
    assert meta["counts"]["dropped"]["unmatched"] < 0.02 * meta["counts"]["centres_in"]
    xyz = p[["x", "y", "z"]].to_numpy()
    g = truth["scans"]["gauge"]
    for laser in ("A", "B"):
        d = surface_distances(xyz[p.laser.to_numpy() == laser], g)
        assert d["gauge top"].size > 500 and d["gauge plate"].size > 500, laser
        for face in ("gauge top", "gauge plate"):
            assert abs(np.median(d[face])) < 0.002, (laser, face)
    up = np.asarray(g["plate_plane_base"][:3])
    res = measure_gauge_block(xyz, g["height"], up=up if up[2] > 0 else -up, frame=p.frame.to_numpy())
    assert res.normal_from == "frames"
    assert abs(res.figures()["mean_mm"] - g["height"]) < 0.002

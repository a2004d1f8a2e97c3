"""The fuse stage: outlier removal and counts, per-laser voxels, oriented normals, byte-stable files."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import open3d as o3d
import pandas as pd
import pytest

from crossline.errors import StageError
from crossline.fuse import (
    camera_centres,
    fuse_cloud,
    read_ply,
    run_fuse,
    voxel_down_sample,
)
from crossline.geometry import invert_transform, make_transform, rotvec_to_matrix, transform_points
from crossline.io.atomic import write_parquet
from crossline.io.capture import CaptureError
from tests.test_report_synthetic import scan_points, scene


@pytest.fixture(scope="module")
def plate_scan():
    """A small synthetic cross-line scan of a plate, in an arbitrary base pose, with noise."""
    T = make_transform(rotvec_to_matrix([0.1, -0.2, 0.7]), [250.0, -80.0, 40.0])
    df, Ts, _ = scan_points(scene("plane")[0], frames=45, rays=200, noise=0.003, seed=1,
                                 T_scene=T)
    return df, Ts, T


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_camera_centres_recovered_exactly():
    rng = np.random.default_rng(0)
    frames, pc, pb, centres = [], [], [], {}
    for f in (3, 4, 7, 8):
        T = make_transform(rotvec_to_matrix(rng.normal(size=3)), rng.uniform(-200, 200, 3))
        if f == 7:  # collinear points: this frame borrows its neighbour's centre
            p = np.outer(rng.uniform(-10, 10, 50), [1.0, 0.5, 0.2]) + np.array([0, 0, 150.0])
        else:
            p = rng.uniform([-20, -20, 120], [20, 20, 180], (50, 3))
        frames.append(np.full(50, f))
        pc.append(p)
        pb.append(transform_points(T, p))
        centres[f] = T[:3, 3]
    fr, c = camera_centres(np.concatenate(frames), np.vstack(pc), np.vstack(pb))
    assert fr.tolist() == [3, 4, 7, 8]
    for i, f in enumerate(fr):
        want = centres[8] if f == 7 else centres[f]
        assert np.linalg.norm(c[i] - want) < 1e-8


def test_voxels_keep_lasers_apart():
    p = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [0.2, 0.2, 0.2], [1.5, 0.1, 0.1]])
    lab = np.array([1, 1, 2, 1], dtype=np.uint8)
    fr = np.array([5, 3, 4, 9])
    vp, vl, vf = voxel_down_sample(p, lab, fr, 1.0)
    # voxel (0,0,0) holds two A points and one B point: two averaged points, never mixed
    assert vl.tolist() == [1, 1, 2]
    assert np.allclose(vp[0], [0.2, 0.1, 0.1]) and vf[0] == 3
    assert np.allclose(vp[1], [1.5, 0.1, 0.1]) and vf[1] == 9
    assert np.allclose(vp[2], [0.2, 0.2, 0.2]) and vf[2] == 4


def test_outliers_removed_and_counted(plate_scan):
    df, _, T = plate_scan
    rng = np.random.default_rng(2)
    n_out = 40
    # isolated points 8-15 mm off the plate (the stripes of this small scan lie ~1 mm apart)
    base = df[["x", "y", "z"]].to_numpy()[rng.choice(len(df), n_out, replace=False)]
    far = base + T[:3, 2] * rng.uniform(8, 15, n_out)[:, None]
    pts = np.vstack([df[["x", "y", "z"]].to_numpy(), far])
    lab = np.concatenate([df["laser"].to_numpy(), np.full(n_out, "A")])
    fr = np.concatenate([df["frame"].to_numpy(), np.zeros(n_out, int)])
    c = fuse_cloud(pts, lab, fr, neighbours=20, std_ratio=3.0)
    s = c.stats
    assert s["n_input"] == len(pts) == s["n_outliers"] + s["n_after_outlier_removal"]
    assert s["n_output"] == len(c.points) == s["n_after_outlier_removal"]
    # every planted outlier is gone, and almost nothing else
    d = np.abs((c.points - T[:3, 3]) @ T[:3, 2])
    assert d.max() < 0.05
    assert s["n_outliers"] - n_out < 0.01 * len(df)
    assert s["by_laser_input"]["A"] + s["by_laser_input"]["B"] == len(pts)


def test_outliers_removed_in_place_where_the_columns_are_handed_over(plate_scan):
    # run_fuse hands its columns over: the kept points are moved to the front of the same
    # arrays (a long scan's points not held twice), with the cloud fuse_cloud gives
    from crossline.fuse.cloud import _compact, fuse_columns

    df, _, T = plate_scan
    rng = np.random.default_rng(5)
    far = df[["x", "y", "z"]].to_numpy()[:30] + T[:3, 2] * 10.0
    pts = np.vstack([far[:15], df[["x", "y", "z"]].to_numpy(), far[15:]])
    lab = np.r_[np.ones(15), np.where(df["laser"] == "A", 1, 2), np.full(15, 2)].astype(np.uint8)
    fr = np.r_[np.zeros(15), df["frame"].to_numpy(), np.zeros(15)].astype(np.int64)
    ref = fuse_cloud(pts, lab, fr, neighbours=20, std_ratio=3.0)
    held = pts.copy()
    c = fuse_columns({"xyz": held, "laser": lab.copy(), "frame": fr.copy()}, neighbours=20,
                     std_ratio=3.0)
    assert ref.stats["n_outliers"] >= 30
    assert np.array_equal(c.points, ref.points) and np.shares_memory(c.points, held)
    assert np.array_equal(c.laser, ref.laser) and np.array_equal(c.frame, ref.frame)
    a = rng.standard_normal((1001, 3))
    keep = rng.random(1001) < 0.7
    assert np.array_equal(_compact(a.copy(), keep, block=64), a[keep])


def test_normals_face_the_camera(plate_scan):
    df, Ts, T = plate_scan
    c = fuse_cloud(df[["x", "y", "z"]].to_numpy(), df["laser"].to_numpy(), df["frame"].to_numpy(),
                   df[["x_cam", "y_cam", "z_cam"]].to_numpy(), normal_radius_mm=0.8)
    assert c.stats["normals_oriented_to"] == "camera"
    cam = Ts[c.frame, :3, 3]
    assert (np.sum(c.normals * (cam - c.points), axis=1) > 0).all()
    # the plate's normal, +z of the scene (the camera looks down on it)
    assert np.median(c.normals @ T[:3, 2]) > 0.999


def test_run_fuse_files_are_deterministic(plate_scan, tmp_path):
    df, _, _ = plate_scan
    pq = tmp_path / "plate.parquet"
    write_parquet(pq, df)
    a = run_fuse(pq, tmp_path / "a.ply", stats=tmp_path / "a.json", mesh="ball_pivoting",
                 mesh_out=tmp_path / "a.stl")
    run_fuse(pq, tmp_path / "b.ply", stats=tmp_path / "b.json", mesh="ball_pivoting",
             mesh_out=tmp_path / "b.stl")
    assert _sha(tmp_path / "a.ply") == _sha(tmp_path / "b.ply")
    assert _sha(tmp_path / "a.stl") == _sha(tmp_path / "b.stl")
    assert (tmp_path / "a.json").read_text() == (tmp_path / "b.json").read_text()
    # nothing half-written left beside the outputs
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["plate.parquet", "a.ply", "a.json", "a.stl", "b.ply", "b.json", "b.stl"])
    # the PLY: float64 coordinates, exact; laser and frame kept; Open3D reads it too
    r = read_ply(tmp_path / "a.ply")
    assert np.array_equal(r["points"], a.points)
    assert np.array_equal(r["laser"], a.laser) and np.array_equal(r["frame"], a.frame)
    given = set(map(tuple, df[["x", "y", "z"]].to_numpy()))
    assert all(tuple(q) in given for q in a.points)  # every output point is an input, bit for bit
    pcd = o3d.io.read_point_cloud(str(tmp_path / "a.ply"))
    assert len(pcd.points) == len(a.points) and pcd.has_normals()
    assert np.allclose(np.asarray(pcd.points), a.points, atol=0, rtol=0)
    stats = json.loads((tmp_path / "a.json").read_text())
    assert stats["n_output"] == len(a.points) and stats["mesh_triangles"] > 1000
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "a.stl"))
    assert len(mesh.triangles) == stats["mesh_triangles"]


@pytest.mark.slow
def test_run_fuse_voxels_and_poisson(plate_scan, tmp_path):
    df, _, T = plate_scan
    pq = tmp_path / "plate.parquet"
    write_parquet(pq, df)
    c = run_fuse(pq, tmp_path / "v.ply", voxel_mm=0.5, mesh="poisson", mesh_out=tmp_path / "v.stl",
                 threads=2)
    run_fuse(pq, tmp_path / "w.ply", voxel_mm=0.5, mesh="poisson", mesh_out=tmp_path / "w.stl",
             threads=2)
    assert _sha(tmp_path / "v.stl") == _sha(tmp_path / "w.stl")
    assert 0 < c.stats["n_output"] < c.stats["n_after_outlier_removal"]
    assert set(np.unique(c.laser)) == {1, 2}
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "v.stl"))
    V = np.asarray(mesh.vertices)
    # the Poisson surface of a plate stays on the plate where it has support (it smooths
    # 0.5 mm voxels over stripes ~1 mm apart, and curls a little at the border)
    dev = np.abs((V - T[:3, 3]) @ T[:3, 2])
    assert np.median(dev) < 0.03 and np.percentile(dev, 90) < 0.2


def test_run_fuse_errors_name_the_problem(tmp_path):
    with pytest.raises(StageError, match="not found"):
        run_fuse(tmp_path / "none.parquet", tmp_path / "x.ply")
    pq = tmp_path / "bad.parquet"
    write_parquet(pq, pd.DataFrame({"x": [1.0], "y": [2.0]}))
    with pytest.raises(StageError, match="missing column"):
        run_fuse(pq, tmp_path / "x.ply")
    with pytest.raises(StageError, match="mesh-out"):
        run_fuse(pq, tmp_path / "x.ply", mesh="poisson")
    assert not (tmp_path / "x.ply").exists()


def test_points_in_camera_and_base_agree(plate_scan):
    # the synthetic scan itself: base = T_base_cam · cam, frame by frame (guards the fixtures)
    df, Ts, _ = plate_scan
    f = df["frame"].to_numpy()
    pc = df[["x_cam", "y_cam", "z_cam"]].to_numpy()
    pb = df[["x", "y", "z"]].to_numpy()
    back = np.einsum("nij,nj->ni", invert_transform(Ts)[f, :3, :3], pb) + invert_transform(Ts)[f, :3, 3]
    assert np.abs(back - pc).max() < 1e-9


# ----------------------------------------------------------------------------- pose refinement


def _posed_plate(root, scale: float = 1.0):
    """A plate scan whose reported arm poses carry known errors (``scale`` x the paper arm's),
    as the stage's files in ``root``."""
    from crossline.geometry import matrix_to_quat
    from tests.test_refine import PRIOR, Scan, X, arm_errors, reported

    s = Scan("plane", frames=60, rays=1200)
    e = arm_errors(len(s.T), PRIOR, seed=8, scale=scale)
    p, _ = reported(s.df, s.T, e)
    df = s.df.copy()
    df[["x", "y", "z"]] = p
    write_parquet(root / "plate.parquet", df)
    # frames.csv: the REPORTED flange poses (what the arm says) and the frame times
    Tt = s.T @ invert_transform(X)
    Rt = Tt[:, :3, :3]
    dth = np.einsum("fji,fj->fi", Rt, e[:, :3])
    Trep = make_transform(Rt @ rotvec_to_matrix(dth), Tt[:, :3, 3] + e[:, 3:])
    q = matrix_to_quat(Trep[:, :3, :3])
    states = np.array(["A", "B", "AB"])[np.arange(len(s.T)) % 3]
    pd.DataFrame({"frame": np.arange(len(s.T)), "time_s": s.times, "lasers": states,
                  "x": Trep[:, 0, 3], "y": Trep[:, 1, 3], "z": Trep[:, 2, 3],
                  "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3]}).to_csv(
        root / "frames.csv", index=False, float_format="%.10f")
    return root


@pytest.fixture(scope="module")
def posed_plate(tmp_path_factory):
    """A plate scan whose reported arm poses carry the paper arm's errors."""
    return _posed_plate(tmp_path_factory.mktemp("posed"))


def _flatness(c) -> float:
    """RMS of a cloud's points about their own plane z = a + b x + c y (mm)."""
    A = np.column_stack([np.ones(len(c.points)), c.points[:, :2]])
    z = c.points[:, 2]
    return float(np.sqrt(np.mean((z - A @ np.linalg.lstsq(A, z, rcond=None)[0]) ** 2)))


def test_run_fuse_refines_the_poses(posed_plate, tmp_path):
    pq, frames = posed_plate / "plate.parquet", posed_plate / "frames.csv"
    plain = run_fuse(pq, tmp_path / "plain.ply", stats=tmp_path / "plain.json")
    a = run_fuse(pq, tmp_path / "a.ply", stats=tmp_path / "a.json", refine_poses=True, frames=frames)
    run_fuse(pq, tmp_path / "b.ply", stats=tmp_path / "b.json", refine_poses=True, frames=frames)
    assert _sha(tmp_path / "a.ply") == _sha(tmp_path / "b.ply")
    assert (tmp_path / "a.json").read_text() == (tmp_path / "b.json").read_text()
    # the plate z = 0 is flat again: residuals to its own plane from ~4 µm to under 1 µm
    assert _flatness(plain) > 0.003 and _flatness(a) < 0.25 * _flatness(plain)
    # the PLY is the same format, every point keeps its laser and frame
    r = read_ply(tmp_path / "a.ply")
    assert len(r["points"]) == len(a.points) and set(r) == set(read_ply(tmp_path / "plain.ply"))
    assert np.array_equal(np.unique(r["frame"]), np.unique(plain.frame))
    st = json.loads((tmp_path / "a.json").read_text())
    ref = st["refine"]
    assert st["parameters"]["refine_poses"] is True and "refine" not in json.loads(
        (tmp_path / "plain.json").read_text())
    assert ref["prior"]["time_correlated"] and ref["prior"]["rotation_centre"].startswith("flange")
    assert ref["crossings"] > 100 and ref["gap_rms_after_mm"] < ref["gap_rms_before_mm"] / 5
    pf = ref["per_frame"]
    assert pf["frame"] == list(range(60)) and np.shape(pf["rotation_rad"]) == (60, 3)
    assert len(pf["correction_rms_mm"]) == 60 and max(pf["correction_rms_mm"]) < 0.05
    assert ref["centres_not_crossing"] == 0  # no cut lengths in these points: every centre
    assert st["parameters"]["crossing_max_width_ratio"] == 2.0


def test_run_fuse_draws_the_arm_error_it_leaves(posed_plate, tmp_path):
    """With --arm-draws-out, fuse writes draws of every frame's remaining pose error: the
    refinement's posterior (narrower than the prior along what the plate's crossings see: the
    height and the two tilts), or without refinement the arm's prior itself; reproducibly."""
    from crossline.io.arm_draws import read_arm_draws
    from tests.test_refine import PRIOR

    pq, frames = posed_plate / "plate.parquet", posed_plate / "frames.csv"
    for k in ("a", "b"):
        run_fuse(pq, tmp_path / f"{k}.ply", refine_poses=True, frames=frames, arm_draws=48,
                 arm_draws_out=tmp_path / f"{k}.npz")
    assert _sha(tmp_path / "a.npz") == _sha(tmp_path / "b.npz")
    post = read_arm_draws(tmp_path / "a.npz")
    table = pd.read_csv(frames)
    assert post.kind == "posterior" and post.draws.shape == (48, 60, 6)
    assert np.array_equal(post.frames, np.arange(60))
    assert np.allclose(post.origins, table[["x", "y", "z"]].to_numpy())  # the flange's
    sd = post.draws.std(axis=(0, 1)) / PRIOR.sigmas()
    # frame against frame (each draw's error common to all frames taken out: that moves the
    # whole plate rigidly and nothing sees it) a plate z = 0 sees the height (0.11 of the
    # prior's sigma here) and the tilts about x, y (0.41), not its in-plane shifts and turn
    # (0.74-0.81, the prior's own spread between frames); those stay at the prior (0.96-1.08)
    rel = (post.draws - post.draws.mean(axis=1, keepdims=True)).std(axis=(0, 1)) / PRIOR.sigmas()
    assert rel[5] < 0.2 and rel[:2].max() < 0.6 and rel[2:5].min() > 0.65
    assert np.all((sd[2:5] > 0.8) & (sd[2:5] < 1.2))
    run_fuse(pq, tmp_path / "c.ply", frames=frames, arm_draws=48, arm_draws_out=tmp_path / "c.npz",
             arm_precision_mm=0.04)
    prior = read_arm_draws(tmp_path / "c.npz")
    assert prior.kind == "prior" and prior.draws.shape == (48, 60, 6)
    assert np.allclose(prior.draws.std(axis=(0, 1)) / (2 * PRIOR.sigmas()), 1.0, atol=0.15)
    run_fuse(pq, tmp_path / "d.ply", arm_draws=0, arm_draws_out=tmp_path / "d.npz")
    assert read_arm_draws(tmp_path / "d.npz").draws.shape[0] == 0
    with pytest.raises(StageError, match="arm_draws=-1"):
        run_fuse(pq, tmp_path / "x.ply", arm_draws=-1, arm_draws_out=tmp_path / "x.npz")


def _handeye_file(path, sigma_mm: float, sigma_rad: float, views: int = 8) -> None:
    """A handeye.json with the refinement's estimate of the arm's noise, as calibrate-handeye
    writes it."""
    from tests.test_refine import X

    noise = {"arm_sigma_mm": sigma_mm, "arm_sigma_rad": sigma_rad, "image_sigma_px": 0.01}
    path.write_text(json.dumps({"T_tool_cam": X.tolist(), "method": "refined",
                                "board_poses": [np.eye(4).tolist()] * views,
                                "methods": {"refined": {"noise_model": noise}}}))


def test_run_fuse_takes_the_arm_prior_from_the_hand_eye_views(tmp_path):
    """An arm 10x noisier than the stated 0.02 mm: with arm_precision_mm auto the prior is the
    noise the hand-eye views measured, and the refinement corrects what the tight prior held."""
    from tests.test_refine import PRIOR

    root = _posed_plate(tmp_path / "noisy", scale=10.0)
    pq, frames = root / "plate.parquet", root / "frames.csv"
    he = tmp_path / "handeye.json"
    _handeye_file(he, 10 * PRIOR.sigma_mm, 10 * PRIOR.sigma_rad)
    stated = run_fuse(pq, tmp_path / "s.ply", refine_poses=True, frames=frames, arm_precision_mm=0.02,
                      handeye=he)
    auto = run_fuse(pq, tmp_path / "a.ply", refine_poses=True, frames=frames, arm_precision_mm="auto",
                    handeye=he)
    plain = run_fuse(pq, tmp_path / "p.ply")
    assert auto.stats["arm_prior"]["source"] == "hand-eye calibration (8 views)"
    assert auto.stats["arm_prior"]["sigma_mm"] == pytest.approx(10 * PRIOR.sigma_mm)
    assert auto.stats["arm_prior"]["precision_mm"] == pytest.approx(0.2)
    assert stated.stats["arm_prior"]["source"] == "stated (arm_precision_mm)"
    assert stated.stats["arm_prior"]["handeye_ratio"] == pytest.approx(10.0)  # the report's warning
    assert _flatness(auto) < 0.5 * _flatness(stated) < 0.5 * _flatness(plain)
    # a rotation estimate below the position's over one arm link is raised to it
    _handeye_file(he, 10 * PRIOR.sigma_mm, 0.0001 * PRIOR.sigma_rad)
    low = run_fuse(pq, tmp_path / "l.ply", refine_poses=True, frames=frames, arm_precision_mm="auto",
                   handeye=he)
    assert low.stats["arm_prior"]["sigma_rad"] == pytest.approx(10 * PRIOR.sigma_mm / 300.0)


def test_run_fuse_auto_prior_needs_the_hand_eye_estimate(posed_plate, tmp_path):
    pq, frames = posed_plate / "plate.parquet", posed_plate / "frames.csv"
    with pytest.raises(StageError, match=r"give its handeye\.json \(--handeye\)"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, frames=frames, arm_precision_mm="auto")
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"T_tool_cam": np.eye(4).tolist(), "method": "park"}))
    with pytest.raises(StageError, match=r"old\.json: holds no estimate of the arm's noise"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, frames=frames, arm_precision_mm="auto",
                 handeye=old)
    with pytest.raises(StageError, match=r"missing\.json: cannot read the hand-eye calibration"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, frames=frames, arm_precision_mm="auto",
                 handeye=tmp_path / "missing.json")


def test_run_fuse_keeps_long_cut_centres_out_of_the_crossings(posed_plate, tmp_path):
    df = pd.read_parquet(posed_plate / "plate.parquet")
    long_cut = np.arange(len(df)) % 10 == 0
    df["width"] = np.where(long_cut, 30.0, 6.0)  # px along the column; the median cut is 6
    pq = tmp_path / "plate.parquet"
    write_parquet(pq, df)
    frames = posed_plate / "frames.csv"
    a = run_fuse(pq, tmp_path / "a.ply", refine_poses=True, frames=frames)
    assert a.stats["refine"]["centres_not_crossing"] == long_cut.sum()
    b = run_fuse(pq, tmp_path / "b.ply", refine_poses=True, frames=frames, crossing_max_width_ratio=0)
    assert b.stats["refine"]["centres_not_crossing"] == 0
    # the excluded centres are still points of the cloud, moved with their frames
    assert len(a.points) == len(b.points)


def test_run_fuse_refinement_needs_what_it_names(posed_plate, tmp_path):
    pq = posed_plate / "plate.parquet"
    df = pd.read_parquet(pq)
    bad = tmp_path / "frames.csv"
    pd.read_csv(posed_plate / "frames.csv").iloc[:-5].to_csv(bad, index=False)
    # the table is named, with the frames it lacks
    with pytest.raises(StageError, match=r"frames\.csv: frame\(s\) \[55, 56, 57, 58, 59\] of plate"
                       r"\.parquet \(5 in all\) are not rows of this frames table"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, frames=bad)
    nocam = tmp_path / "nocam.parquet"
    write_parquet(nocam, df.drop(columns=["x_cam", "y_cam", "z_cam"]))
    with pytest.raises(StageError, match="camera frame"):
        run_fuse(nocam, tmp_path / "x.ply", refine_poses=True)
    with pytest.raises(StageError, match="arm_precision_mm"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, arm_precision_mm=0.0)
    with pytest.raises(StageError, match=r"crossing_min_angle_deg=90 \(0\.\.90\)"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, crossing_min_angle_deg=90)
    with pytest.raises(StageError, match=r"crossing_half_mm=0 \(> 0\)"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, crossing_half_mm=0)
    with pytest.raises(StageError, match=r"crossing_max_width_ratio=-1 \(>= 0, 0 = off\)"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, crossing_max_width_ratio=-1)
    with pytest.raises(StageError, match="frames table not found"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, frames=tmp_path / "none.csv")
    # a faulty frames table is read by the capture's own parser: every faulty row named
    rows = pd.read_csv(posed_plate / "frames.csv")
    rows["time_s"] = rows["time_s"].astype(object)
    rows.loc[2, "time_s"] = "soon"
    rows.loc[5, "qw"] = 3.0
    rows.to_csv(bad, index=False)
    with pytest.raises(CaptureError, match=r"(?s)line 4: 'time_s' = 'soon' is not a number.*"
                                           r"line 7: quaternion .* has length"):
        run_fuse(pq, tmp_path / "x.ply", refine_poses=True, frames=bad)
    assert not (tmp_path / "x.ply").exists()
    # without the frames table it still runs: independent per-frame prior, camera centres
    c = run_fuse(pq, tmp_path / "y.ply", refine_poses=True)
    assert c.stats["refine"]["prior"]["time_correlated"] is False

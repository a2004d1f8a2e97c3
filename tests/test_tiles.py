"""Slab-by-slab neighbourhood work gives the whole cloud's answer: Open3D's outlier test,
normals, camera centres from chunked moments."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from crossline.fuse import FrameMoments, camera_centres, estimate_normals, read_points_columns
from crossline.geometry import make_transform, rotvec_to_matrix, transform_points
from crossline.io.atomic import write_parquet
from crossline.tiles import slabs, statistical_inliers


def _wavy_cloud(n: int, seed: int = 1) -> np.ndarray:
    """Dense points on a wavy strip 200 x 60 mm, isolated points around it, some duplicates."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 200, n), rng.uniform(0, 60, n)
    p = np.column_stack([u, v, 0.5 * np.sin(u / 7) + rng.normal(0, 0.01, n)])
    return np.vstack([p, rng.uniform([0, 0, -5], [200, 60, 5], (300, 3)), p[:50]])


def test_slabs_cover_every_point_once_with_its_halo():
    p = _wavy_cloud(20_000)
    cores = []
    for s in slabs(p, halo=0.7, target=3_000):
        cores.append(s.core)
        assert np.array_equal(s.reach[s.start:s.stop], s.core)
        x = p[:, s.axis]
        lo, hi = x[s.core].min(), x[s.core].max()
        near = np.flatnonzero((x >= lo - 0.7) & (x <= hi + 0.7))
        assert set(near) <= set(s.reach.tolist())  # every point within the halo is in reach
    allc = np.concatenate(cores)
    assert len(allc) == len(p) and len(np.unique(allc)) == len(p)
    one = list(slabs(p, halo=0.7, target=len(p)))  # a small cloud: one slab, its own order
    assert len(one) == 1 and np.array_equal(one[0].core, np.arange(len(p)))


def test_outliers_by_slabs_are_open3ds():
    p = _wavy_cloud(60_000)
    for k in (20, 8):
        _, ind = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).remove_statistical_outlier(
            nb_neighbors=k, std_ratio=3.0)
        want = np.zeros(len(p), bool)
        want[np.asarray(ind)] = True
        assert 200 < (~want).sum() < 400  # most of the 300 planted isolated points
        for target in (len(p), 7_000):  # one slab, and slabs whose halo misses the outliers' k-th
            got = statistical_inliers(p, k, 3.0, halo=0.3, target=target)
            assert np.array_equal(got, want), (k, target, int((got != want).sum()))


def test_normals_by_slabs_equal_the_whole_clouds(monkeypatch):
    p = _wavy_cloud(30_000)[:30_000]
    whole, deg = estimate_normals(p, 0.8)
    import crossline.fuse.cloud as fz
    monkeypatch.setattr(fz, "slabs", lambda pts, halo: slabs(pts, halo, target=4_000))
    cut, deg2 = fz.estimate_normals(p, 0.8)
    assert np.array_equal(deg, deg2)
    assert np.abs(np.abs(np.sum(whole * cut, axis=1)) - 1).max() < 1e-9


def test_camera_centres_from_chunked_moments(tmp_path):
    rng = np.random.default_rng(3)
    rows = []
    centres = {}
    for f in range(12):
        T = make_transform(rotvec_to_matrix(rng.normal(size=3) * 0.3), rng.uniform(-300, 300, 3))
        pc = rng.uniform([-20, -5, 120], [20, 5, 180], (400, 3))
        pb = transform_points(T, pc)
        centres[f] = T[:3, 3]
        rows.append(np.column_stack([np.full(400, f), pc, pb]))
    a = np.vstack(rows)
    whole = camera_centres(a[:, 0].astype(int), a[:, 1:4], a[:, 4:7])
    m = FrameMoments()
    for c0 in range(0, len(a), 777):  # chunks that split frames
        m.add(a[c0:c0 + 777, 0].astype(int), a[c0:c0 + 777, 1:4], a[c0:c0 + 777, 4:7])
    fr, c = m.centres()
    assert np.array_equal(fr, whole[0])
    assert np.abs(c - whole[1]).max() < 1e-9
    assert max(np.linalg.norm(c[i] - centres[f]) for i, f in enumerate(fr)) < 1e-8
    # the points reader gives the same centres from a parquet of several row groups
    import pandas as pd
    df = pd.DataFrame({"frame": a[:, 0].astype(np.int64), "laser": np.where(a[:, 1] > 0, "A", "B"),
                       "x_cam": a[:, 1], "y_cam": a[:, 2], "z_cam": a[:, 3],
                       "x": a[:, 4], "y": a[:, 5], "z": a[:, 6]})
    df.loc[5, "x"] = np.nan
    path = tmp_path / "p.parquet"
    write_parquet(path, df)
    import pyarrow.parquet as pq
    pq.write_table(pq.read_table(path), path, row_group_size=1000)
    cols = read_points_columns(path)
    assert cols["non_finite"] == 1 and len(cols["xyz"]) == len(a) - 1
    assert np.array_equal(cols["laser"], np.where(np.delete(a[:, 1], 5) > 0, 1, 2))
    assert np.abs(cols["cameras"][1] - whole[1]).max() < 1e-8


def test_normals_are_open3d_s_and_a_view_direction_where_no_plane_is_spanned():
    rng = np.random.default_rng(4)
    u, v = rng.uniform(0, 20, 20_000), rng.uniform(0, 20, 20_000)  # dense: ~80 within 0.8 mm
    p = np.column_stack([u, v, 0.5 * np.sin(u / 3) + 0.2 * v + rng.normal(0, 0.01, len(u))])
    ours, deg = estimate_normals(p, 0.8)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.8, max_nn=100))
    theirs = np.asarray(pcd.normals)
    assert not deg.any()
    assert np.abs(np.abs(np.sum(ours * theirs, axis=1)) - 1).max() < 1e-9
    # far from everything: a point alone, a pair, a row of three (a line): no plane
    lone = np.array([[500.0, 0, 0], [600.0, 0, 0], [600.2, 0, 0], [700, 0, 0], [700.2, 0.1, 0],
                     [700.4, 0.2, 0]])
    q = np.vstack([p, lone])
    view = np.tile(rng.normal(size=3) * 10 + [0, 0, 100], (len(q), 1))
    n, deg = estimate_normals(q, 0.8, view + q)
    assert deg[-6:].all() and not deg[:-6].any()
    assert np.allclose(n[-6], view[0] / np.linalg.norm(view[0]))  # alone: the view direction
    for i, t in ((-5, [1.0, 0, 0]), (-3, [2.0, 1, 0])):  # a line: the view direction across it
        t = np.array(t) / np.linalg.norm(t)
        v = view[0] - (view[0] @ t) * t
        assert np.allclose(n[i], v / np.linalg.norm(v))

"""Nominal (CAD) comparison against a constructed truth: a known part, dent, table and pose.

The nominal is built here, independently of the code under test: a closed, asymmetric
rounded box (a superellipsoid of exponent 3 with two off-axis bumps, so that no rigid
symmetry maps it onto itself), triangulated from Open3D's sphere. The scan is sampled on it
with 5 µm noise, a 0.100 mm Gaussian dent (sigma 2 mm) pushed in along the normal, the bottom
left unseen, a table the part stands on, all moved by a known rigid transform.
"""

from __future__ import annotations

import json
import math
import re

import matplotlib
import numpy as np
import open3d as o3d
import pytest
from matplotlib.figure import Figure
from scipy.spatial.transform import Rotation

from crossline.errors import CrosslineError
from crossline.report.metrics import point_triangle_closest
from crossline.report.nominal import (
    align_to_nominal,
    deviation_colours,
    deviation_map_figure,
    deviation_summary,
    load_nominal,
    signed_deviation,
    weakest_mode_ratio,
    write_coloured_ply,
)

NOISE_MM = 0.005
DENT_MM = 0.100
DENT_SIGMA_MM = 2.0
TOL_MM = 0.05
N_PART = 50_000
N_TABLE = 400
SEMI_AXES = (30.0, 20.0, 12.0)


def _part_mesh(resolution: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of the closed asymmetric rounded box (mm, CAD frame)."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    u = np.asarray(sphere.vertices)
    a, b, c = SEMI_AXES
    r = (np.abs(u[:, 0] / a) ** 3 + np.abs(u[:, 1] / b) ** 3 + np.abs(u[:, 2] / c) ** 3) ** (-1 / 3)
    for direction, height, width in (((0.5, 0.4, 0.77), 0.12, 0.08), ((-0.6, -0.3, 0.74), 0.07, 0.05)):
        d = np.asarray(direction) / np.linalg.norm(direction)
        r = r * (1.0 + height * np.exp(-np.sum((u - d) ** 2, axis=1) / width))
    return u * r[:, None], np.asarray(sphere.triangles, dtype=np.int64)


def _sample(V: np.ndarray, F: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform by area on the triangles and their unit (outward) face normals."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    tri = rng.choice(len(F), n, p=area / area.sum())
    s, t = rng.random(n), rng.random(n)
    fold = s + t > 1
    s[fold], t[fold] = 1 - s[fold], 1 - t[fold]
    p = a[tri] + s[:, None] * (b - a)[tri] + t[:, None] * (c - a)[tri]
    return p, cross[tri] / area[tri, None]


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def _pose_error(T: np.ndarray, T_true: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    """Rotation error (deg) and the largest displacement error (mm) over the points p."""
    dR = T[:3, :3] @ T_true[:3, :3].T
    angle = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(dR) - 1.0) / 2.0))))
    return angle, float(np.linalg.norm(_apply(T, p) - _apply(T_true, p), axis=1).max())


def _brute_force_distance(p: np.ndarray, V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unsigned distance of each point to its nearest of all triangles (float64, no ray casting)."""
    out = np.empty(len(p))
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    for i, x in enumerate(p):
        q = point_triangle_closest(np.broadcast_to(x, a.shape), a, b, c)
        out[i] = np.linalg.norm(q - x, axis=1).min()
    return out


@pytest.fixture(scope="module")
def scan() -> dict:
    """The nominal mesh, the scan (part + table) in the arm frame and its truth."""
    rng = np.random.default_rng(20)
    V, F = _part_mesh()
    p, n = _sample(V, F, 3 * N_PART, rng)
    seen = n[:, 2] > -0.3  # the scanner does not see the underside
    p, n = p[seen][:N_PART], n[seen][:N_PART]
    top = np.flatnonzero(n[:, 2] > 0.95)
    centre = p[top[np.argmin(np.hypot(p[top, 0] + 8.0, p[top, 1] - 6.0))]]
    dent = -DENT_MM * np.exp(-np.sum((p - centre) ** 2, axis=1) / (2 * DENT_SIGMA_MM**2))
    noise = rng.normal(0.0, NOISE_MM, p.shape)
    part = p + dent[:, None] * n + noise
    # the table the part stands on, seen also under its rounded sides (a tenth of its points
    # start within the fit's first gate) but not where it nearly touches (within 1.5 mm)
    xy = rng.uniform((-55.0, -40.0), (55.0, 40.0), (4 * N_TABLE, 2))
    table = np.column_stack([xy, np.full(len(xy), V[:, 2].min())])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    gap = scene.compute_distance(o3d.core.Tensor(table.astype(np.float32))).numpy()
    table = table[gap > 1.5][:N_TABLE]
    T_cloud_nominal = np.eye(4)
    T_cloud_nominal[:3, :3] = Rotation.from_euler("zyx", [37.0, -24.0, 18.0], degrees=True).as_matrix()
    T_cloud_nominal[:3, 3] = [412.0, -233.0, 157.0]
    return {
        "V": V, "F": F,
        "cloud": _apply(T_cloud_nominal, np.vstack([part, table])),
        "part_nominal": part,
        "T_true": np.linalg.inv(T_cloud_nominal),  # T_nominal_cloud
        "dent_centre": centre,
        # the deviation each point was given: dent plus the noise along the normal
        "true_dev": dent + np.sum(noise * n, axis=1),
    }


@pytest.fixture(scope="module")
def ransac_fit(scan: dict) -> dict:
    return align_to_nominal(scan["cloud"], scan["V"], scan["F"])


@pytest.fixture(scope="module")
def deviations(scan: dict, ransac_fit: dict) -> tuple[np.ndarray, np.ndarray]:
    x = _apply(ransac_fit["T_nominal_cloud"], scan["cloud"])
    return x, signed_deviation(x, scan["V"], scan["F"])


# ----------------------------------------------------------------------------- alignment


def test_align_without_datum_recovers_the_pose(scan: dict, ransac_fit: dict) -> None:
    assert ransac_fit["coarse"] == "fpfh_ransac" and not ransac_fit["ambiguous"]
    T = np.asarray(ransac_fit["T_nominal_cloud"])
    assert T.shape == (4, 4)
    angle, move = _pose_error(T, scan["T_true"], scan["cloud"][:N_PART])
    assert angle < 0.01, angle
    assert move < 0.002, move
    # the fit sees the noise: its inliers' RMS is the 5 µm noise, not the dent or the table
    assert 0.95 < ransac_fit["fitness"] < 1.0
    assert ransac_fit["inlier_rmse_mm"] == pytest.approx(NOISE_MM, rel=0.1)


def test_align_with_datum_recovers_the_pose(scan: dict, ransac_fit: dict) -> None:
    wrong = np.eye(4)
    wrong[:3, :3] = Rotation.from_rotvec(math.radians(1.0) * np.array([0.6, 0.8, 0.0])).as_matrix()
    wrong[:3, 3] = [0.6, 0.0, 0.8]  # 1 mm
    fit = align_to_nominal(scan["cloud"], scan["V"], scan["F"], initial=wrong @ scan["T_true"])
    assert fit["coarse"] == "datum"
    angle, move = _pose_error(np.asarray(fit["T_nominal_cloud"]), scan["T_true"], scan["cloud"][:N_PART])
    assert angle < 0.01, angle
    assert move < 0.002, move
    # both coarse poses end in the same minimum
    _, apart = _pose_error(np.asarray(fit["T_nominal_cloud"]), ransac_fit["T_nominal_cloud"],
                           scan["cloud"][:N_PART])
    assert apart < 1e-5


def test_table_points_do_not_move_the_fit(scan: dict, ransac_fit: dict) -> None:
    part_only = scan["cloud"][:N_PART]
    fit = align_to_nominal(part_only, scan["V"], scan["F"], initial=ransac_fit["T_nominal_cloud"])
    _, apart = _pose_error(np.asarray(fit["T_nominal_cloud"]), ransac_fit["T_nominal_cloud"], part_only)
    assert apart < 1e-5


def test_align_ignores_clutter_on_the_surface(scan: dict, ransac_fit: dict) -> None:
    # dust, tape or a clamp: 2000 points 0.3 mm proud of a 6 mm patch, within every gate
    # but the robust kernel's (a least-squares fit moves by ~10 µm)
    V, F = scan["V"], scan["F"]
    p, n = _sample(V, F, 200_000, np.random.default_rng(9))
    patch = np.linalg.norm(p - [18.0, -9.0, 10.0], axis=1) < 6.0
    clutter = (p + 0.3 * n)[patch][:2000]
    assert len(clutter) == 2000
    cloud = np.vstack([scan["cloud"], _apply(np.linalg.inv(scan["T_true"]), clutter)])
    fit = align_to_nominal(cloud, V, F, initial=ransac_fit["T_nominal_cloud"])
    angle, move = _pose_error(np.asarray(fit["T_nominal_cloud"]), scan["T_true"], scan["cloud"][:N_PART])
    assert angle < 0.01, angle
    assert move < 0.002, move


def test_align_is_reproducible(scan: dict, ransac_fit: dict) -> None:
    again = align_to_nominal(scan["cloud"], scan["V"], scan["F"])
    assert np.array_equal(again["T_nominal_cloud"], ransac_fit["T_nominal_cloud"])


# ----------------------------------------------------------------------------- signed deviation


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (240.0, -150.0, 100.0)])
def test_signed_deviation_is_exact_and_signed(offset: tuple[float, float, float]) -> None:
    # 300 mm from the origin a plain float32 closest point is off by up to ~6e-5 mm; centred
    # and recomputed in float64 it is exact, but where float32 rounding picks a neighbouring
    # triangle (a few points in 10^4), off by about a float32 spacing at the part's size (nm)
    V, F = _part_mesh()
    V = V + np.asarray(offset)
    p, n = _sample(V, F, 20_000, np.random.default_rng(5))
    on = signed_deviation(p, V, F)
    assert np.abs(on).max() < 1e-6
    for step, sign in ((0.05, 1.0), (-0.05, -1.0)):
        d = signed_deviation(p + step * n, V, F)
        assert (np.sign(d) == sign).all()
        # moved 0.05 mm along its face normal, a point is 0.05 mm from that face and no
        # farther from the surface; on convex parts exactly 0.05 mm
        assert np.abs(d).max() <= 0.05 + 1e-5
        assert np.mean(np.abs(np.abs(d) - 0.05) < 1e-9) > 0.95
        sub = slice(0, 60)
        ref = _brute_force_distance(p[sub] + step * n[sub], V, F)
        np.testing.assert_allclose(np.abs(d[sub]), ref, rtol=0, atol=1e-5)


def test_sign_of_open_and_reversed_meshes() -> None:
    V, F = _part_mesh()
    p, n = _sample(V, F, 5000, np.random.default_rng(6))
    p, n = p[(n[:, 2] > 0.5) & (p[:, 2] > 5.0)], n[(n[:, 2] > 0.5) & (p[:, 2] > 5.0)]
    out = p + 0.05 * n
    # closed: the parity of ray crossings decides, whatever the winding
    assert (signed_deviation(out, V, F) > 0).all()
    assert (signed_deviation(out, V, F[:, ::-1]) > 0).all()
    # open (the top cap only): the side of the closest triangle's normal decides
    cap = F[(V[F][:, :, 2] > 0.0).all(axis=1)]
    assert (signed_deviation(out, V, cap) > 0).all()
    assert (signed_deviation(p - 0.05 * n, V, cap) < 0).all()
    assert (signed_deviation(out, V, cap[:, ::-1]) < 0).all()


# ----------------------------------------------------------------------------- summary and regions


def test_summary_finds_the_dent(scan: dict, deviations: tuple[np.ndarray, np.ndarray]) -> None:
    x, dev = deviations
    s = deviation_summary(dev, tolerance_mm=TOL_MM, points=x, max_distance_mm=1.0)
    json.dumps(s, allow_nan=False)
    assert s["n_excluded"] == N_TABLE and s["n"] == N_PART  # the table, all of it and only it
    assert s["n_regions"] == 1
    (region,) = s["regions"]
    assert abs(region["extreme_mm"] - (-DENT_MM)) < 0.015, region
    assert abs(region["depth_mm"] - (-DENT_MM)) < 0.015, region
    assert np.linalg.norm(np.asarray(region["centroid_mm"]) - scan["dent_centre"]) < 1.0
    assert np.linalg.norm(np.asarray(region["extreme_at_mm"]) - scan["dent_centre"]) < 1.0
    # the given deviations are true to ~2 µm (the pose, and noise carrying a point over a
    # facet edge): only points that close to ±tolerance may count on the other side
    true_dev = scan["true_dev"]
    beyond = np.count_nonzero(np.abs(true_dev) > TOL_MM)
    borderline = np.count_nonzero(np.abs(np.abs(true_dev) - TOL_MM) < 0.002)
    assert abs(region["n"] - beyond) <= borderline
    within = np.count_nonzero(np.abs(true_dev) <= TOL_MM)
    assert abs(s["share_within_tolerance"] * N_PART - within) <= borderline
    assert s["rms_mm"] == pytest.approx(np.sqrt(np.mean(true_dev**2)), abs=2e-4)
    assert s["min_mm"] <= s["p2_5_mm"] <= s["p50_mm"] <= s["p97_5_mm"] <= s["max_mm"]
    assert abs(s["p50_mm"]) < 0.001
    # without the distance gate the table is not hidden: it shows, far off the part
    s_all = deviation_summary(dev, tolerance_mm=TOL_MM)
    assert s_all["n"] == N_PART + N_TABLE and s_all["n_excluded"] == 0
    assert s_all["max_mm"] > 1.0 and s_all["regions"] is None


def test_regions_are_separate_defects() -> None:
    g = np.arange(-20.0, 20.0 + 1e-9, 0.25)
    x, y = np.meshgrid(g, g)
    p = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])

    def bump(cx: float, cy: float, h: float, s: float) -> np.ndarray:
        return h * np.exp(-((p[:, 0] - cx) ** 2 + (p[:, 1] - cy) ** 2) / (2 * s * s))

    dent, ridge, boss = bump(-10, 0, -0.1, 2.0), bump(-7, 0, 0.1, 0.5), bump(10, 5, 0.07, 1.5)
    dev = dent + ridge + boss
    # the ridge's out-of-tolerance points are 1.03 mm from the dent's, within one cluster
    # radius: only their sign keeps them apart
    s = deviation_summary(dev, tolerance_mm=TOL_MM, points=p, cluster_radius_mm=1.5, n_largest=2)
    assert s["n_regions"] == 3 and len(s["regions"]) == 2
    first, second = s["regions"]
    assert first["id"] == 1 and second["id"] == 2
    assert first["n"] == np.count_nonzero(dev < -TOL_MM)
    assert first["extreme_mm"] == pytest.approx(dev.min())
    assert first["extreme_at_mm"] == pytest.approx([-10.0, 0.0, 0.0])
    assert second["n"] == np.count_nonzero((dev > TOL_MM) & (p[:, 0] > 0))
    assert second["centroid_mm"] == pytest.approx([10.0, 5.0, 0.0], abs=1e-9)
    assert second["extreme_mm"] == pytest.approx(0.07)
    top = np.sort(dev[(dev > TOL_MM) & (p[:, 0] > 0)])[::-1]
    assert second["depth_mm"] == pytest.approx(np.median(top[: math.ceil(0.1 * len(top))]))


# ----------------------------------------------------------------------------- files


def test_bad_mesh_files_name_the_file(tmp_path) -> None:
    empty = tmp_path / "empty.stl"
    empty.write_bytes(b"")
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(np.random.default_rng(3).bytes(1000))
    nan = tmp_path / "nan.ply"
    nan.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                   "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                   "end_header\n0 0 0\n1 0 nan\n0 1 0\n3 0 1 2\n")
    points_only = tmp_path / "points.obj"
    points_only.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    step = tmp_path / "part.step"
    step.write_text("ISO-10303-21;\n")
    for path in (empty, garbage, nan, points_only, step, tmp_path / "missing.stl"):
        with pytest.raises(CrosslineError, match=re.escape(str(path))):
            load_nominal(path)


def test_load_nominal_reads_a_closed_stl(tmp_path) -> None:
    V, F = _part_mesh(resolution=20)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F))
    mesh.compute_triangle_normals()
    path = tmp_path / "part.STL"
    assert o3d.io.write_triangle_mesh(str(path), mesh)
    V2, F2 = load_nominal(path)
    # STL repeats each triangle's vertices: they must be shared again
    assert V2.dtype == np.float64 and len(V2) == len(V) and len(F2) == len(F)
    p, n = _sample(V, F, 500, np.random.default_rng(8))
    assert (signed_deviation(p + 0.01 * n, V2, F2) > 0).all()
    assert np.abs(signed_deviation(p, V2, F2)).max() < 1e-5  # STL is float32


def test_colours_are_symmetric_and_clipped() -> None:
    cmap = matplotlib.colormaps["coolwarm"]
    rgb = deviation_colours(np.array([-1.0, -0.1, 0.0, 0.1, 1.0, np.nan]), 0.1)
    assert rgb.shape == (6, 3) and (rgb >= 0).all() and (rgb <= 1).all()
    np.testing.assert_allclose(rgb[0], cmap(0.0)[:3])
    np.testing.assert_allclose(rgb[1], cmap(0.0)[:3])
    np.testing.assert_allclose(rgb[2], cmap(0.5)[:3])
    np.testing.assert_allclose(rgb[3], cmap(1.0)[:3])
    np.testing.assert_allclose(rgb[4], cmap(1.0)[:3])
    np.testing.assert_allclose(rgb[5], 0.5)
    assert rgb[3, 0] > rgb[3, 2] and rgb[1, 2] > rgb[1, 0]  # excess red, lack blue


def test_coloured_ply_round_trips(tmp_path, deviations: tuple[np.ndarray, np.ndarray]) -> None:
    x, dev = deviations
    rgb = deviation_colours(dev, 0.1)
    path = tmp_path / "out" / "deviation.ply"
    write_coloured_ply(path, x, rgb, deviation=dev)
    write_coloured_ply(path, x, rgb, deviation=dev)  # over an existing file
    assert sorted(q.name for q in path.parent.iterdir()) == ["deviation.ply"]
    back = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(back.points), x)
    np.testing.assert_allclose(np.asarray(back.colors), rgb, atol=0.5 / 255 + 1e-12)
    tback = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(tback.point.deviation.numpy().ravel(), dev)


def test_deviation_map_figure(deviations: tuple[np.ndarray, np.ndarray]) -> None:
    x, dev = deviations
    s = deviation_summary(dev, tolerance_mm=TOL_MM, points=x, max_distance_mm=1.0)
    fig = deviation_map_figure(x, dev, 0.1, regions=s["regions"], tolerance_mm=TOL_MM)
    assert isinstance(fig, Figure)
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(bars) == 1 and "mm" in bars[0].get_ylabel()
    views = [ax for ax in fig.axes if ax.collections and ax.get_label() != "<colorbar>"]
    assert len(views) == 3
    for ax in views:
        assert ax.get_aspect() == 1.0
        assert len(ax.collections[0].get_array()) == len(x)
        assert [t.get_text() for t in ax.texts] == ["1"]


def test_weakest_mode_ratio_free_and_fixed_motions(scan: dict, ransac_fit: dict) -> None:
    rng = np.random.default_rng(5)
    xy = rng.uniform(-20, 20, (2000, 2))
    up = np.tile([0.0, 0.0, 1.0], (2000, 1))
    plane = np.column_stack([xy, np.zeros(2000)])
    assert weakest_mode_ratio(plane, up) < 1e-12  # two slides and a turn are free
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert weakest_mode_ratio(300.0 + 20.0 * d, d) < 1e-12  # a sphere turns freely
    # a box's corner: three planes at right angles fix every motion
    corner = np.vstack([np.column_stack([rng.uniform(0, 20, (3000, 2)), np.zeros(3000)])[:, p]
                        for p in ([0, 1, 2], [0, 2, 1], [2, 0, 1])])
    normals = np.repeat(np.eye(3)[[2, 1, 0]], 3000, axis=0)
    assert weakest_mode_ratio(corner, normals) > 0.05
    # the asymmetric part scanned from above is held firmly; the quick capture's flat top is
    # not (tests/test_report_quick.py)
    assert not ransac_fit["ambiguous"] and ransac_fit["weakest_mode_ratio"] > 0.01


def test_a_symmetric_patch_is_flagged_ambiguous() -> None:
    """The top of a sphere alone fits turned about any axis through its centre: without a
    datum the alignment says it is ambiguous (and the asymmetric part is not, above)."""
    m = o3d.geometry.TriangleMesh.create_sphere(radius=20.0, resolution=60)
    V, F = np.asarray(m.vertices), np.asarray(m.triangles)
    rng = np.random.default_rng(3)
    p, _ = _sample(V, F, 20000, rng)
    cap = p[p[:, 2] > 12.0]  # the cap seen from above
    T = np.eye(4)
    T[:3, 3] = [300.0, -50.0, 20.0]
    al = align_to_nominal(_apply(T, cap), V, F)
    assert al["ambiguous"] and al["rival_poses"] >= 1
    # and the pose it chose still lays the cap on the sphere, within the facets' sagitta
    # (turned, a point sampled on one facet lands across others: up to 20 (1 - cos(pi/60)),
    # 0.027 mm)
    d = signed_deviation(_apply(al["T_nominal_cloud"], _apply(T, cap)), V, F)
    assert np.abs(d).max() < 0.03


def test_freeform_figures_follow_a_move_and_ignore_a_rigid_one() -> None:
    """The freeform's Monte Carlo figures (crossline.report.uncertainty.freeform_figures): a
    rigid motion of the whole cloud is undone by the linearised re-alignment (no deviation
    changes), a local bump of points along the surface is seen as the exact signed distance
    sees it, and the deviation's gradient is the surface normal on the surface."""
    from crossline.report.nominal import signed_deviation
    from crossline.report.uncertainty import freeform_figures

    rng = np.random.default_rng(3)
    V, F = _part_mesh()
    p, n = _sample(V, F, 6000, rng)
    up = p[:, 2] > 0  # the half a scan sees
    p, n = p[up], n[up]
    p = p + 0.002 * rng.standard_normal(len(p))[:, None] * n  # off the surface along its normal
    dev, grad = signed_deviation(p, V, F, directions=True)
    keep = np.ones(len(p), bool)
    # the gradient is the outward normal of the face the point lies over (unit, same side)
    assert np.median(np.einsum("ni,ni->n", grad, n)) > 0.999
    assert np.allclose(np.linalg.norm(grad, axis=1), 1.0)
    T = np.eye(4)  # the cloud already in the nominal's frame
    fig = freeform_figures(p, T, dev, grad, keep, 0.005)
    w = np.ones(len(p))
    v0 = fig(p, w)
    assert v0["deviation_mean_mm"] == pytest.approx(dev.mean(), abs=1e-12)
    # a rigid motion of 20 µm and 0.2 mrad: its deviations are all undone by the re-alignment
    R = o3d.geometry.get_rotation_matrix_from_xyz((2e-4, -1e-4, 1.5e-4))
    moved = (p - p.mean(0)) @ R.T + p.mean(0) + [0.02, -0.01, 0.015]
    v1 = fig(moved, w)
    for k in v0:
        assert v1[k] == pytest.approx(v0[k], abs=2e-6), k
    # a bump of 10 µm along the normal on a patch: the linearised deviation is the exact one
    # (after the same re-alignment, which the bump moves a little)
    patch = np.linalg.norm(p[:, :2] - p[np.argmax(p[:, 2]), :2], axis=1) < 8.0
    bumped = p + (0.01 * patch)[:, None] * grad
    exact = signed_deviation(bumped, V, F)
    v2 = fig(bumped, w)
    assert v2["deviation_mean_mm"] - v0["deviation_mean_mm"] < 0.01 * patch.mean()
    assert np.mean(np.abs(exact - dev)[patch]) == pytest.approx(0.01, rel=0.05)
    assert v2["deviation_rms_mm"] > v0["deviation_rms_mm"] + 0.001

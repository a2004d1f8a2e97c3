"""Compare a scanned cloud with its nominal (CAD) shape: align, signed deviation, regions, map.

A freeform scan may name a nominal mesh (STL, PLY or OBJ, in mm, in the part's own CAD
frame). The fused cloud is in the arm's base frame, so the comparison runs in three steps:

1. ``align_to_nominal``: the rigid transform ``T_nominal_cloud``. Coarse from a datum the
   user gives or from RANSAC on FPFH features; fine by iterating Open3D's point-to-plane
   step with a Tukey kernel on the *exact* closest points of the mesh (not on samples of
   it), the kernel's scale following the residuals' robust sigma, so that a local defect
   and points off the part (table, fixture) do not pull the fit.
2. ``signed_deviation``: distance of every point to the mesh, positive outside.
3. ``deviation_summary`` / ``deviation_colours`` / ``deviation_map_figure``: statistics,
   the out-of-tolerance *regions* (connected clusters, not neighbouring points of one
   defect), a colour map and its PLY.

Precision: Open3D's ``RaycastingScene`` is float32, whose spacing is ~4 nm at 50 mm and
~60 nm at 1 m from the origin; its closest points lose a few bits more. So the scene is
built in coordinates centred on the mesh, and each distance is recomputed in float64 on the
triangle the scene found (``crossline.report.metrics.point_triangle_closest``): exact to
~1e-12 mm where that triangle is the closest one, and off by about one float32 spacing at
the part's own size (nanometres) where rounding picked a neighbour instead.

Everything here takes and returns arrays; only ``load_nominal`` and ``write_coloured_ply``
touch files.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from crossline.errors import CrosslineError
from crossline.report.metrics import point_triangle_closest

__all__ = [
    "align_to_nominal",
    "deviation_colours",
    "deviation_map_figure",
    "deviation_summary",
    "load_nominal",
    "signed_deviation",
    "support_plane",
    "weakest_mode_ratio",
    "write_coloured_ply",
]

MESH_SUFFIXES = (".stl", ".ply", ".obj")
COLOUR_MAP = "coolwarm"
TUKEY_C = 4.685  # Tukey biweight constant: 95 % efficiency at Gaussian residuals
MAD_TO_SIGMA = 1.4826
# the fit's weakest motion constrained less than this fraction as strongly as its strongest
# (smallest over largest eigenvalue of the point-to-plane information, rotations scaled by
# the cloud's RMS radius, so the ratio has no unit): the surface lets the pose slide along
# it, and where RANSAC lands along that slide is chance. Conservative: it also refuses
# nearly flat patches that did fix the pose. Each alignment records its ratio
# (``weakest_mode_ratio``); docs/method.md says where the value comes from.
WEAK_MODE_RATIO = 1e-3
# the identity and half turns about x, y and z: the symmetric poses a coarse match may land in
_HALF_TURNS = (np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
               np.diag([-1.0, -1.0, 1.0]))


# ----------------------------------------------------------------------------- mesh


def load_nominal(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 mm and triangles (F, 3) int64 of an STL, PLY or OBJ mesh."""
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise CrosslineError(f"{path}: nominal mesh must be STL, PLY or OBJ, not '{path.suffix}'")
    if not path.is_file():
        raise CrosslineError(f"{path}: nominal mesh not found")
    # Open3D only warns on a file it cannot parse and returns an empty mesh: the checks
    # below turn that into an error that names the file
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise CrosslineError(
            f"{path}: no triangles could be read (expected a triangle mesh in STL, PLY or OBJ)"
        )
    V = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.isfinite(V).all():
        bad = int(np.flatnonzero(~np.isfinite(V).all(1))[0])
        raise CrosslineError(f"{path}: vertex {bad} is not finite ({V[bad].tolist()})")
    F = np.asarray(mesh.triangles, dtype=np.int64)
    if F.min() < 0 or F.max() >= len(V):
        raise CrosslineError(f"{path}: triangle indices outside 0..{len(V) - 1}")
    # STL stores three vertices per triangle: merge the exact duplicates so that edges are
    # shared and a closed part is recognised as closed (its sign then comes from parity)
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        raise CrosslineError(f"{path}: every triangle is degenerate (zero area)")
    return (np.asarray(mesh.vertices, dtype=np.float64).copy(),
            np.asarray(mesh.triangles, dtype=np.int64).copy())


def support_plane(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The plane ``(n, d)`` of a mesh's open boundary, if it is one plane: the face a part
    stands on and its drawing leaves open (``n`` points into the part). None for a closed
    mesh or a boundary that is not flat (to 1e-4 of the part's size)."""
    from crossline.geometry import fit_plane

    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(triangles, dtype=np.int64)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    rim = np.unique(uniq[counts == 1])
    if len(rim) < 3:
        return None
    n, d = fit_plane(V[rim])
    size = float(np.linalg.norm(np.ptp(V, axis=0)))
    if np.abs(V[rim] @ n + d).max() > 1e-4 * size:
        return None
    if float(V.mean(axis=0) @ n + d) < 0:
        n, d = -n, -d
    return n, float(d)


def _is_closed(F: np.ndarray) -> bool:
    """True if every undirected edge of the triangles is shared by exactly two of them."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e[:, 0] * (int(F.max()) + 1) + e[:, 1], return_counts=True)
    return bool((counts == 2).all())


class _Surface:
    """A triangle mesh with its float32 ray-casting scene, centred for precision."""

    def __init__(self, V: np.ndarray, F: np.ndarray) -> None:
        import open3d as o3d

        self.V = np.asarray(V, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int64)
        if self.V.ndim != 2 or self.V.shape[1] != 3 or self.F.ndim != 2 or self.F.shape[1] != 3:
            raise ValueError("vertices and triangles must be (V, 3) and (F, 3)")
        if len(self.F) == 0:
            raise ValueError("the nominal mesh has no triangles")
        if self.F.min() < 0 or self.F.max() >= len(self.V) or not np.isfinite(self.V).all():
            raise ValueError("the nominal mesh has non-finite vertices or triangle indices out of range")
        # float32 loses precision with distance from the origin: centre on the mesh
        self.c0 = 0.5 * (self.V.min(0) + self.V.max(0))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor((self.V - self.c0).astype(np.float32)),
            o3d.core.Tensor(self.F.astype(np.uint32)),
        )
        a, b, c = (self.V[self.F[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.normals = n / np.linalg.norm(n, axis=1, keepdims=True)
        self.normals = np.nan_to_num(self.normals)
        self.closed = _is_closed(self.F)
        self.diagonal = float(np.linalg.norm(self.V.max(0) - self.V.min(0)))

    def _query(self, p: np.ndarray) -> Any:
        import open3d as o3d

        return o3d.core.Tensor((p - self.c0).astype(np.float32))

    def closest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest points (N, 3) float64 on the mesh and the index of their triangle."""
        ans = self.scene.compute_closest_points(self._query(p))
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        vid = self.F[tri]
        q = point_triangle_closest(p, self.V[vid[:, 0]], self.V[vid[:, 1]], self.V[vid[:, 2]])
        return q, tri

    def signed(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance (N,), closest points (N, 3) and triangle normals (N, 3)."""
        q, tri = self.closest(p)
        delta = p - q
        dist = np.linalg.norm(delta, axis=1)
        n = self.normals[tri]
        if self.closed:
            # parity of ray crossings: right whatever the triangles' winding, and also at
            # sharp edges where one face's normal can point the wrong way
            inside = self.scene.compute_occupancy(self._query(p), nsamples=3).numpy() > 0.5
        else:
            inside = (delta * n).sum(1) < 0
        return np.where(inside, -dist, dist), q, n


# ----------------------------------------------------------------------------- alignment


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """Run Open3D on one thread: its TBB reductions sum in a thread-dependent order."""
    import open3d as o3d

    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)


def _to_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> Any:
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return pc


def _transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def _fpfh(pc: Any, voxel: float) -> tuple[Any, Any]:
    """Voxel-downsampled cloud with outward-oriented normals and its FPFH features."""
    import open3d as o3d

    down = pc.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    # FPFH depends on the normals' sign: orient both clouds the same way (consistently
    # over the surface, then outward on the whole) or their features do not match
    down.orient_normals_consistent_tangent_plane(12)
    p = np.asarray(down.points)
    n = np.asarray(down.normals)
    if ((p - p.mean(0)) * n).sum() < 0:
        down.normals = o3d.utility.Vector3dVector(-n)
    feat = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    )
    return down, feat


def _refine(
    p: np.ndarray, surface: _Surface, T: np.ndarray, gate: float, max_iterations: int
) -> tuple[np.ndarray, float, int]:
    """Robust point-to-plane ICP of points p on the mesh's exact closest points, from pose T.

    Returns the pose, the final Tukey scale and the number of iterations.
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    src = _to_cloud(p)
    # with noise-free points the robust sigma goes to zero: keep the kernel from vanishing
    sigma_floor = 1e-5 * surface.diagonal
    lever = max(surface.diagonal, 1.0)
    k = gate
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 (returned)
        x = _transform(T, p)
        q, tri = surface.closest(x)
        n = surface.normals[tri]
        r = ((x - q) * n).sum(1)
        use = np.flatnonzero(np.linalg.norm(x - q, axis=1) < gate)
        if len(use) < 6:
            raise CrosslineError(
                f"the scan does not lie on its nominal shape: fewer than 6 of {len(p)} points "
                f"within {gate:.3g} mm of it after the coarse pose (give a datum)"
            )
        # the gate keeps points off the part (table, fixture) out of the robust sigma
        sigma = max(MAD_TO_SIGMA * float(np.median(np.abs(r[use]))), sigma_floor)
        k = TUKEY_C * sigma
        src.points = o3d.utility.Vector3dVector(x)
        corres = o3d.utility.Vector2iVector(np.repeat(use[:, None].astype(np.int32), 2, axis=1))
        with _one_thread():  # TBB's reduction order depends on the threads: same bits anywhere
            step = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k)).compute_transformation(
                src, _to_cloud(q, n), corres
            )
        T = step @ T
        gate = min(gate, max(3.0 * k, 10.0 * sigma_floor))
        angle = math.acos(min(1.0, max(-1.0, (np.trace(step[:3, :3]) - 1.0) / 2.0)))
        # bound on how far any point of the part moved in this step
        move = float(np.linalg.norm(step[:3, :3] @ surface.c0 + step[:3, 3] - surface.c0)) + angle * lever
        if move < 1e-7:
            break
    return T, k, iterations


def _ransac(points: np.ndarray, surface: _Surface, voxel: float, seed: int, hypotheses: int) -> np.ndarray:
    """Coarse T_nominal_cloud: the best of RANSAC runs on FPFH correspondences, each refined."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(surface.V), o3d.utility.Vector3iVector(surface.F.astype(np.int32))
    )
    # a few samples per voxel, so that the nominal's voxel grid is as full as the scan's
    n_samples = int(min(max(4.0 * mesh.get_surface_area() / voxel**2, 5000), 400_000))
    o3d.utility.random.seed(seed)
    nominal = mesh.sample_points_uniformly(n_samples)
    src, src_f = _fpfh(_to_cloud(points), voxel)
    dst, dst_f = _fpfh(nominal, voxel)
    p_down = np.asarray(src.points)
    best, best_score = None, -1.0
    fits: list[tuple[np.ndarray, float]] = []
    for h in range(hypotheses):
        # seeded and on one thread, or the hypotheses drawn depend on the threads' timing
        with _one_thread():
            o3d.utility.random.seed(seed + h)
            result = reg.registration_ransac_based_on_feature_matching(
                src, dst, src_f, dst_f, True, 1.5 * voxel,
                reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
                reg.RANSACConvergenceCriteria(100_000, 0.999),
            )
        if len(result.correspondence_set) < 3:
            continue
        # a part that is nearly symmetric matches almost as well turned over: RANSAC's
        # voxel-level score cannot tell, the surface after refinement can. So each hypothesis
        # is also tried turned half a turn about each axis of the nominal's bounding box.
        for flip in _HALF_TURNS:
            F = np.eye(4)
            F[:3, :3] = flip
            F[:3, 3] = surface.c0 - flip @ surface.c0
            try:
                T, _, _ = _refine(p_down, surface, F @ np.asarray(result.transformation),
                                  3.0 * voxel, 20)
            except CrosslineError:
                continue
            d, _, _ = surface.signed(_transform(T, p_down))
            score = float(np.mean(np.abs(d) < 0.1 * voxel))
            fits.append((T, score))
            if score > best_score:
                best, best_score = T, score
    if best is None:
        raise CrosslineError("the scan could not be matched to its nominal shape (RANSAC on FPFH "
                             "features found no consistent correspondences): give a datum")
    # other poses that fit (almost) as well but put the points elsewhere on the part: the
    # scanned surface does not fix the alignment (a symmetric part, a patch seen alone)
    rivals = [T for T, sc in fits if sc >= best_score - 0.02 and
              np.sqrt(np.mean(np.sum((_transform(T, p_down) - _transform(best, p_down)) ** 2, 1)))
              > voxel]
    return best, len(rivals)


def align_to_nominal(
    points: np.ndarray,
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    initial: np.ndarray | None = None,
    voxel_mm: float | None = None,
    seed: int = 0,
    hypotheses: int = 5,
    max_points: int = 200_000,
    max_iterations: int = 60,
) -> dict[str, Any]:
    """Rigid T_nominal_cloud (4x4) mapping cloud points (N, 3) onto the nominal mesh, robustly.

    The coarse pose is ``initial`` (a datum, T_nominal_cloud) when given, else the best of
    ``hypotheses`` seeded RANSAC runs on FPFH features of the clouds downsampled to
    ``voxel_mm`` (default: 1/50 of the nominal's bounding-box diagonal); a part with an
    exact symmetry can still come out in a symmetric pose: give it a datum. The fine pose
    iterates Open3D's point-to-plane step against the mesh's exact closest points with a
    Tukey kernel of 4.685 robust sigmas, on at most ``max_points`` points, until no point
    of the part moves by 1e-7 mm. ``fitness`` is the share of points within the final
    Tukey scale and ``inlier_rmse_mm`` their RMS distance to the mesh. ``ambiguous``: without
    a datum, other coarse poses (``rival_poses``) fitted within 2 % as many points as well but
    put the points more than a voxel elsewhere, or the fitted surface fixes some motion of
    the pose less than ``WEAK_MODE_RATIO`` as firmly as another (``weakest_mode_ratio``, see
    :func:`weakest_mode_ratio`: a nearly flat patch seen alone slides on its drawing, and
    which rival RANSAC happens to draw there is chance): the scanned surface does not fix
    the pose.
    """
    p_all = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p_all = p_all[np.isfinite(p_all).all(1)]
    if len(p_all) < 10:
        raise ValueError("align_to_nominal needs at least 10 finite points")
    surface = _Surface(vertices, triangles)
    voxel = float(voxel_mm) if voxel_mm is not None else surface.diagonal / 50.0
    if not voxel > 0:
        raise ValueError("voxel_mm must be positive")
    rivals = 0
    if initial is not None:
        T0 = np.asarray(initial, dtype=np.float64).reshape(4, 4)
        coarse = "datum"
    else:
        T0, rivals = _ransac(p_all, surface, voxel, seed, max(1, int(hypotheses)))
        coarse = "fpfh_ransac"
    # the fit's statistics need no more than a few hundred thousand points: a fixed,
    # seeded subset keeps each iteration's ray casting cheap on clouds of millions
    if len(p_all) > max_points:
        p = p_all[np.sort(np.random.default_rng(seed).choice(len(p_all), max_points, replace=False))]
    else:
        p = p_all
    # a datum wrong by a degree and a millimetre is still well within this gate
    T, k, iterations = _refine(p, surface, T0, 3.0 * voxel, max_iterations)
    x = _transform(T, p)
    d, _, _ = surface.signed(x)
    inl = np.abs(d) <= k
    _, tri = surface.closest(x[inl])
    weak = weakest_mode_ratio(x[inl], surface.normals[tri])
    return {
        "T_nominal_cloud": T,
        "fitness": float(inl.mean()),
        "inlier_rmse_mm": float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else float("nan"),
        "coarse": coarse,
        "ambiguous": rivals > 0 or (initial is None and weak < WEAK_MODE_RATIO),
        "rival_poses": int(rivals),
        "weakest_mode_ratio": weak,
        "iterations": int(iterations),
        "tukey_scale_mm": float(k),
        "voxel_mm": voxel,
        "n_points": len(p),
    }


def weakest_mode_ratio(points: np.ndarray, normals: np.ndarray) -> float:
    """How firmly a surface fixes a rigid fit: the smallest over the largest eigenvalue of the
    point-to-plane information (Gelfand et al., geometrically stable sampling for ICP, 2003).

    Each point (N, 3) on its unit surface normal (N, 3) constrains the motion (rotation about
    the points' centroid, scaled by their RMS radius, and translation) by
    ``[(p - c) x n / L, n]``; a plane leaves three motions free (ratio 0), a sphere's cap three
    turns, a cylinder two.
    """
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    if len(p) < 6:
        return 0.0
    c = p.mean(0)
    lever = max(float(np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1)))), 1e-12)
    J = np.hstack([np.cross(p - c, n) / lever, n])
    w = np.linalg.eigvalsh(J.T @ J)
    return float(max(w[0], 0.0) / w[-1]) if w[-1] > 0 else 0.0


# ----------------------------------------------------------------------------- deviation


def signed_deviation(
    points_nominal_frame: np.ndarray, vertices: np.ndarray, triangles: np.ndarray
) -> np.ndarray:
    """Signed distance (N,) in mm of points (N, 3) to the nominal mesh, positive outside (excess).

    Closed meshes (every edge shared by two triangles) take the sign from the parity of ray
    crossings (``RaycastingScene.compute_occupancy``, three rays), as
    ``compute_signed_distance`` does; meshes that are not closed take it from the side of
    the closest triangle, i.e. positive where its counter-clockwise normal points. The
    distance is Open3D's closest point, recomputed in float64 on that triangle. Points that
    are not finite get NaN.
    """
    p = np.asarray(points_nominal_frame, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(p), np.nan)
    ok = np.isfinite(p).all(1)
    if ok.any():
        out[ok], _, _ = _Surface(vertices, triangles).signed(p[ok])
    return out


def _regions(
    points: np.ndarray, dev: np.ndarray, mask: np.ndarray, radius: float
) -> list[dict[str, Any]]:
    """Connected clusters (within ``radius``) of the masked points, one sign at a time."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    out: list[dict[str, Any]] = []
    # an excess next to a dent is a second defect, not the same one: cluster each sign alone
    for sel in (mask & (dev < 0), mask & (dev > 0)):
        idx = np.flatnonzero(sel)
        if len(idx) == 0:
            continue
        pairs = cKDTree(points[idx]).query_pairs(radius, output_type="ndarray")
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
        _, label = connected_components(g, directed=False)
        order = np.argsort(label, kind="stable")
        bounds = np.flatnonzero(np.diff(label[order])) + 1
        for members in np.split(idx[order], bounds):
            dv = dev[members]
            a = np.abs(dv)
            j = int(np.argmax(a))
            deep = np.argsort(a, kind="stable")[::-1][: max(1, math.ceil(0.1 * len(a)))]
            out.append({
                "n": len(members),
                "centroid_mm": points[members].mean(0).tolist(),
                "extreme_mm": float(dv[j]),
                "extreme_at_mm": points[members[j]].tolist(),
                "depth_mm": float(np.sign(dv[j]) * np.median(a[deep])),
                # where it is deepest: less noisy than the extreme point, and unlike the
                # centroid not pulled aside where the stripes cross one side of the defect
                "depth_at_mm": points[members[deep]].mean(0).tolist(),
            })
    out.sort(key=lambda g: (-abs(g["extreme_mm"]), g["centroid_mm"]))
    for i, g in enumerate(out, start=1):
        g["id"] = i
    return out


def line_gap_mm(points: np.ndarray, frames: np.ndarray, probes: int = 4000, seed: int = 0) -> float:
    """How far apart a line scan's lines lie: twice the 95th percentile, over sampled points, of
    the distance to the nearest point of another frame (a point between two lines is at most
    half their spacing from one; mm; 0 with fewer than two frames).

    A scan samples densely along each stripe and sparsely across them; a defect seen on
    neighbouring stripes is one defect. The nearest point of another frame is found with trees
    of random halves of the frames (eight draws: any one other frame falls in the probe's
    opposite half at least once with probability 1 - 2^-8)."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(frames).reshape(-1)
    uniq, fi = np.unique(f, return_inverse=True)
    if len(uniq) < 2:
        return 0.0
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(p), min(probes, len(p)), replace=False)
    best = np.full(len(pick), np.inf)
    for _ in range(8):
        half = rng.integers(0, 2, len(uniq)).astype(bool)[fi]
        for side in (False, True):
            mine = np.flatnonzero(half[pick] == side)
            other = p[half != side]
            if len(mine) and len(other):
                d, _ = cKDTree(other).query(p[pick[mine]])
                best[mine] = np.minimum(best[mine], d)
    best = best[np.isfinite(best)]
    return 2.0 * float(np.percentile(best, 95)) if best.size else 0.0


def deviation_summary(
    dev: np.ndarray,
    *,
    tolerance_mm: float,
    points: np.ndarray | None = None,
    n_largest: int = 10,
    cluster_radius_mm: float | None = None,
    max_distance_mm: float | None = None,
    frames: np.ndarray | None = None,
) -> dict[str, Any]:
    """Statistics of signed deviations (mm) and the largest out-of-tolerance regions, JSON-ready.

    Points farther than ``max_distance_mm`` (when given) are not on the part (table,
    fixture) and, with non-finite deviations, are left out of everything but ``n_excluded``.
    With ``points`` (N, 3), the points beyond ±``tolerance_mm`` are grouped into regions:
    connected within ``cluster_radius_mm`` (default: 5 median point spacings, or with
    ``frames`` (N,), each point's frame, the scan's :func:`line_gap_mm` where larger), excess and
    lack apart; each has its centroid, point count, extreme deviation and its location, and
    a robust depth (the median of its 10 % largest deviations, signed) and where that is
    (``depth_at_mm``, the mean of those points). The ``n_largest``
    regions with the largest extreme deviation are returned, largest first (``n_regions``
    counts them all).
    """
    from scipy.spatial import cKDTree

    dev = np.asarray(dev, dtype=np.float64).reshape(-1)
    tol = float(tolerance_mm)
    if not tol > 0:
        raise ValueError("tolerance_mm must be positive")
    keep = np.isfinite(dev)
    if max_distance_mm is not None:
        keep &= np.abs(dev) <= float(max_distance_mm)
    d = dev[keep]
    out: dict[str, Any] = {
        "n": int(d.size),
        "n_excluded": int(dev.size - d.size),
        "tolerance_mm": tol,
        "max_distance_mm": None if max_distance_mm is None else float(max_distance_mm),
    }
    if d.size == 0:
        return out | {"share_within_tolerance": None, "regions": []}
    p025, p50, p975 = np.percentile(d, [2.5, 50.0, 97.5])
    out |= {
        "mean_mm": float(d.mean()),
        "std_mm": float(d.std(ddof=1)) if d.size > 1 else 0.0,
        "rms_mm": float(np.sqrt(np.mean(d**2))),
        "min_mm": float(d.min()),
        "max_mm": float(d.max()),
        "p2_5_mm": float(p025),
        "p50_mm": float(p50),
        "p97_5_mm": float(p975),
        "share_within_tolerance": float(np.mean(np.abs(d) <= tol)),
    }
    if points is None:
        out["regions"] = None
        return out
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) != len(dev):
        raise ValueError(f"points ({len(p)}) and deviations ({len(dev)}) differ in number")
    p = p[keep]
    if cluster_radius_mm is None:
        spacing = 0.0
        if len(p) > 1:
            # the median spacing is as well known from 20 000 points as from millions
            probe = p
            if len(p) > 20_000:
                probe = p[np.random.default_rng(0).choice(len(p), 20_000, replace=False)]
            nn, _ = cKDTree(p).query(probe, k=2)
            spacing = float(np.median(nn[:, 1]))
        radius = 5.0 * spacing
        if frames is not None:
            # a defect that neighbouring stripes cross is one region, however far apart they lie
            gap = line_gap_mm(p, np.asarray(frames).reshape(-1)[keep])
            out["line_gap_mm"] = gap
            radius = max(radius, gap)
    else:
        radius = float(cluster_radius_mm)
    regions = _regions(p, d, np.abs(d) > tol, radius)
    out["cluster_radius_mm"] = radius
    out["n_regions"] = len(regions)
    out["regions"] = regions[: max(0, int(n_largest))]
    return out


# ----------------------------------------------------------------------------- colours and map


def deviation_colours(dev: np.ndarray, limit_mm: float) -> np.ndarray:
    """RGB (N, 3) in [0, 1] of deviations on a diverging map, symmetric ±limit_mm, clipped."""
    import matplotlib

    lim = float(limit_mm)
    if not lim > 0:
        raise ValueError("limit_mm must be positive")
    dev = np.asarray(dev, dtype=np.float64).reshape(-1)
    t = np.clip((dev / lim + 1.0) / 2.0, 0.0, 1.0)
    rgb = np.asarray(matplotlib.colormaps[COLOUR_MAP](np.nan_to_num(t, nan=0.5)), dtype=np.float64)[:, :3]
    rgb[~np.isfinite(dev)] = 0.5  # no deviation: neutral grey
    return rgb


def write_coloured_ply(
    path: str | Path, points: np.ndarray, colours: np.ndarray, *, deviation: np.ndarray | None = None
) -> None:
    """Write points (N, 3) mm with RGB colours (N, 3) in [0, 1] as a binary PLY, atomically.

    Coordinates are doubles, colours 8-bit; ``deviation`` (N,) mm, when given, is an extra
    ``double deviation`` vertex property, which CloudCompare reads as a scalar field.
    """
    import open3d as o3d

    path = Path(path)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c = np.clip(np.asarray(colours, dtype=np.float64).reshape(-1, 3), 0.0, 1.0)
    if len(p) != len(c):
        raise ValueError(f"points ({len(p)}) and colours ({len(c)}) differ in number")
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(p)))
    pc.point.colors = o3d.core.Tensor(np.rint(c * 255.0).astype(np.uint8))
    if deviation is not None:
        dv = np.asarray(deviation, dtype=np.float64).reshape(-1, 1)
        if len(dv) != len(p):
            raise ValueError(f"points ({len(p)}) and deviations ({len(dv)}) differ in number")
        pc.point.deviation = o3d.core.Tensor(np.ascontiguousarray(dv))
    if len(p) == 0:
        raise CrosslineError(f"{path}: no points to write (PLY needs at least one)")
    path.parent.mkdir(parents=True, exist_ok=True)
    # Open3D picks the writer by the file's suffix: the temporary file must end in .ply
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.ply", dir=path.parent)
    os.close(fd)
    try:
        if not o3d.t.io.write_point_cloud(tmp, pc, write_ascii=False, compressed=False):
            raise CrosslineError(f"{path}: the coloured cloud could not be written")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def deviation_map_figure(
    points_nominal: np.ndarray,
    dev: np.ndarray,
    limit_mm: float,
    *,
    regions: list[dict[str, Any]] | None = None,
    tolerance_mm: float | None = None,
    max_points: int = 150_000,
    title: str | None = None,
    fig: Figure | None = None,
    rect: tuple[float, float, float, float] | None = None,
) -> Figure:
    """Top, front and side views of the part coloured by deviation, the histogram, a colour bar in mm.

    Views are orthographic along the nominal frame's axes (third-angle layout), nearest
    points drawn last; ``regions`` (from ``deviation_summary``) are marked and numbered
    at their centroids.
    """
    p = np.asarray(points_nominal, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dev, dtype=np.float64).reshape(-1)
    if len(p) != len(d):
        raise ValueError(f"points ({len(p)}) and deviations ({len(d)}) differ in number")
    lim = float(limit_mm)
    ok = np.flatnonzero(np.isfinite(d))
    if len(ok) > max_points:
        ok = np.sort(np.random.default_rng(0).choice(ok, max_points, replace=False))
    p, d = p[ok], d[ok]

    if fig is None:  # a figure of its own; else drawn into ``rect`` (left, bottom, right, top)
        fig = Figure(figsize=(11.0, 8.0), layout="constrained")
        grid = fig.add_gridspec(2, 2)
    else:
        left, bottom, right, top = rect or (0.08, 0.08, 0.92, 0.92)
        grid = fig.add_gridspec(2, 2, left=left, bottom=bottom, right=right, top=top,
                                wspace=0.35, hspace=0.35)
    # (axes position, horizontal axis, vertical axis, depth axis towards the viewer, name)
    views = (((0, 0), 0, 1, 2, "top (x-y)"), ((1, 0), 0, 2, 1, "front (x-z)"),
             ((1, 1), 1, 2, 0, "side (y-z)"))
    axes = []
    sc = None
    for (row, col), h, v, depth, name in views:
        ax = fig.add_subplot(grid[row, col])
        sign = -1.0 if depth == 1 else 1.0  # the front view looks along +y
        order = np.argsort(sign * p[:, depth], kind="stable")
        sc = ax.scatter(p[order, h], p[order, v], c=d[order], s=1.0, cmap=COLOUR_MAP,
                        vmin=-lim, vmax=lim, linewidths=0, rasterized=True)
        for g in regions or []:
            cxyz = g["centroid_mm"]
            ax.plot(cxyz[h], cxyz[v], marker="o", ms=9, mfc="none", mec="k", mew=1.2)
            ax.annotate(str(g.get("id", "")), (cxyz[h], cxyz[v]), xytext=(5, 5),
                        textcoords="offset points", fontsize=9, fontweight="bold")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("xyz"[h] + " (mm)")
        ax.set_ylabel("xyz"[v] + " (mm)")
        ax.set_title(name, fontsize=10)
        axes.append(ax)
    ax = fig.add_subplot(grid[0, 1])
    bins = np.linspace(-lim, lim, 61)
    ax.hist(np.clip(d, -lim, lim), bins=bins, color="0.35")
    if tolerance_mm is not None:
        for t in (-tolerance_mm, tolerance_mm):
            ax.axvline(t, color="k", ls="--", lw=1.0)
    ax.set_xlabel("deviation (mm), clipped at ±limit")
    ax.set_ylabel("points")
    ax.set_title("deviation histogram", fontsize=10)
    if sc is not None:
        bar = fig.colorbar(sc, ax=axes, shrink=0.8, extend="both")
        bar.set_label("deviation from nominal (mm), + = material excess")
    if title:
        fig.suptitle(title)
    return fig

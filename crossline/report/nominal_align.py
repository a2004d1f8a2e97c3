"""Align a scanned cloud to its nominal mesh: the coarse pose, the robust fine fit, its ambiguity.

``align_to_nominal`` (step 1 of :mod:`crossline.report.nominal`'s docstring): a coarse
``T_nominal_cloud`` from a datum or from seeded RANSAC on FPFH features (``_ransac``, each
hypothesis also tried turned half a turn about each axis), refined by Open3D's point-to-plane
step with a Tukey kernel on the mesh's exact closest points (``_refine``); and
``weakest_mode_ratio``, how firmly the fitted surface fixes the pose. Split from
``crossline.report.nominal`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import Any

import numpy as np

from crossline.errors import CrosslineError
from crossline.report.nominal_surface import _Surface
from crossline.robust import robust_sigma

__all__ = ["align_to_nominal", "weakest_mode_ratio"]

TUKEY_C = 4.685  # Tukey biweight constant: 95 % efficiency at Gaussian residuals
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


def _fpfh(pc: Any, voxel: float, what: str = "cloud") -> tuple[Any, Any]:
    """Voxel-downsampled cloud with outward-oriented normals and its FPFH features
    (ValueError naming ``what`` where the normals cannot be oriented: a flat surface)."""
    import open3d as o3d

    down = pc.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    # FPFH depends on the normals' sign: orient both clouds the same way (consistently
    # over the surface, then outward on the whole) or their features do not match
    try:
        down.orient_normals_consistent_tangent_plane(12)
    except RuntimeError as exc:  # Open3D's qhull: points all in one plane (or line) have no hull
        raise ValueError(
            f"the coarse alignment cannot orient the normals of the {what}: its {len(down.points)} "
            f"points (at {voxel:g} mm) lie in one plane or line ({str(exc).splitlines()[0].strip()}); "
            "a flat surface cannot be placed by its shape: give a datum (rig.yaml nominal_pose)") from None
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
        sigma = max(robust_sigma(r[use], about=0.0), sigma_floor)
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
    src, src_f = _fpfh(_to_cloud(points), voxel, "scanned cloud")
    dst, dst_f = _fpfh(nominal, voxel, "nominal mesh")
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

"""A laser's plane from the stripe points of all its poses, and how it follows the camera.

``robust_plane``: a least-median start from triples drawn across poses, then trimmed,
weighted least squares, each noise group (pose and albedo class) trimmed and weighted by its
own robust sigma (``group_sigma``); ``camera_jacobian``: how the fitted plane moves with the
camera's parameters, the board poses found again with each changed camera. Split from
``crossline.calibrate.lasers`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

import numpy as np

from crossline.board import Board
from crossline.calibrate.laser_board import board_plane_points
from crossline.calibrate.laser_stripe import PoseStripe
from crossline.calibrate.pose import board_pose
from crossline.camera import Camera
from crossline.geometry import fit_plane, plane_distance, plane_tilt_basis
from crossline.robust import robust_sigma

__all__ = ["camera_jacobian", "group_sigma", "robust_plane"]

def group_sigma(residuals: np.ndarray, groups: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """Each point's noise (N,): the robust sigma (1.4826 MAD) of its group's inlier residuals
    (all of the group's where fewer than 5 are inliers)."""
    r = np.asarray(residuals, dtype=np.float64)
    sigma = np.empty(len(r))
    for k in np.unique(groups):
        mk = groups == k
        rk = r[mk & inliers] if (mk & inliers).sum() >= 5 else r[mk]
        sigma[mk] = robust_sigma(rk)
    return np.maximum(sigma, 1e-12)


def robust_plane(
    points: np.ndarray,
    trim: float = 3.0,
    samples: int = 300,
    seed: int = 0,
    groups: np.ndarray | None = None,
    noise_groups: np.ndarray | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Plane ``(n, d)`` through points (N, 3) and the inlier mask: LMedS start, trimmed LSQ.

    ``noise_groups`` (N,) labels points that share a noise level (e.g. pose and albedo class:
    where the noise is additive, the stripe on the dark class is the noisier; where speckle
    rules, it is not). Each group's robust sigma, measured on the residuals, trims it and
    weights it (1 / sigma^2) in the least squares; by default one sigma for all.

    ``groups`` (N,) names the board pose of each point. One pose's stripe is a line, and
    the plane of its board holds it exactly: with poses of unequal size a plain median would
    pick that board plane. So each candidate plane is drawn from two poses or more and
    scored by the median, over poses, of each pose's median residual (the largest of
    them for two poses): the plane must fit most poses, not most points.
    """
    p = np.asarray(points, dtype=np.float64)
    rng = np.random.default_rng(seed)
    g = np.zeros(len(p), dtype=np.int64) if groups is None else np.unique(groups, return_inverse=True)[1]
    ng = int(g.max()) + 1 if len(g) else 0
    idx = rng.integers(0, len(p), size=(samples * (4 if ng > 1 else 1), 3))
    if ng > 1:
        idx = idx[~((g[idx[:, 0]] == g[idx[:, 1]]) & (g[idx[:, 1]] == g[idx[:, 2]]))][:samples]
    a, b, c = p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]]
    nn = np.cross(b - a, c - a)
    norm = np.linalg.norm(nn, axis=1)
    ok = norm > 1e-9 * np.max(norm)
    nn = nn[ok] / norm[ok, None]
    dd = -np.sum(nn * a[ok], axis=1)
    res = np.abs(p @ nn.T + dd)
    per_pose = np.stack([np.median(res[g == k], axis=0) for k in range(ng)])
    med = per_pose.max(axis=0) if ng == 2 else np.median(per_pose, axis=0)
    best = int(np.argmin(med))
    n, d = nn[best], dd[best]
    ng_ = np.zeros(len(p), dtype=np.int64) if noise_groups is None else \
        np.unique(noise_groups, return_inverse=True)[1]
    inl = np.ones(len(p), dtype=bool)
    for _ in range(50):
        r = plane_distance(p, n, d)
        sigma = group_sigma(r, ng_, inl)
        new = np.abs(r) <= trim * sigma
        if new.sum() < 3:
            break
        n, d = fit_plane(p[new], 1.0 / sigma[new] ** 2)
        if np.array_equal(new, inl):
            break
        inl = new
    return n, float(d), inl


def camera_jacobian(
    camera: Camera, board: Board, stripes: list[PoseStripe], inliers: np.ndarray,
    weights: np.ndarray, normal: np.ndarray, d: float, steps: np.ndarray,
) -> np.ndarray:
    """How the fitted plane follows the camera: d(tilt e1, tilt e2, d) / d(fx fy cx cy k1 k2 p1
    p2 k3), (3, 9), by central differences of ``steps`` (9,).

    For each step every board pose is found again with the changed camera (PnP on the same
    detected points), its stripe pixels are carried onto that board plane and the plane is
    fitted again to the same inliers with the same weights. A camera error moves the planes
    with it, so that near the boards triangulation partly undoes it: drawing the camera and
    the planes independently would miss that.
    """
    E = plane_tilt_basis(normal)
    J = np.zeros((3, 9))
    for j in range(9):
        vals = []
        for sign in (1.0, -1.0):
            x = np.zeros(9)
            x[j] = sign * steps[j]
            cam = camera.perturbed(x)
            pts = np.concatenate([
                board_plane_points(cam, board_pose(cam, board, st.board_points,
                                                   bias_correction=st.bias_correction).T_cam_board,
                                   st.uv) for st in stripes])
            n, dd = fit_plane(pts[inliers], weights)
            if n @ normal < 0:
                n, dd = -n, -dd
            vals.append(np.array([(n - normal) @ E[0], (n - normal) @ E[1], dd - d]))
        J[:, j] = (vals[0] - vals[1]) / (2 * steps[j])
    return J

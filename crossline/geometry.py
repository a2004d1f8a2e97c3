"""Rigid transforms, quaternions, and least-squares plane and sphere fits.

Conventions (``shared/DESIGN.md`` §1): lengths in mm, angles in radians, ``T_a_b`` maps
coordinates in frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``), quaternions are
``(qw, qx, qy, qz)``, planes are ``n · p + d = 0`` with ``|n| = 1``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "angle_between",
    "fit_plane",
    "fit_sphere",
    "invert_transform",
    "make_transform",
    "matrix_to_quat",
    "matrix_to_rotvec",
    "orthonormalize",
    "plane_covariance",
    "plane_distance",
    "plane_line_intersection",
    "plane_tilt_basis",
    "quat_to_matrix",
    "rotation_angle",
    "rotvec_to_matrix",
    "transform_from_pose",
    "transform_points",
    "transform_to_pose",
]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) ordered (qw, qx, qy, qz)."""
    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q, scalar_first=True).as_matrix()


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) ordered (qw, qx, qy, qz) with qw >= 0 from rotations."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat(scalar_first=True)
    return np.where(q[..., :1] < 0, -q, q)


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (axis × angle, radians)."""
    return Rotation.from_rotvec(np.asarray(rv, dtype=np.float64)).as_matrix()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) (axis × angle, radians) from rotation matrices."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle in radians of rotation matrices (..., 3, 3), in [0, pi]."""
    R = np.asarray(R, dtype=np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    # arccos is ill-conditioned near 0; combine with the skew part for full precision.
    s = 0.5 * np.linalg.norm(
        np.stack(
            [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
            axis=-1,
        ),
        axis=-1,
    )
    return np.arctan2(s, c)


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest proper rotation (Frobenius norm) to a 3×3 matrix, by SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ D @ Vt


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4×4 homogeneous transform (..., 4, 4) from rotations (..., 3, 3) and translations (..., 3)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4), using the rotation's transpose."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_transform(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def transform_points(T: np.ndarray, p: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
    """Apply a transform (4, 4) or per-point transforms (N, 4, 4) to points (N, 3).

    With ``index`` (N,), ``T`` holds one transform per frame (F, 4, 4) and point i is moved by
    ``T[index[i]]``: ``transform_points(T[index], p)`` up to rounding (the last bit), frame
    by frame, without an (N, 4, 4) array.
    """
    T = np.asarray(T, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    if index is not None:
        idx = np.asarray(index)
        if idx.dtype.kind not in "iu":  # an int32 index stays one: no copy of a long scan's
            idx = idx.astype(np.int64)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or idx.ndim != 1 or p.shape != (idx.size, 3):
            raise ValueError(f"with an index, T must be (F, 4, 4), index (N,) and p (N, 3); got "
                             f"T {T.shape}, index {idx.shape}, p {p.shape}")
        in_order = idx.size < 2 or bool(np.all(idx[1:] >= idx[:-1]))
        order = None if in_order else np.argsort(idx, kind="stable")
        s = idx if order is None else idx[order]
        cut = np.flatnonzero(s[1:] != s[:-1]) + 1
        out = np.empty((idx.size, 3))
        for a, b in zip(np.r_[0, cut].tolist(), np.r_[cut, idx.size].tolist(), strict=True):
            if a == b:
                continue
            M = T[s[a]]
            sel = slice(a, b) if order is None else order[a:b]
            out[sel] = p[sel] @ M[:3, :3].T + M[:3, 3]
        return out
    if T.ndim == 2:
        return p @ T[:3, :3].T + T[:3, 3]
    return np.einsum("...ij,...j->...i", T[..., :3, :3], p) + T[..., :3, 3]


def transform_from_pose(xyz: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Transforms (..., 4, 4) from positions (..., 3) in mm and quaternions (..., 4) (qw, qx, qy, qz).

    The quaternion is normalised first; callers validate that it was close to unit length.
    """
    quat = np.asarray(quat, dtype=np.float64)
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    return make_transform(quat_to_matrix(quat), xyz)


def transform_to_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (..., 3) and quaternions (..., 4) (qw, qx, qy, qz) of transforms (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), matrix_to_quat(T[..., :3, :3])


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in radians between vectors (..., 3), robust for nearly parallel vectors."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def fit_plane(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Total-least-squares plane ``n · p + d = 0`` through points (N, 3), N >= 3.

    The normal is oriented so that ``d <= 0`` (the origin lies on the side the normal
    points away from), which keeps planes comparable across fits.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise ValueError(f"fit_plane needs an (N, 3) array with N >= 3, got shape {p.shape}")
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=np.float64)
    c = (w[:, None] * p).sum(0) / w.sum()
    _, _, Vt = np.linalg.svd(np.sqrt(w)[:, None] * (p - c), full_matrices=False)
    n = Vt[2]
    d = -float(n @ c)
    if d > 0:
        n, d = -n, -d
    return n, d


def plane_tilt_basis(normal: np.ndarray) -> np.ndarray:
    """Two unit vectors (2, 3) orthogonal to ``normal`` and to each other: the axes along which
    :func:`plane_covariance` tilts a plane (``n' ∝ n + a e1 + b e2``)."""
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


def plane_covariance(
    points: np.ndarray, normal: np.ndarray, d: float, *,
    weights: np.ndarray | None = None, clusters: np.ndarray | None = None,
) -> np.ndarray:
    """Covariance (3, 3) of a least-squares plane's tilts ``(a, b)`` along
    :func:`plane_tilt_basis` (rad) and its offset ``d`` (mm), from the points it was fitted to.

    With ``weights`` (N,) of ``1 / sigma_i^2`` the fit's information matrix ``H = J^T W J``,
    scaled by the weighted residual variance, gives the covariance for independent errors.
    Points of one ``cluster`` (N,) (a board pose: its stripe moves with the pose's error)
    share an error; the cluster-robust (sandwich) covariance
    ``H^-1 (sum_g s_g s_g^T) H^-1 G / (G - 1)``, ``s_g = sum_{i in g} w_i r_i J_i``, measures
    that from the scatter between clusters. The larger of the two in every direction is
    returned: with few clusters the sandwich alone can miss a direction the points still
    constrain only so well.
    """
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=np.float64)
    E = plane_tilt_basis(n)
    J = np.column_stack([p @ E[0], p @ E[1], np.ones(len(p))])
    r = p @ n + d
    H = (J * w[:, None]).T @ J
    Hi = np.linalg.inv(H)
    scale = float(np.sum(w * r**2) / max(len(p) - 3, 1))
    C = scale * Hi
    if clusters is not None:
        g = np.unique(clusters, return_inverse=True)[1]
        G = int(g.max()) + 1
        if G > 1:
            S = np.zeros((G, 3))
            np.add.at(S, g, (w * r)[:, None] * J)
            Cs = Hi @ (S.T @ S) @ Hi * (G / (G - 1))
            # add what the sandwich finds beyond the independent-error covariance
            L = np.linalg.cholesky(C)
            Li = np.linalg.inv(L)
            vals, vecs = np.linalg.eigh(Li @ Cs @ Li.T)
            extra = vecs @ np.diag(np.maximum(vals - 1.0, 0.0)) @ vecs.T
            C = C + L @ extra @ L.T
    return 0.5 * (C + C.T)


def plane_distance(points: np.ndarray, normal: np.ndarray, d: float) -> np.ndarray:
    """Signed distances (N,) of points (N, 3) to the plane ``n · p + d = 0``."""
    n = np.asarray(normal, dtype=np.float64)
    r = np.asarray(points, dtype=np.float64) @ n
    r /= np.linalg.norm(n)  # in place: a long scan's distances are 8 B a point each
    r += d / np.linalg.norm(n)
    return r


def plane_line_intersection(
    n1: np.ndarray, d1: float, n2: np.ndarray, d2: float
) -> tuple[np.ndarray, np.ndarray]:
    """Line where two planes meet: a point on it (closest to the origin) and a unit direction."""
    n1 = np.asarray(n1, dtype=np.float64)
    n2 = np.asarray(n2, dtype=np.float64)
    u = np.cross(n1, n2)
    norm = np.linalg.norm(u)
    if norm < 1e-12:
        raise ValueError("the planes are parallel: they have no line of intersection")
    A = np.stack([n1, n2, u])
    p = np.linalg.solve(A, np.array([-d1, -d2, 0.0]))
    return p, u / norm


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Geometric least-squares sphere through points (N, 3), N >= 4.

    Returns the centre (3,), the radius and the radial residuals (N,) (distance to the
    centre minus the radius). The algebraic fit seeds a Levenberg–Marquardt refinement of
    the orthogonal distances, as ISO 10360 asks for.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4:
        raise ValueError(f"fit_sphere needs an (N, 3) array with N >= 4, got shape {p.shape}")
    c0 = p.mean(0)
    q = p - c0
    A = np.column_stack([2 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(A, (q**2).sum(1), rcond=None)
    centre = sol[:3]
    r = np.sqrt(sol[3] + centre @ centre)

    def residual(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(q - x[:3], axis=1) - x[3]

    from scipy.optimize import least_squares  # imported here: the scan stages never fit a sphere

    res = least_squares(residual, np.r_[centre, r], method="lm", xtol=1e-15, ftol=1e-15)
    centre, r = res.x[:3], float(res.x[3])
    return centre + c0, r, residual(res.x)

"""Measure calibrated artefacts in point clouds: gauge block, plane, sphere, freeform part.

Every function takes arrays (points (N, 3) in mm, base frame) and returns a small result
object whose ``figures()`` are the plain numbers a report prints; the per-point arrays it
also holds (heights, residuals, masks) are for plots. Nothing here reads files.

Conventions: lengths in mm, angles in radians inside (``_deg`` in figure names), planes
``n · p + d = 0`` with ``|n| = 1``. Random sampling (RANSAC) uses a fixed seed, so every
result is reproducible.

The figures follow the paper and the standards a metrologist expects:

- gauge block (the paper's Fig. 10): the distance of every top-face point to the plane of
  the surface plate the block stands on, away from the block's edges; beside it the
  central length (ISO 3650 style: from the top face's centre to the plate plane) and the
  parallelism of the two faces;
- plane (the paper's Fig. 16): distances to the least-squares plane, the share within a
  band (±0.05 mm), flatness as the full range and as the 2.5–97.5 % range;
- sphere (ISO 10360-8 PSize / PForm): least-squares sphere on the RANSAC inliers, size
  error = fitted − nominal diameter, form error = range of radial residuals, for all points
  and for the 95 % closest to the sphere (``PForm.Sph.D95%``);
- freeform: signed distance of every point to a reference mesh (float64 refinement).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import ConvexHull, QhullError

from crossline.geometry import angle_between, fit_sphere, plane_distance, rotation_angle, rotvec_to_matrix
from crossline.scan.labels import nearest_in_column

__all__ = [
    "ABComparison",
    "GaugeResult",
    "PlaneResult",
    "SphereResult",
    "camera_error",
    "compare_lasers",
    "deviation_stats",
    "fit_plane",
    "frame_rotation",
    "label_errors",
    "laser_codes",
    "laser_plane_error",
    "measure_gauge_block",
    "measure_plane",
    "measure_sphere",
    "mesh_signed_distance",
    "plane_basis",
    "plane_offset",
    "point_triangle_closest",
    "ransac_plane",
    "ransac_sphere",
    "robust_sigma",
    "sphere_by_incidence",
    "transform_error",
    "volume_points",
]

MIN_POINTS = 20  # fewest points for a figure to be reported at all


def robust_sigma(x: np.ndarray) -> float:
    """Standard deviation estimated from the median absolute deviation (1.4826 · MAD)."""
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def _subsample(n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of at most ``size`` of ``n`` items (all of them when n <= size)."""
    if n <= size:
        return np.arange(n)
    return np.sort(rng.choice(n, size=size, replace=False))


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares plane ``n · p + d = 0`` of points (N, 3), oriented so that ``d <= 0``.

    The same plane as ``crossline.geometry.fit_plane`` (which takes the SVD of the whole
    N × 3 matrix), from the 3 × 3 scatter matrix of the centred points instead: ten times
    quicker on the half-million points of a scan, and as exact for clouds of mm size
    (tests compare the two).
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise ValueError(f"fit_plane needs an (N, 3) array with N >= 3, got shape {p.shape}")
    c = p.mean(0)
    q = p - c
    _, V = np.linalg.eigh(q.T @ q)
    n = V[:, 0]
    d = -float(n @ c)
    if d > 0:
        n, d = -n, -d
    return n, d


def laser_codes(laser: np.ndarray) -> np.ndarray:
    """Laser of each point as uint8 codes 1 = A, 2 = B, 0 = other, from codes or labels."""
    lab = np.asarray(laser)
    if lab.dtype.kind in "OUS":
        s = lab.astype(str)
        return np.select([s == "A", s == "B"], [1, 2], 0).astype(np.uint8)
    return lab.astype(np.uint8)


def _orient(n: np.ndarray, d: float, up: np.ndarray | None) -> tuple[np.ndarray, float]:
    if up is not None and float(n @ up) < 0:
        return -n, -d
    return n, d


# ----------------------------------------------------------------------------- RANSAC


def ransac_plane(
    points: np.ndarray,
    threshold: float,
    *,
    iterations: int = 300,
    sample: int = 20000,
    seed: int = 0,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Dominant plane of points (N, 3): RANSAC on a subsample, then least squares on the inliers.

    Returns the unit normal, ``d`` and the inlier mask (N,) (``|distance| < threshold``).
    The candidates are scored together (one matrix product), so 300 iterations on 20 000
    points take milliseconds.
    """
    p = np.asarray(points, dtype=np.float64)
    if len(p) < 3:
        raise ValueError(f"ransac_plane needs at least 3 points, got {len(p)}")
    rng = np.random.default_rng(seed)
    sub = p[_subsample(len(p), sample, rng)]
    c0 = sub.mean(0)
    q = sub - c0
    tri = rng.integers(0, len(q), size=(iterations, 3))
    a, b, c = q[tri[:, 0]], q[tri[:, 1]], q[tri[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12 * max(1.0, float(np.abs(q).max()) ** 2)
    if not ok.any():
        raise ValueError("ransac_plane: all samples are degenerate (collinear points)")
    n = n[ok] / norm[ok, None]
    d = -np.sum(n * a[ok], axis=1)
    score = np.zeros(len(n), dtype=np.int64)
    for s in range(0, len(n), 64):  # bounded memory: (sample, 64) distances at a time
        score[s : s + 64] = (np.abs(q @ n[s : s + 64].T + d[s : s + 64]) < threshold).sum(0)
    best = int(np.argmax(score))
    nb, db = n[best], float(d[best] - n[best] @ c0)
    inl = np.abs(p @ nb + db) < threshold
    for _ in range(3):  # least squares on the inliers, then re-select: converges in 1-2 steps
        if inl.sum() < 3:
            break
        nb, db = fit_plane(p[inl])
        new = np.abs(p @ nb + db) < threshold
        if np.array_equal(new, inl):
            break
        inl = new
    return nb, db, inl


def _spheres_from_4(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (M, 3), radii (M,) and validity (M,) of spheres through point quadruples (M, 4, 3)."""
    A = np.concatenate([2 * p, np.ones((*p.shape[:2], 1))], axis=2)
    rhs = (p**2).sum(2)
    det = np.linalg.det(A)
    scale = np.abs(p - p.mean(1, keepdims=True)).max(axis=(1, 2)) ** 3 + 1e-30
    ok = np.abs(det) > 1e-9 * scale
    sol = np.zeros((len(p), 4))
    sol[ok] = np.linalg.solve(A[ok], rhs[ok][..., None])[..., 0]
    c = sol[:, :3]
    r2 = sol[:, 3] + (c**2).sum(1)
    ok &= r2 > 0
    return c, np.sqrt(np.where(ok, r2, 0.0)), ok


def ransac_sphere(
    points: np.ndarray,
    radius: float,
    threshold: float,
    *,
    iterations: int = 2000,
    sample: int = 20000,
    radius_tolerance: float = 0.1,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Sphere of about the nominal ``radius`` among points (N, 3) (stem, plate and all).

    Spheres through random point quadruples whose radius is within ``radius_tolerance``
    (relative) of the nominal one are scored by their points within ``threshold``.
    Returns the best candidate's centre and its inlier mask (N,).
    """
    p = np.asarray(points, dtype=np.float64)
    if len(p) < 4:
        raise ValueError(f"ransac_sphere needs at least 4 points, got {len(p)}")
    rng = np.random.default_rng(seed)
    sub = p[_subsample(len(p), sample, rng)]
    c0 = sub.mean(0)
    q = sub - c0
    quad = q[rng.integers(0, len(q), size=(iterations, 4))]
    c, r, ok = _spheres_from_4(quad)
    ok &= np.abs(r - radius) < radius_tolerance * radius
    if not ok.any():
        raise ValueError(
            f"ransac_sphere: no sphere of radius {radius:g} mm ± {100 * radius_tolerance:g} % "
            f"among {len(p)} points"
        )
    c = c[ok]
    score = np.zeros(len(c), dtype=np.int64)
    for s in range(0, len(c), 64):
        dist = np.linalg.norm(q[:, None, :] - c[None, s : s + 64], axis=2)
        score[s : s + 64] = (np.abs(dist - radius) < threshold).sum(0)
    centre = c[int(np.argmax(score))] + c0
    inl = np.abs(np.linalg.norm(p - centre, axis=1) - radius) < threshold
    return centre, inl


# ----------------------------------------------------------------------------- plane


@dataclass(frozen=True)
class PlaneResult:
    """Least-squares plane of a flat artefact and the distances of its points to it."""

    normal: np.ndarray
    d: float
    distances: np.ndarray  # (N,) signed, mm
    band_mm: float

    def figures(self) -> dict[str, Any]:
        """The plain numbers: n, RMS, share within the band, flatness (full and 95 %)."""
        r = self.distances
        lo, hi = np.percentile(r, [2.5, 97.5])
        return {
            "n": int(r.size),
            "normal": self.normal.tolist(),
            "d_mm": self.d,
            "mean_mm": float(r.mean()),
            "std_mm": float(r.std(ddof=1)) if r.size > 1 else 0.0,
            "rms_mm": float(np.sqrt(np.mean(r**2))),
            "band_mm": self.band_mm,
            "share_within_band": float(np.mean(np.abs(r) <= self.band_mm)),
            "flatness_mm": float(r.max() - r.min()),
            "flatness_95_mm": float(hi - lo),
            "min_mm": float(r.min()),
            "max_mm": float(r.max()),
        }


def measure_plane(
    points: np.ndarray, *, band_mm: float = 0.05, up: np.ndarray | None = None
) -> PlaneResult:
    """Least-squares plane of every point (the paper's Fig. 16) and the distances to it."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) < MIN_POINTS:
        raise ValueError(f"measure_plane needs at least {MIN_POINTS} points, got {len(p)}")
    n, d = _orient(*fit_plane(p), up)
    return PlaneResult(n, d, plane_distance(p, n, d), band_mm)


def plane_offset(
    plane_a: tuple[np.ndarray, float], plane_b: tuple[np.ndarray, float], at: np.ndarray
) -> tuple[float, float]:
    """Offset (mm) of plane b from plane a measured at point ``at`` along a's normal, and their angle (rad).

    The offset is the distance from ``at``'s projection on plane a to plane b, along a's
    normal: what a height gauge would read between the two planes there.
    """
    na, da = plane_a
    nb, db = plane_b
    if float(na @ nb) < 0:
        nb, db = -nb, -db
    foot = at - (at @ na + da) * na
    # along a's normal from the foot to plane b: t with nb·(foot + t·na) + db = 0
    t = -(foot @ nb + db) / float(na @ nb)
    return float(t), float(angle_between(na, nb))


# ----------------------------------------------------------------------------- gauge block


@dataclass(frozen=True)
class GaugeResult:
    """Height of a gauge block standing on a surface plate, from one point cloud."""

    nominal_mm: float
    plate_normal: np.ndarray  # points up, from the plate towards the top face
    plate_d: float
    top_normal: np.ndarray
    top_d: float
    heights: np.ndarray  # (n_top,) height of each top-face point (see ``reference``)
    top_mask: np.ndarray  # (N,) top-face points used (away from the edges)
    plate_mask: np.ndarray  # (N,) plate points used (away from the block)
    plate_residuals: np.ndarray  # (n_plate,)
    central_length_mm: float
    length_variation_mm: float
    edge_margin_mm: float
    # "frame": each height is referenced to the plate as seen in the same frame; "plane": to
    # the plate plane fitted over the whole scan (the paper's Fig. 10)
    reference: str = "plane"
    heights_plane: np.ndarray | None = None  # (n,) the paper's heights of the same points
    frame_offsets: np.ndarray | None = None  # per-frame plate offset from the plate plane, mm

    def figures(self) -> dict[str, Any]:
        """Mean, std, n, error of the mean against nominal, and the extra figures."""
        h = self.heights
        n = int(h.size)
        std = float(h.std(ddof=1)) if n > 1 else 0.0
        mean = float(h.mean())
        return {
            "nominal_mm": self.nominal_mm,
            "n": n,
            "n_plate": int(self.plate_mask.sum()),
            "mean_mm": mean,
            "std_mm": std,
            "error_mm": mean - self.nominal_mm,
            "sem_mm": std / np.sqrt(n) if n else float("nan"),
            "median_mm": float(np.median(h)),
            "min_mm": float(h.min()),
            "max_mm": float(h.max()),
            "central_length_mm": self.central_length_mm,
            "central_length_error_mm": self.central_length_mm - self.nominal_mm,
            "length_variation_mm": self.length_variation_mm,
            "parallelism_deg": float(np.degrees(angle_between(self.plate_normal, self.top_normal))),
            "plate_rms_mm": float(np.sqrt(np.mean(self.plate_residuals**2))),
            "plate_normal": self.plate_normal.tolist(),
            "plate_d_mm": self.plate_d,
            "edge_margin_mm": self.edge_margin_mm,
            "reference": self.reference,
            **(
                {
                    "plane_reference_mean_mm": float(self.heights_plane.mean()),
                    "plane_reference_std_mm": float(self.heights_plane.std(ddof=1)),
                    "plane_reference_error_mm": float(self.heights_plane.mean()) - self.nominal_mm,
                    "frames": int(self.frame_offsets.size),
                    "frame_offset_std_mm": float(self.frame_offsets.std(ddof=1))
                    if self.frame_offsets.size > 1 else 0.0,
                }
                if self.heights_plane is not None and self.frame_offsets is not None
                else {}
            ),
        }


def plane_basis(n: np.ndarray) -> np.ndarray:
    """Two orthonormal vectors (2, 3) spanning the plane with unit normal n (right-handed with n)."""
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


def _hull_signed_distance(hull_eq: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Signed distance of 2-D points to a convex polygon: < 0 inside (exact), > 0 outside.

    Outside, the largest edge-line distance is used: exact beside an edge, smaller than the
    true distance near a corner (so a margin test excludes slightly more there, never less
    inside).
    """
    out = np.empty(len(xy))
    for s in range(0, len(xy), 65536):  # bounded memory: (chunk, E) at a time
        out[s : s + 65536] = (xy[s : s + 65536] @ hull_eq[:, :2].T + hull_eq[:, 2]).max(axis=1)
    return out


def _polygon_centroid(v: np.ndarray) -> np.ndarray:
    """Area centroid of a polygon (M, 2) given in order."""
    x, y = v[:, 0], v[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    a = cross.sum() / 2
    if abs(a) < 1e-12:
        return v.mean(0)
    return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6 * a)


def _hull(xy: np.ndarray) -> ConvexHull | None:
    try:
        return ConvexHull(xy)
    except (QhullError, ValueError):
        return None


def _edges(hull: ConvexHull, min_length: float = 0.5) -> np.ndarray:
    """The hull's edge lines (E, 3), without the many tiny edges noise puts at its corners.

    Leaving out an edge enlarges the polygon only at a corner, by less than the edge's
    length: inside it, distances to the long edges that remain are unchanged.
    """
    v = hull.points[hull.simplices]
    length = np.linalg.norm(v[:, 1] - v[:, 0], axis=1)
    keep = length >= min_length
    if keep.sum() < 3:
        keep = length >= np.sort(length)[-3]
    return hull.equations[keep]


def measure_gauge_block(
    points: np.ndarray,
    nominal_height: float,
    *,
    edge_margin_mm: float = 1.0,
    band_mm: float = 0.2,
    up: np.ndarray | None = None,
    seed: int = 0,
    frame: np.ndarray | None = None,
    min_frame_points: int = 20,
) -> GaugeResult:
    """Height of a gauge block on a surface plate: every top-face point against the plate plane.

    1. RANSAC finds the dominant plane; the other face is the densest layer of points near
       ``±nominal_height`` from it (a height histogram), refined by RANSAC within it.
    2. The lower of the two (along ``up``, the direction towards the scanner, if given;
       otherwise the face with the larger footprint) is the plate.
    3. Top-face points closer than ``edge_margin_mm`` to the face's outline (convex hull) and
       plate points closer than that to the block's footprint are left out: there the stripe
       runs over the edge and mixes the two levels.
    4. The plate plane is fitted by least squares to the remaining plate points; the height
       of each remaining top point is its distance to that plane.

    ``band_mm`` is the half-width of the layer that counts as a face.

    With ``frame`` (the frame of each point), every height is referenced to the plate *as
    seen in the same frame*: the mean offset of that frame's plate points from the plate plane
    is subtracted from its top points' heights (frames with fewer than ``min_frame_points``
    plate points are left out). The stripe crosses plate and top face in one exposure, so the
    arm's pose error of that frame, common to both, cancels: what a line profiler does for a
    step height. The paper's plane-referenced heights are kept in ``heights_plane``.
    """
    p = np.asarray(points, dtype=np.float64)
    if len(p) < 2 * MIN_POINTS:
        raise ValueError(f"measure_gauge_block needs at least {2 * MIN_POINTS} points, got {len(p)}")
    up = None if up is None else np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    n1, d1, in1 = ransac_plane(p, band_mm, seed=seed)
    h = p @ n1 + d1
    window = max(0.25 * nominal_height, 5 * band_mm)
    best: tuple[int, float] | None = None
    for sign in (1.0, -1.0):
        sel = np.abs(h - sign * nominal_height) < window
        if sel.sum() < MIN_POINTS:
            continue
        # the densest band_mm-wide layer in the window: histogram of heights
        edges = np.arange(sign * nominal_height - window, sign * nominal_height + window + band_mm,
                          band_mm)
        counts, _ = np.histogram(h[sel], bins=edges)
        k = int(np.argmax(counts))
        if best is None or counts[k] > best[0]:
            best = (int(counts[k]), float((edges[k] + edges[k + 1]) / 2))
    if best is None or best[0] < MIN_POINTS:
        raise ValueError(
            f"measure_gauge_block: found one face but no second face {nominal_height:g} mm "
            f"(± {window:g} mm) from it"
        )
    layer = np.abs(h - best[1]) < 2 * band_mm
    _, _, in2l = ransac_plane(p[layer], band_mm, seed=seed + 1)
    in2 = np.zeros(len(p), dtype=bool)
    in2[np.flatnonzero(layer)[in2l]] = True
    in1 &= ~in2

    basis = plane_basis(n1)
    hull1 = _hull(p[in1] @ basis.T)
    hull2 = _hull(p[in2] @ basis.T)
    if hull1 is None or hull2 is None:
        raise ValueError("measure_gauge_block: a face's points are degenerate (collinear)")
    if up is not None:
        # the face farther along `up` is the top; plane 2 lies at signed height best[1] from plane 1
        first_is_plate = (best[1] > 0) == (float(n1 @ up) > 0)
    else:
        first_is_plate = hull1.volume >= hull2.volume  # ConvexHull.volume is the area in 2-D
    if first_is_plate:
        plate_in, top_in, top_hull = in1, in2, hull2
        plate_n, plate_d = fit_plane(p[in1])
    else:
        plate_in, top_in, top_hull = in2, in1, hull1
        plate_n, plate_d = fit_plane(p[in2])
    # orient the plate normal towards the top face
    if float(np.median(p[top_in] @ plate_n + plate_d)) < 0:
        plate_n, plate_d = -plate_n, -plate_d

    # top outline in the plate's own coordinates, so both faces share one footprint
    basis = plane_basis(plate_n)
    top_xy = p[top_in] @ basis.T
    top_hull = _hull(top_xy)
    if top_hull is None:
        raise ValueError("measure_gauge_block: the top face's points are collinear")
    eq = _edges(top_hull)
    top_mask = np.zeros(len(p), dtype=bool)
    top_mask[np.flatnonzero(top_in)[_hull_signed_distance(eq, top_xy) <= -edge_margin_mm]] = True
    plate_idx = np.flatnonzero(plate_in)
    plate_mask = np.zeros(len(p), dtype=bool)
    plate_mask[plate_idx[_hull_signed_distance(eq, p[plate_idx] @ basis.T) >= edge_margin_mm]] = True
    if top_mask.sum() < MIN_POINTS or plate_mask.sum() < MIN_POINTS:
        raise ValueError(
            f"measure_gauge_block: too few points away from the edges (top {int(top_mask.sum())}, "
            f"plate {int(plate_mask.sum())}); is the edge margin of {edge_margin_mm} mm too wide?"
        )
    plate_n, plate_d = fit_plane(p[plate_mask])
    if float(np.median(p[top_mask] @ plate_n + plate_d)) < 0:
        plate_n, plate_d = -plate_n, -plate_d
    heights = plane_distance(p[top_mask], plate_n, plate_d)
    heights_plane = frame_offsets = None
    reference = "plane"
    if frame is not None:
        frame = np.asarray(frame)
        ufr, inv = np.unique(frame[plate_mask], return_inverse=True)
        res = plane_distance(p[plate_mask], plate_n, plate_d)
        count = np.bincount(inv, minlength=ufr.size)
        offset = np.bincount(inv, weights=res, minlength=ufr.size) / np.maximum(count, 1)
        ufr, offset = ufr[count >= min_frame_points], offset[count >= min_frame_points]
        top_idx = np.flatnonzero(top_mask)
        k = np.zeros(top_idx.size, dtype=np.int64)
        seen = np.zeros(top_idx.size, dtype=bool)
        if ufr.size:
            k = np.clip(np.searchsorted(ufr, frame[top_idx]), 0, ufr.size - 1)
            seen = ufr[k] == frame[top_idx]
        if seen.sum() < MIN_POINTS:
            raise ValueError(
                f"measure_gauge_block: only {int(seen.sum())} top points lie in frames that also "
                f"see at least {min_frame_points} plate points; cannot reference per frame"
            )
        top_mask = np.zeros(len(p), dtype=bool)
        top_mask[top_idx[seen]] = True
        heights_plane = heights[seen]
        heights = heights_plane - offset[k[seen]]
        frame_offsets = offset
        reference = "frame"
    top_n, top_d = fit_plane(p[top_mask])
    if float(top_n @ plate_n) < 0:
        top_n, top_d = -top_n, -top_d

    # central length and variation: the top LSQ plane over the usable top outline
    basis = plane_basis(plate_n)
    inner_xy = p[top_mask] @ basis.T
    inner_hull = _hull(inner_xy)
    verts = inner_xy[inner_hull.vertices] if inner_hull is not None else inner_xy
    ctr = _polygon_centroid(verts)

    def top_height_at(xy: np.ndarray) -> np.ndarray:
        # point on the top plane above plate coordinates xy (along the plate normal)
        base = xy @ basis - plate_d * plate_n
        t = -(base @ top_n + top_d) / float(plate_n @ top_n)
        return t

    central = float(top_height_at(ctr[None])[0])
    corner_h = top_height_at(verts)
    return GaugeResult(
        nominal_mm=float(nominal_height),
        plate_normal=plate_n,
        plate_d=float(plate_d),
        top_normal=top_n,
        top_d=float(top_d),
        heights=heights,
        top_mask=top_mask,
        plate_mask=plate_mask,
        plate_residuals=plane_distance(p[plate_mask], plate_n, plate_d),
        central_length_mm=central,
        length_variation_mm=float(corner_h.max() - corner_h.min()),
        edge_margin_mm=float(edge_margin_mm),
        reference=reference,
        heights_plane=heights_plane,
        frame_offsets=frame_offsets,
    )


# ----------------------------------------------------------------------------- sphere


@dataclass(frozen=True)
class SphereResult:
    """Least-squares sphere of a reference ball (ISO 10360-8 PSize / PForm in spirit)."""

    nominal_diameter_mm: float
    centre: np.ndarray
    radius: float
    residuals: np.ndarray  # (n_inliers,) radial: distance to centre minus radius
    inlier_mask: np.ndarray  # (N,)

    def figures(self) -> dict[str, Any]:
        """Diameter, size error, form error (all points; 95 % closest; 99.7 % closest, as
        VDI/VDE 2634-2 allows discarding up to 0.3 %; 2.5-97.5 %), RMS."""
        r = self.residuals
        order = np.sort(np.abs(r))
        keep = order[: max(1, int(np.floor(0.95 * r.size)))]
        r95 = r[np.abs(r) <= keep[-1]]
        r997 = r[np.abs(r) <= order[max(0, r.size - 1 - int(np.floor(0.003 * r.size)))]]
        lo, hi = np.percentile(r, [2.5, 97.5])
        d = 2 * self.radius
        return {
            "nominal_diameter_mm": self.nominal_diameter_mm,
            "n": int(r.size),
            "n_total": int(self.inlier_mask.size),
            "centre_mm": self.centre.tolist(),
            "diameter_mm": d,
            "size_error_mm": d - self.nominal_diameter_mm,
            "form_error_mm": float(r.max() - r.min()),
            "form_error_d95_mm": float(r95.max() - r95.min()),
            "form_error_vdi_mm": float(r997.max() - r997.min()),
            "form_error_p95_mm": float(hi - lo),
            "rms_mm": float(np.sqrt(np.mean(r**2))),
        }


def measure_sphere(
    points: np.ndarray,
    nominal_diameter: float,
    *,
    ransac_threshold_mm: float = 0.2,
    trim_sigma: float = 5.0,
    min_band_mm: float = 0.002,
    seed: int = 0,
) -> SphereResult:
    """Least-squares sphere of a ball among other points (its stem, the plate under it).

    RANSAC with the nominal radius finds the ball; the least-squares sphere (geometric,
    ``fit_sphere``) is then fitted to its inliers and the inliers re-selected at
    ``trim_sigma`` robust sigmas (at least ``min_band_mm``), until they settle.
    """
    p = np.asarray(points, dtype=np.float64)
    radius = nominal_diameter / 2
    centre, inl = ransac_sphere(p, radius, ransac_threshold_mm, seed=seed)
    if inl.sum() < MIN_POINTS:
        raise ValueError(f"measure_sphere: only {int(inl.sum())} points lie on the ball")
    r = radius
    for _ in range(3):
        centre, r, res = fit_sphere(p[inl])
        band = max(trim_sigma * robust_sigma(res), min_band_mm)
        new = np.abs(np.linalg.norm(p - centre, axis=1) - r) < band
        if np.array_equal(new, inl) or new.sum() < MIN_POINTS:
            break
        inl = new
    centre, r, res = fit_sphere(p[inl])
    return SphereResult(float(nominal_diameter), centre, float(r), res, inl)


def sphere_by_incidence(
    points: np.ndarray, sphere: SphereResult, viewpoints: np.ndarray, *,
    band_deg: float = 10.0, max_incidence_deg: float = 60.0,
) -> dict[str, Any]:
    """Radial residuals of a sphere fit by angle of incidence, and the size from the steep part.

    The angle of incidence of a point is between the sphere's normal there and the direction
    to the camera that saw it (``viewpoints`` (N, 3), base frame). Near grazing incidence a
    stripe is wide and faint and its centre can be biased; the bands show whether it is, and
    the diameter fitted to the points seen within ``max_incidence_deg`` shows how much that
    moves the size.
    """
    p = np.asarray(points, dtype=np.float64)[sphere.inlier_mask]
    v = np.asarray(viewpoints, dtype=np.float64)[sphere.inlier_mask] - p
    r = p - sphere.centre
    cosang = np.sum(r * v, axis=1) / (np.linalg.norm(r, axis=1) * np.linalg.norm(v, axis=1))
    inc = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    res = sphere.residuals
    bands = []
    for lo in np.arange(0.0, 90.0, band_deg):
        m = (inc >= lo) & (inc < lo + band_deg)
        if m.sum() >= MIN_POINTS:
            bands.append({"from_deg": float(lo), "to_deg": float(lo + band_deg), "n": int(m.sum()),
                          "mean_residual_mm": float(res[m].mean()),
                          "std_residual_mm": float(res[m].std(ddof=1))})
    out: dict[str, Any] = {"bands": bands, "max_incidence_deg": float(max_incidence_deg)}
    steep = inc <= max_incidence_deg
    if steep.sum() >= MIN_POINTS:
        _, rad, _ = fit_sphere(p[steep])
        out["n_steep"] = int(steep.sum())
        out["size_error_steep_mm"] = 2 * rad - sphere.nominal_diameter_mm
    return out


# ----------------------------------------------------------------------------- A against B


@dataclass(frozen=True)
class ABComparison:
    """The same artefact measured from laser-A points alone and from laser-B points alone."""

    artefact: str
    a: dict[str, Any]
    b: dict[str, Any]
    difference: dict[str, Any]  # A minus B

    def figures(self) -> dict[str, Any]:
        """``{"A": ..., "B": ..., "A_minus_B": ...}``."""
        return {"artefact": self.artefact, "A": self.a, "B": self.b, "A_minus_B": self.difference}


def compare_lasers(
    artefact: str,
    points: np.ndarray,
    laser: np.ndarray,
    *,
    gauge: GaugeResult | None = None,
    plane: PlaneResult | None = None,
    sphere: SphereResult | None = None,
    band_mm: float = 0.05,
    min_spread_mm: float = 0.5,
) -> ABComparison | None:
    """Measure the artefact from laser-A and laser-B points separately, using the segmentation
    found on all points (so both lasers see the same faces, margins and inliers).

    ``laser`` holds ``"A"``/``"B"`` (or codes 1/2) per point. Returns None when either laser has fewer than
    ``MIN_POINTS`` points on the artefact; raises ValueError when one laser's points on a
    plane are too narrow (RMS width < ``min_spread_mm`` across their main direction) to
    define it.
    """
    p = np.asarray(points, dtype=np.float64)
    lab = laser_codes(laser)
    code = {"A": 1, "B": 2}
    out: dict[str, dict[str, Any]] = {}

    def surface_ok(m: np.ndarray, what: str, axis: int = 1) -> bool:
        # a laser's points along one line (its stripes all in the direction of motion)
        # define no plane: refuse rather than report a meaningless offset
        if m.sum() < MIN_POINTS:
            return False
        q = p[m] - p[m].mean(0)
        s = np.linalg.svd(q[:: max(1, len(q) // 20000)], compute_uv=False) / np.sqrt(
            len(q[:: max(1, len(q) // 20000)]))
        if s[axis] < min_spread_mm:
            shape = "along a line" if axis == 1 else "in one plane"
            raise ValueError(f"laser points on the {what} lie {shape} ({s[axis]:.3g} mm wide): "
                             f"they do not define the {what}")
        return True

    if artefact == "gauge_block":
        if gauge is None:
            raise ValueError("compare_lasers: the gauge comparison needs the all-points result")
        planes = {}
        for L in ("A", "B"):
            pm = gauge.plate_mask & (lab == code[L])
            tm = gauge.top_mask & (lab == code[L])
            if not surface_ok(pm, "plate") or tm.sum() < MIN_POINTS:
                return None
            n, d = fit_plane(p[pm])
            if float(n @ gauge.plate_normal) < 0:
                n, d = -n, -d
            planes[L] = (n, d)
            if gauge.reference == "frame":
                # each laser's top points, referenced per frame like the all-points heights
                h = gauge.heights[lab[gauge.top_mask] == code[L]]
            else:
                h = plane_distance(p[tm], n, d)
            out[L] = {"n": int(tm.sum()), "n_plate": int(pm.sum()), "mean_mm": float(h.mean()),
                      "std_mm": float(h.std(ddof=1))}
        at = p[gauge.plate_mask].mean(0)
        off, ang = plane_offset(planes["B"], planes["A"], at)
        diff = {"height_mm": out["A"]["mean_mm"] - out["B"]["mean_mm"],
                "plate_offset_mm": off, "plate_angle_deg": float(np.degrees(ang))}
    elif artefact == "plane":
        if plane is None:
            raise ValueError("compare_lasers: the plane comparison needs the all-points result")
        planes = {}
        for L in ("A", "B"):
            m = lab == code[L]
            if not surface_ok(m, "plane"):
                return None
            res = measure_plane(p[m], band_mm=band_mm, up=plane.normal)
            planes[L] = (res.normal, res.d)
            f = res.figures()
            out[L] = {k: f[k] for k in ("n", "rms_mm", "share_within_band", "flatness_mm",
                                        "flatness_95_mm")}
        off, ang = plane_offset(planes["B"], planes["A"], p.mean(0))
        diff = {"plane_offset_mm": off, "plane_angle_deg": float(np.degrees(ang))}
    elif artefact == "sphere":
        if sphere is None:
            raise ValueError("compare_lasers: the sphere comparison needs the all-points result")
        cs = {}
        for L in ("A", "B"):
            m = sphere.inlier_mask & (lab == code[L])
            if not surface_ok(m, "sphere", axis=2):
                return None
            c, r, res = fit_sphere(p[m])
            cs[L] = c
            out[L] = {"n": int(m.sum()), "diameter_mm": 2 * r, "centre_mm": c.tolist(),
                      "form_error_mm": float(res.max() - res.min())}
        dc = cs["A"] - cs["B"]
        diff = {"diameter_mm": out["A"]["diameter_mm"] - out["B"]["diameter_mm"],
                "centre_mm": dc.tolist(), "centre_distance_mm": float(np.linalg.norm(dc))}
    else:
        return None
    return ABComparison(artefact, out["A"], out["B"], diff)


# ----------------------------------------------------------------------------- freeform


def point_triangle_closest(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points (N, 3) on triangles (a, b, c) (each (N, 3)) to points p (N, 3), in float64.

    Ericson's region test (Real-Time Collision Detection, 5.1.5), vectorised.
    """
    p, a, b, c = (np.asarray(x, dtype=np.float64) for x in (p, a, b, c))
    ab, ac, ap = b - a, c - a, p - a
    d1 = (ab * ap).sum(1)
    d2 = (ac * ap).sum(1)
    bp = p - b
    d3 = (ab * bp).sum(1)
    d4 = (ac * bp).sum(1)
    cp = p - c
    d5 = (ab * cp).sum(1)
    d6 = (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        out = a + ab * v[:, None] + ac * w[:, None]  # inside the face
        # edges
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    e_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    out = np.where(e_bc[:, None], b + (c - b) * t_bc[:, None], out)
    e_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out = np.where(e_ac[:, None], a + ac * t_ac[:, None], out)
    e_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out = np.where(e_ab[:, None], a + ab * t_ab[:, None], out)
    # vertices (checked last: they take precedence)
    out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    return out


def mesh_signed_distance(
    points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray
) -> np.ndarray:
    """Signed distance (N,) in mm of points (N, 3) to a triangle mesh, positive on the normals' side.

    Open3D's ``RaycastingScene`` (float32) finds each point's closest triangle, in
    coordinates centred on the mesh to keep float32 rounding small; the distance to that
    triangle is then recomputed in float64, so it is exact to ~1e-12 mm whenever the
    closest triangle is right (a wrong one, within float32 rounding, differs by < 1e-5 mm).
    The sign is that of the triangle's normal (vertex order, counter-clockwise).
    """
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(triangles, dtype=np.int64)
    if len(p) == 0:
        return np.zeros(0)
    c0 = V.mean(0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((V - c0).astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32))
    )
    ans = scene.compute_closest_points(o3d.core.Tensor((p - c0).astype(np.float32)))
    tri = F[ans["primitive_ids"].numpy().astype(np.int64)]
    a, b, c = V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]]
    q = point_triangle_closest(p, a, b, c)
    delta = p - q
    dist = np.linalg.norm(delta, axis=1)
    normal = np.cross(b - a, c - a)
    side = np.sign((delta * normal).sum(1))
    return np.where(side < 0, -dist, dist)


def deviation_stats(dev: np.ndarray, band_mm: float = 0.05) -> dict[str, Any]:
    """Summary of signed deviations (mm): n, mean, std, RMS, 95th percentile of |dev|, share in band."""
    dev = np.asarray(dev, dtype=np.float64)
    if dev.size == 0:
        return {"n": 0}
    return {
        "n": int(dev.size),
        "mean_mm": float(dev.mean()),
        "std_mm": float(dev.std(ddof=1)) if dev.size > 1 else 0.0,
        "rms_mm": float(np.sqrt(np.mean(dev**2))),
        "abs_p95_mm": float(np.percentile(np.abs(dev), 95)),
        "max_abs_mm": float(np.abs(dev).max()),
        "band_mm": band_mm,
        "share_within_band": float(np.mean(np.abs(dev) <= band_mm)),
    }


# ----------------------------------------------------------------------------- against truth


def label_errors(
    frame: np.ndarray, laser: np.ndarray, u: np.ndarray, v: np.ndarray,
    true_frame: np.ndarray, true_laser: np.ndarray, true_u: np.ndarray, true_v: np.ndarray,
    *, near_px: float = 3.0, crossing_px: float = 15.0,
) -> dict[str, Any]:
    """Wrong A/B labels of stripe points (px) against the true centre lines of their frames.

    A point is checked where one true line of its frame passes within ``near_px`` of it in its
    column (``round(u)``) and the other does not; its true laser is that line's (a line that
    crosses the column more than once counts with its row nearest the point). Points where
    the two true lines are within ``crossing_px`` of each other are the crossing band, counted
    apart. ``centre_error``: per laser, the right-labelled centres' offset from their true
    line along the column (px; n, mean, RMS and robust sigma), away from the crossing band.
    """
    frame = np.asarray(frame, dtype=np.int64)
    col = np.rint(np.asarray(u, dtype=np.float64)).astype(np.int64)
    v = np.asarray(v, dtype=np.float64)
    laser = np.asarray(laser).astype(str)
    tf = np.asarray(true_frame, dtype=np.int64)
    tu = np.asarray(true_u, dtype=np.int64)
    tv = np.asarray(true_v, dtype=np.float64)
    tl = np.asarray(true_laser).astype(str)
    span = int(max(col.max(initial=0), tu.max(initial=0))) + 2
    query = frame * span + col
    true_row = {}
    for name in ("A", "B"):
        m = tl == name
        if not m.any():
            true_row[name] = np.full(query.size, np.nan)
            continue
        key = (tf[m] * span + tu[m]).astype(np.float64)
        order = np.lexsort((tv[m], key))
        # a line can cross a column more than once (a step, an occlusion): the nearest row
        j, _ = nearest_in_column(key[order], tv[m][order], query.astype(np.float64), v)
        true_row[name] = np.where(j >= 0, tv[m][order][np.maximum(j, 0)], np.nan)
    da = np.abs(v - true_row["A"])
    db = np.abs(v - true_row["B"])
    with np.errstate(invalid="ignore"):
        # where both true lines pass within near_px the point could be either: not checked
        checked = (np.fmin(da, db) <= near_px) & ~(np.maximum(da, db) <= near_px)
        truth = np.where(np.nan_to_num(da, nan=np.inf) <= np.nan_to_num(db, nan=np.inf), "A", "B")
        crossing = np.abs(true_row["A"] - true_row["B"]) < crossing_px
    wrong = checked & (laser != truth)
    n_checked = int(checked.sum())
    # how far the right-labelled centres lie from their true line, along the column, away
    # from the crossing (where the two stripes' light overlaps)
    centre = {}
    for name in ("A", "B"):
        m = checked & ~crossing & (laser == truth) & (truth == name)
        r = (v - true_row[name])[m]
        if r.size >= 10:
            med = float(np.median(r))
            centre[name] = {"n": int(r.size), "mean_px": float(r.mean()),
                            "rms_px": float(np.sqrt(np.mean(r**2))),
                            "sigma_px": 1.4826 * float(np.median(np.abs(r - med)))}
    return {"points": int(frame.size), "checked": n_checked, "wrong": int(wrong.sum()),
            "wrong_away_from_crossing": int((wrong & ~crossing).sum()),
            "wrong_in_crossing_band": int((wrong & crossing).sum()),
            "wrong_rate": float(wrong.sum() / n_checked) if n_checked else None,
            "near_px": near_px, "crossing_px": crossing_px, "centre_error": centre}


def volume_points(
    camera: Any,
    *,
    z_range: tuple[float, float] = (115.0, 185.0),
    region: tuple[int, int, int, int] | None = None,
    grid: tuple[int, int] = (17, 9),
    depths: int = 8,
) -> np.ndarray:
    """Points (M, 3) in the camera frame filling the measured volume: a pixel grid over
    ``region`` (x, y, width, height; default the full sensor) seen through ``camera``, at
    ``depths`` distances evenly spread over ``z_range`` (mm along the optical axis)."""
    w, h = camera.image_size
    x0, y0, rw, rh = region if region is not None else (0, 0, w, h)
    u, v = np.meshgrid(np.linspace(x0, x0 + rw - 1, grid[0]), np.linspace(y0, y0 + rh - 1, grid[1]))
    xy = camera.undistort(np.column_stack([u.ravel(), v.ravel()]))
    z = np.linspace(z_range[0], z_range[1], depths)
    pts = np.concatenate([np.column_stack([xy * zi, np.full(len(xy), zi)]) for zi in z])
    return pts


def plane_depth_range(
    camera: Any,
    planes: list[tuple[np.ndarray, float]],
    *,
    region: tuple[int, int, int, int] | None = None,
    grid: tuple[int, int] = (64, 48),
    quantiles: tuple[float, float] = (0.01, 0.99),
) -> tuple[float, float] | None:
    """Depth range (mm along the optical axis) over which laser planes (n, d) cross the rays of
    ``region`` (x, y, width, height; default the full sensor): the scanner's measuring range.

    The extreme 1 % at each end are left out, where a ray runs nearly along a plane. None when
    no ray meets a plane in front of the camera.
    """
    w, h = camera.image_size
    x0, y0, rw, rh = region if region is not None else (0, 0, w, h)
    u, v = np.meshgrid(np.linspace(x0, x0 + rw - 1, grid[0]), np.linspace(y0, y0 + rh - 1, grid[1]))
    rays = camera.rays(np.column_stack([u.ravel(), v.ravel()]))
    z = []
    for n, d in planes:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -float(d) / (rays @ np.asarray(n, dtype=np.float64))
        zi = (rays * t[:, None])[:, 2]
        z.append(zi[np.isfinite(zi) & (t > 0) & (zi > 0)])
    z = np.concatenate(z) if z else np.empty(0)
    if len(z) == 0:
        return None
    lo, hi = np.quantile(z, quantiles)
    return float(lo), float(hi)


def frame_rotation(est: Any, true: Any, volume_cam: np.ndarray) -> np.ndarray:
    """Rotation R (3, 3) of the estimated camera's frame against the true one that best explains
    the projection difference over the volume: ``est.project(R @ X)`` nearest ``true.project(X)``.

    A camera model is determined by its views only up to such a rotation where they leave the
    principal point loose: a principal-point error with the rotation that undoes it bends no
    ray, and the laser planes and hand-eye, found through the same camera, carry the same
    rotation, so measured points in the arm's frame do not feel it.
    """
    X = np.asarray(volume_cam, dtype=np.float64)
    target = true.project(X)

    def resid(rv: np.ndarray) -> np.ndarray:
        return (est.project(X @ rotvec_to_matrix(rv).T) - target).ravel()

    return rotvec_to_matrix(least_squares(resid, np.zeros(3), x_scale=1e-3).x)


def camera_error(est: Any, true: Any, volume_cam: np.ndarray) -> dict[str, Any]:
    """Projection difference (px) of the estimated camera against the true one over the volume,
    the same after the best rotation of its frame (``frame_free``: what bends rays), and the
    parameter differences (estimated minus true)."""
    duv = est.project(volume_cam) - true.project(volume_cam)
    dn = np.linalg.norm(duv, axis=1)
    R = frame_rotation(est, true, volume_cam)
    dn_free = np.linalg.norm(est.project(volume_cam @ R.T) - true.project(volume_cam), axis=1)
    names = ("fx", "fy", "cx", "cy")
    out: dict[str, Any] = {
        "rms_px": float(np.sqrt(np.mean(dn**2))),
        "max_px": float(dn.max()),
        "n_points": len(volume_cam),
        "frame_free": {"rms_px": float(np.sqrt(np.mean(dn_free**2))),
                       "max_px": float(dn_free.max()),
                       "rotation_deg": float(np.degrees(rotation_angle(R))),
                       "R_cam_est_cam": R.tolist()},
    }
    for n_, e, t in zip(names, (est.fx, est.fy, est.cx, est.cy),
                        (true.fx, true.fy, true.cx, true.cy), strict=True):
        out[f"d{n_}_px"] = e - t
    for n_, e, t in zip(("k1", "k2", "p1", "p2", "k3"), est.dist, true.dist, strict=True):
        out[f"d{n_}"] = float(e - t)
    return out


def laser_plane_error(
    est: tuple[np.ndarray, float],
    true: tuple[np.ndarray, float],
    true_camera: Any,
    *,
    z_range: tuple[float, float] = (115.0, 185.0),
    region: tuple[int, int, int, int] | None = None,
) -> dict[str, Any]:
    """Estimated laser plane (camera frame) against the true one, over the measured volume.

    Points of the true plane seen by the camera within ``z_range`` are compared with the
    estimated plane: their perpendicular distance to it (``rms_mm``, ``max_mm``) and how far
    a triangulated point moves along its ray (``ray_rms_mm``, what a scan would feel).
    """
    n_e, d_e = np.asarray(est[0], dtype=np.float64), float(est[1])
    n_t, d_t = np.asarray(true[0], dtype=np.float64), float(true[1])
    if float(n_e @ n_t) < 0:
        n_e, d_e = -n_e, -d_e
    w, h = true_camera.image_size
    x0, y0, rw, rh = region if region is not None else (0, 0, w, h)
    u, v = np.meshgrid(np.linspace(x0, x0 + rw - 1, 64), np.linspace(y0, y0 + rh - 1, 48))
    rays = true_camera.rays(np.column_stack([u.ravel(), v.ravel()]))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_true = -d_t / (rays @ n_t)
        t_est = -d_e / (rays @ n_e)
    p = rays * t_true[:, None]
    ok = np.isfinite(t_true) & (p[:, 2] >= z_range[0]) & (p[:, 2] <= z_range[1])
    out: dict[str, Any] = {
        "angle_deg": float(np.degrees(angle_between(n_e, n_t))),
        "d_diff_mm": d_e - d_t,
        "n_points": int(ok.sum()),
    }
    if ok.any():
        dist = p[ok] @ n_e + d_e
        move = np.abs(t_est[ok] - t_true[ok])
        out.update(rms_mm=float(np.sqrt(np.mean(dist**2))), max_mm=float(np.abs(dist).max()),
                   ray_rms_mm=float(np.sqrt(np.mean(move**2))), ray_max_mm=float(move.max()))
    return out


def transform_error(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> dict[str, Any]:
    """Rigid transform against the true one: rotation angle, translation, and the RMS / max
    displacement of ``points`` (M, 3) mapped by each (e.g. the measured volume in ``cam``)."""
    from crossline.geometry import invert_transform, transform_points

    T_est = np.asarray(T_est, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    D = invert_transform(T_true) @ T_est
    disp = np.linalg.norm(transform_points(T_est, points) - transform_points(T_true, points), axis=1)
    return {
        "rotation_deg": float(np.degrees(rotation_angle(D[:3, :3]))),
        "translation_mm": float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])),
        "rms_mm": float(np.sqrt(np.mean(disp**2))),
        "max_mm": float(disp.max()),
    }

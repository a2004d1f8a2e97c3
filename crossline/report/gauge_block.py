"""Height of a gauge block on a surface plate (the paper's Fig. 10).

``measure_gauge_block``: every top-face point against the plate plane, the central length and
parallelism, with its ``GaugeResult``; the 2-D outline helpers it uses (``plane_basis``, convex
hull edges and margins); ``gauge_groups`` and ``normal_within_frames``, the per-frame
orientation of the faces that ``crossline.report.uncertainty`` shares. Built on the fitting of
``crossline.report.fitting``; ``crossline.report.metrics`` re-exports the public names.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from crossline.calibrate.laser_plane_fit import robust_plane
from crossline.geometry import angle_between, plane_distance
from crossline.report.fitting import MIN_POINTS, fit_plane, ransac_plane

__all__ = [
    "GaugeResult",
    "gauge_groups",
    "measure_gauge_block",
    "normal_within_frames",
    "plane_basis",
]


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
    # "frames": the plate's normal from each frame's stripes about their own centroids
    # (normal_within_frames); "plane": from the plate plane fitted over the whole scan
    normal_from: str = "plane"
    # (N,) the plate points the plate's plane was fitted to (plate_mask less its trimmed
    # outliers); None: all of plate_mask
    plate_plane_mask: np.ndarray | None = None
    reference_note: str | None = None  # why the heights are not referenced per frame

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
            **({"reference_note": self.reference_note} if self.reference_note else {}),
            # "frames": the plate's normal from each frame's stripes; "plane": the plane fit's
            "plate_normal_from": self.normal_from,
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


# the gauge plate's reference plane keeps points within this many robust sigmas of it
PLATE_TRIM = 3.0
# the largest standard error of a gauge's plate normal from its frames' stripes: 1e-4 rad is
# 0.1 um of height per mm between a top point and the plate points of its frame
MAX_TILT_RAD = 1e-4
# the least spread of a gauge scan's stripe directions that counts as crossed (see
# normal_within_frames): parallel stripes give 0, crossed ones their share times sin^2
MIN_DIRECTION_SPREAD = 0.01


def gauge_groups(frame: np.ndarray, plate_mask: np.ndarray,
                 top_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices (M,) of the plate's then the top face's points and their group (M,): one
    group per frame and face, for :func:`normal_within_frames`."""
    plate, top = np.flatnonzero(plate_mask), np.flatnonzero(top_mask)
    both = np.r_[plate, top]
    face = np.r_[np.zeros(plate.size, np.int64), np.ones(top.size, np.int64)]
    return both, np.asarray(frame)[both].astype(np.int64) * 2 + face


def normal_within_frames(points: np.ndarray, group: np.ndarray, weights: np.ndarray | None = None,
                         min_points: int = 20, min_ratio: float = 100.0,
                         max_tilt_rad: float = MAX_TILT_RAD) -> np.ndarray | None:
    """Unit normal of parallel planes scanned frame by frame, from each ``group``'s points (a
    frame's points on one of the planes) about their own centroid, so that a frame's rigid
    shift drops out; None where the groups' stripes do not span the plane (all parallel: a
    one-line rig's sweep, or a scan that only one laser reaches) or are too few.

    The scatter of the groups' points about their centroids has two large eigenvalues when
    crossed stripes span the plane; the normal is then its smallest eigenvector. Groups of
    fewer than ``min_points`` points are left out. Spanning means three things: the groups'
    own stripe directions are not all parallel (the second eigenvalue of their
    point-weighted directions' scatter at least ``MIN_DIRECTION_SPREAD`` of the first: some
    10 % of the points on stripes crossing the others at 20 deg or more), the scatter's
    middle eigenvalue is ``min_ratio`` times its smallest (the points' noise), and the
    normal's tilt about the least spanned direction has a standard error ``sqrt(ev0 / (dof
    ev1))`` of at most ``max_tilt_rad``: short crossing stripes (one laser's on a narrow
    block's top only) tell it well. ``min_ratio = 0`` skips the checks; ``weights`` (M,)
    weigh the points (a resampling's).
    """
    w = np.ones(len(points)) if weights is None else np.asarray(weights, dtype=np.float64)
    _, inv, cnt = np.unique(np.asarray(group), return_inverse=True, return_counts=True)
    use = (cnt[inv] >= min_points) & (w > 0)
    if use.sum() < 3 * max(min_points, 1):
        return None
    q, w = np.asarray(points, dtype=np.float64)[use], w[use]
    inv = np.unique(inv[use], return_inverse=True)[1]
    sw = np.bincount(inv, w)
    c = np.stack([np.bincount(inv, w * q[:, i]) for i in range(3)], 1) / sw[:, None]
    q -= c[inv]
    ev, V = np.linalg.eigh((q * w[:, None]).T @ q)
    if min_ratio > 0:
        # each group's stripe direction: the first eigenvector of its own scatter
        S = np.stack([np.bincount(inv, w * q[:, i] * q[:, j], sw.size) for i in range(3)
                      for j in range(3)], 1).reshape(-1, 3, 3)
        d = np.linalg.eigh(S)[1][:, :, 2]
        lam = np.linalg.eigvalsh(np.einsum("g,gi,gj->ij", sw, d, d))
        dof = max(float(w.sum()) - 3.0 * sw.size, 1.0)  # each group's centroid took 3
        tilt_se = np.sqrt(max(ev[0], 0.0) / (dof * max(ev[1], 1e-300)))
        if not (lam[1] >= MIN_DIRECTION_SPREAD * lam[2] and ev[1] > min_ratio * max(ev[0], 1e-30)
                and tilt_se <= max_tilt_rad):
            return None
    return V[:, 0]


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
    step height. The paper's plane-referenced heights are kept in ``heights_plane``. Where
    too few top points lie in frames that see the plate too, the heights are the paper's, to
    the plate plane, and ``reference_note`` says why.
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
    # the plate's plane with its outliers trimmed (PLATE_TRIM robust sigmas): where the top
    # face is scanned over part of its width only, its outline leaves plate points at the
    # foot of the block's walls outside the margin; on one side of a narrow plate patch they
    # tilt a least-squares plane, and the lever to the top face turns the tilt into height.
    # Only the plane is trimmed: each frame's plate points keep referencing its heights (an
    # arm error offsets a whole frame, which a trim about one plane would cut into)
    plate_idx = np.flatnonzero(plate_mask)
    plate_n, plate_d, kept = robust_plane(p[plate_idx], trim=PLATE_TRIM, seed=seed)
    plane_mask = np.zeros(len(p), dtype=bool)
    plane_mask[plate_idx[kept]] = True
    if float(np.median(p[top_mask] @ plate_n + plate_d)) < 0:
        plate_n, plate_d = -plate_n, -plate_d
    heights = plane_distance(p[top_mask], plate_n, plate_d)
    heights_plane = frame_offsets = reference_note = None
    reference, normal_from = "plane", "plane"
    if frame is not None:
        frame = np.asarray(frame)
        ufr, inv, count = np.unique(frame[plate_mask], return_inverse=True, return_counts=True)
        usable = count >= min_frame_points
        ufr_used = ufr[usable]
        top_idx = np.flatnonzero(top_mask)
        k = np.zeros(top_idx.size, dtype=np.int64)
        seen = np.zeros(top_idx.size, dtype=bool)
        if ufr_used.size:
            k = np.clip(np.searchsorted(ufr_used, frame[top_idx]), 0, ufr_used.size - 1)
            seen = ufr_used[k] == frame[top_idx]
        if seen.sum() < MIN_POINTS:
            # no frame sees both faces (a tall block for the measuring range, a sweep across
            # one face at a time): the paper's heights to the plate plane, saying why
            reference_note = (
                f"heights to the plate plane, not per frame: only {int(seen.sum())} top points "
                f"lie in frames that also see at least {min_frame_points} plate points, so the "
                f"arm's pose error between frames enters the heights")
            frame = None
    if frame is not None:
        top_mask = np.zeros(len(p), dtype=bool)
        top_mask[top_idx[seen]] = True
        heights_plane = heights[seen]
        both, group = gauge_groups(frame, plate_mask, top_mask)
        n_frames = normal_within_frames(p[both], group)
        if n_frames is not None:
            # the plate's normal from the shape of each frame's stripes on the two faces, which
            # the arm's pose error of a frame (a shift of all its points) does not tilt; the
            # heights are measured along it
            plate_n = n_frames if float(n_frames @ plate_n) >= 0 else -n_frames
            plate_d = -float(np.mean(p[plate_mask] @ plate_n))
            normal_from = "frames"
        res = plane_distance(p[plate_mask], plate_n, plate_d)
        offset = (np.bincount(inv, weights=res, minlength=ufr.size) / np.maximum(count, 1))[usable]
        heights = plane_distance(p[top_mask], plate_n, plate_d) - offset[k[seen]]
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
        normal_from=normal_from,
        plate_plane_mask=plane_mask,
        reference_note=reference_note,
    )

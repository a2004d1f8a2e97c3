"""Measure the calibrated artefacts in a point cloud: plane, sphere, ball bar.

``measure_plane`` (the paper's Fig. 16) with its ``PlaneResult`` and ``plane_offset``;
``measure_sphere`` (ISO 10360-8 PSize / PForm) with its ``SphereResult`` and
``sphere_by_incidence``; ``measure_ball_bar`` (ISO 10360-8 sphere-spacing error SD) with its
``BallBarResult``. The gauge block has its own module, ``crossline.report.gauge_block``. Built
on the fitting of ``crossline.report.fitting``; ``crossline.report.metrics`` re-exports these
names.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from crossline.geometry import angle_between, fit_sphere, plane_distance
from crossline.report.fitting import (
    MIN_POINTS,
    _orient,
    fit_plane,
    masked_blocks,
    ransac_sphere,
    robust_sigma,
)

__all__ = [
    "BallBarResult",
    "PlaneResult",
    "SphereResult",
    "measure_ball_bar",
    "measure_plane",
    "measure_sphere",
    "plane_offset",
    "sphere_by_incidence",
]


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
        # sums rather than arrays of deviations, squares and magnitudes: a long scan's
        # distances are 8 B a point, and each such temporary as much again
        n, mean, ss = r.size, float(r.mean()), float(r @ r)
        var = max(ss - n * mean * mean, 0.0) / (n - 1) if n > 1 else 0.0
        within = np.count_nonzero((r >= -self.band_mm) & (r <= self.band_mm))
        return {
            "n": int(n),
            "normal": self.normal.tolist(),
            "d_mm": self.d,
            "mean_mm": mean,
            "std_mm": float(np.sqrt(var)),
            "rms_mm": float(np.sqrt(ss / n)),
            "band_mm": self.band_mm,
            "share_within_band": float(within / n),
            "flatness_mm": float(r.max() - r.min()),
            "flatness_95_mm": float(hi - lo),
            "min_mm": float(r.min()),
            "max_mm": float(r.max()),
        }


def measure_plane(
    points: np.ndarray, *, band_mm: float = 0.05, up: np.ndarray | None = None,
    mask: np.ndarray | None = None,
) -> PlaneResult:
    """Least-squares plane of every point (the paper's Fig. 16; those of ``mask`` where given:
    no copy of them) and the distances to it."""
    p = np.asarray(points, dtype=np.float64)
    count = len(p) if mask is None else int(np.count_nonzero(mask))
    if count < MIN_POINTS:
        raise ValueError(f"measure_plane needs at least {MIN_POINTS} points, got {count}")
    n, d = _orient(*fit_plane(p, mask), up)
    if mask is None:
        return PlaneResult(n, d, plane_distance(p, n, d), band_mm)
    r = np.empty(count)
    a = 0
    for q in masked_blocks(p, np.asarray(mask, dtype=bool)):
        r[a:a + len(q)] = plane_distance(q, n, d)
        a += len(q)
    return PlaneResult(n, d, r, band_mm)


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


# ----------------------------------------------------------------------------- ball bar


@dataclass(frozen=True)
class BallBarResult:
    """Two balls of a ball bar and their centre distance (ISO 10360-8 sphere-spacing error SD)."""

    nominal_length_mm: float
    balls: tuple[SphereResult, SphereResult]  # ordered along the base frame's x, then y

    @property
    def length(self) -> float:
        """The measured centre-to-centre distance, mm."""
        return float(np.linalg.norm(self.balls[0].centre - self.balls[1].centre))

    @property
    def inlier_mask(self) -> np.ndarray:
        """The points of either ball (N,)."""
        return self.balls[0].inlier_mask | self.balls[1].inlier_mask

    @property
    def residuals(self) -> np.ndarray:
        """Radial residuals of both balls' points, ball 1's first."""
        return np.concatenate([b.residuals for b in self.balls])

    def figures(self) -> dict[str, Any]:
        """Centre distance and its error SD (measured − nominal length); each ball's size and
        form (PSize, PForm) as :meth:`SphereResult.figures` gives them."""
        L = self.length
        balls = [b.figures() for b in self.balls]
        return {
            "nominal_length_mm": self.nominal_length_mm,
            "length_mm": L,
            "length_error_mm": L - self.nominal_length_mm,
            "n": int(sum(b["n"] for b in balls)),
            "n_total": int(self.inlier_mask.size),
            "size_error_max_mm": max((b["size_error_mm"] for b in balls), key=abs),
            "form_error_max_mm": max(b["form_error_mm"] for b in balls),
            "balls": balls,
        }


def measure_ball_bar(
    points: np.ndarray,
    nominal_diameter: float,
    nominal_length: float,
    *,
    ransac_threshold_mm: float = 0.2,
    trim_sigma: float = 5.0,
    search_fraction: float = 0.1,
    seed: int = 0,
) -> BallBarResult:
    """Both balls of a ball bar among other points (stems, bar, table), each a least-squares
    sphere as :func:`measure_sphere` fits it.

    The first ball is the one RANSAC finds among all points; the second is sought among the
    points whose distance from the first one's centre is the nominal length within the ball's
    radius and ``search_fraction`` of the length (a bar far longer or shorter than its
    nominal is not found, and says so).
    """
    p = np.asarray(points, dtype=np.float64)
    kw = dict(ransac_threshold_mm=ransac_threshold_mm, trim_sigma=trim_sigma, seed=seed)
    first = measure_sphere(p, nominal_diameter, **kw)
    dist = np.linalg.norm(p - first.centre, axis=1)
    reach = nominal_diameter / 2 + max(search_fraction * nominal_length, 4 * ransac_threshold_mm)
    cand = np.flatnonzero((np.abs(dist - nominal_length) <= reach) & ~first.inlier_mask)
    if len(cand) < MIN_POINTS:
        raise ValueError(f"measure_ball_bar: one ball found (centre {np.round(first.centre, 3).tolist()} "
                         f"mm), but only {len(cand)} points lie {nominal_length:g} mm "
                         f"± {reach:.3g} mm from it, where the second ball should be")
    try:
        s = measure_sphere(p[cand], nominal_diameter, **kw)
    except ValueError as exc:
        raise ValueError(f"measure_ball_bar: no second ball {nominal_length:g} mm from the first "
                         f"({exc})") from None
    mask = np.zeros(len(p), dtype=bool)
    mask[cand[s.inlier_mask]] = True
    second = SphereResult(s.nominal_diameter_mm, s.centre, s.radius, s.residuals, mask)
    balls = sorted((first, second), key=lambda b: (round(float(b.centre[0]), 6), float(b.centre[1])))
    return BallBarResult(float(nominal_length), (balls[0], balls[1]))

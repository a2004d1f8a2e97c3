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
- ball bar (ISO 10360-8 SD): both balls' least-squares spheres, sphere-spacing error =
  measured − nominal centre distance, each ball's size and form beside it;
- freeform: signed distance of every point to a reference mesh (float64 refinement).

The code lives in modules beside this one (issue 21.3): ``fitting`` (least-squares and
RANSAC planes and spheres, ``robust_sigma``), ``artefacts`` (plane, sphere, ball bar and
their results), ``gauge_block`` (the gauge block and its result), ``freeform`` (signed
distance to a mesh, deviation statistics) and ``validation`` (estimates against truth).
This one keeps the A/B laser comparison and re-exports the names its importers use, so
``from crossline.report import metrics as mt`` and ``mt.<name>`` work as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from crossline.geometry import angle_between as angle_between
from crossline.geometry import fit_sphere, plane_distance
from crossline.report.artefacts import (
    BallBarResult,
    PlaneResult,
    SphereResult,
    measure_ball_bar,
    measure_plane,
    measure_sphere,
    plane_offset,
    sphere_by_incidence,
)
from crossline.report.fitting import (
    MIN_POINTS,
    fit_plane,
    laser_codes,
    ransac_plane,
    ransac_sphere,
    robust_sigma,
)
from crossline.report.freeform import deviation_stats, mesh_signed_distance, point_triangle_closest
from crossline.report.gauge_block import GaugeResult, measure_gauge_block, plane_basis
from crossline.report.validation import (
    camera_error,
    frame_rotation,
    label_errors,
    laser_plane_error,
    transform_error,
    volume_points,
)
from crossline.report.validation import plane_depth_range as plane_depth_range

__all__ = [
    "ABComparison",
    "BallBarResult",
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
    "measure_ball_bar",
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
        # the spread from every k-th point (about 20 000): no copies of a long scan's points
        idx = np.flatnonzero(m)
        q = p[idx[:: max(1, len(idx) // 20000)]]
        q = q - q.mean(0)
        s = np.linalg.svd(q, compute_uv=False) / np.sqrt(len(q))
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
            n, d = fit_plane(p, pm)
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
            res = measure_plane(p, band_mm=band_mm, up=plane.normal, mask=m)
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

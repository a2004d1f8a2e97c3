"""Fuse the points of a scan into one cloud: outlier removal, optional voxel grid, normals, PLY.

The cloud stays in the base frame, in mm. Each point keeps its laser (A or B) and its frame,
so that metrology can measure an artefact from each laser alone: voxel down-sampling
therefore averages the points of each laser separately, never mixing the two.

Normals are oriented towards the camera that saw the point. The camera's position in the
base frame is recovered per frame from the points themselves: each point is known in the
camera frame and in the base frame, and one rigid motion (Kabsch) maps the first to the
second, its translation being the camera centre (:mod:`crossline.fuse.camera_centres`). Frames
whose points are collinear (a single stripe on a plane) borrow the centre of the nearest frame
that has one.

A long scan (tens of millions of points) is read column by column and row group by row group,
and its per-point neighbourhood work (outlier test, normals) runs a slab at a time
(:mod:`crossline.tiles`), with the answers of the whole cloud.

Optionally (``refine_poses``) the arm's per-frame poses are first refined from the scan
itself (:mod:`crossline.scan.refine`): where an A stripe crosses a B stripe of another frame the
two must meet, and the per-frame rigid corrections that make them meet (maximum a
posteriori, with the arm's stated precision as prior) move every point of the frame. The
corrections and what the solve saw go into the stats JSON under ``refine``.

The PLY is binary little-endian with float64 coordinates (``x y z``, then ``nx ny nz`` as
float32, ``laser`` as uchar 1 = A / 2 = B, ``frame`` as int32); Open3D and other readers
read it as an ordinary point cloud with normals (:mod:`crossline.io.ply`, which writes it so
that its bytes depend only on the points).

The code is split by idea (issue 21.3): ``crossline.fuse.normals`` (one slab's normals, their
orientation), ``crossline.fuse.refine`` (the pose refinement step and its stats),
``crossline.fuse.mesh`` (the optional mesh), ``crossline.fuse.inputs`` (the points parquet's
columns, the scan's frames table). This module keeps the cloud (``FusedCloud``),
``estimate_normals`` and the normals towards the camera (which cut the cloud into slabs), the
voxel grid, ``fuse_cloud`` and ``run_fuse``; the package (``crossline.fuse``) re-exports the
names its importers use.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from crossline.errors import StageError
from crossline.fuse.camera_centres import FrameMoments as FrameMoments
from crossline.fuse.camera_centres import camera_centres
from crossline.fuse.inputs import _frames_in_table, _read_frames, _same_scan, read_points_columns
from crossline.fuse.mesh import make_mesh
from crossline.fuse.normals import _slab_normals, orient_normals
from crossline.fuse.refine import _prior_draws, _refine
from crossline.io.arm_draws import ArmDraws, write_arm_draws
from crossline.io.atomic import write_json
from crossline.io.ply import read_ply, write_ply, write_stl
from crossline.scan.refine import HALF_MM, MAX_WIDTH_RATIO, MIN_ANGLE_DEG, ArmPrior, usable_centres
from crossline.tiles import slabs, statistical_inliers

__all__ = [
    "ARM_PRIOR_ADVICE",
    "ARM_PRIOR_WARN",
    "LASER_CODES",
    "FusedCloud",
    "arm_prior",
    "camera_centres",
    "estimate_normals",
    "fuse_cloud",
    "fuse_columns",
    "make_mesh",
    "orient_normals",
    "read_ply",
    "read_points_columns",
    "run_fuse",
    "voxel_down_sample",
    "write_ply",
    "write_stl",
]

log = logging.getLogger("crossline.fuse")

LASER_CODES = {"A": 1, "B": 2}


@dataclass(frozen=True)
class FusedCloud:
    """A fused cloud: points (N, 3) mm, normals (N, 3) (float32, as the PLY stores them),
    laser codes (N,) and frames (N,)."""

    points: np.ndarray
    normals: np.ndarray
    laser: np.ndarray  # uint8: 1 = A, 2 = B, 0 = unknown
    frame: np.ndarray  # int32: the frame the point (or the first point of its voxel) came from
    stats: dict[str, Any] = field(default_factory=dict, compare=False)
    # the arm's pose errors left, drawn per frame (for the report's uncertainty), or None
    arm: ArmDraws | None = field(default=None, compare=False)

    def laser_labels(self) -> np.ndarray:
        """Laser of each point as ``"A"``, ``"B"`` or ``"?"``."""
        return np.array(["?", "A", "B"])[np.clip(self.laser, 0, 2)]


# ----------------------------------------------------------------------------- geometry


def estimate_normals(
    points: np.ndarray, radius: float, viewpoints: np.ndarray | None = None, *, threads: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (N, 3) from the covariance of each point's neighbours within ``radius``.

    Where the neighbours lie along a line (a lone stripe: the next stripe is farther than
    ``radius``) the plane is undetermined; there the normal is taken as the direction to
    the viewpoint made perpendicular to the line, or the view direction itself when there
    are no neighbours at all. Returns the normals and the mask of those fallbacks.
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.empty((len(points), 3))
    degenerate = np.zeros(len(points), dtype=bool)
    # slab by slab (crossline.tiles): every neighbour within the radius is in the slab's reach
    for s in slabs(points, float(radius)):
        views = None if viewpoints is None else viewpoints[s.core]
        normals[s.core], degenerate[s.core] = _slab_normals(points[s.reach], s.start, s.stop,
                                                            radius, views, threads)
    return normals, degenerate


def _normals_towards_camera(
    points: np.ndarray, radius: float, frames: np.ndarray, centres: np.ndarray,
    point_frame: np.ndarray, threads: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Normals (N, 3) float32 facing the camera of each point's frame (``centres`` (F, 3) of
    the sorted ``frames``), and the fallback mask: :func:`estimate_normals` then
    :func:`orient_normals`, a slab at a time, never an (N, 3) array of viewpoints."""
    normals = np.empty((len(points), 3), dtype=np.float32)
    degenerate = np.zeros(len(points), dtype=bool)
    for s in slabs(points, float(radius)):
        views = centres[np.searchsorted(frames, point_frame[s.core])]
        n, deg = _slab_normals(points[s.reach], s.start, s.stop, radius, views, threads)
        normals[s.core] = orient_normals(points[s.core], n, views)
        degenerate[s.core] = deg
    return normals, degenerate


def voxel_down_sample(
    points: np.ndarray, laser: np.ndarray, frame: np.ndarray, voxel: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average the points of each laser in each voxel (edge ``voxel`` mm) on one common grid.

    Returns points (M, 3), laser codes (M,) and frames (M,) (the earliest frame of each
    voxel), ordered by laser, then voxel index: the same input gives the same output.
    """
    p = np.asarray(points, dtype=np.float64)
    if len(p) == 0:
        return p.copy(), np.asarray(laser)[:0], np.asarray(frame)[:0]
    origin = p.min(0)
    k = np.floor((p - origin) / voxel).astype(np.int64)
    dims = k.max(0) + 1
    if float(np.prod(dims.astype(np.float64))) * 4 > 2.0**62:
        raise StageError(f"voxel size {voxel} mm is too small for a cloud of extent "
                         f"{np.ptp(p, axis=0)} mm")
    key = (np.asarray(laser, dtype=np.int64) * dims[0] + k[:, 0]) * dims[1] + k[:, 1]
    key = key * dims[2] + k[:, 2]
    uk, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    out = np.stack([np.bincount(inv, weights=p[:, i], minlength=len(uk)) for i in range(3)], 1)
    out /= cnt[:, None]
    lab = (uk // (dims[0] * dims[1] * dims[2])).astype(np.uint8)
    fr = np.full(len(uk), np.iinfo(np.int64).max)
    np.minimum.at(fr, inv, np.asarray(frame, dtype=np.int64))
    return out, lab, fr.astype(np.int32)


def fuse_cloud(
    points: np.ndarray,
    laser: np.ndarray,
    frame: np.ndarray,
    points_cam: np.ndarray | None = None,
    *,
    widths: np.ndarray | None = None,
    cameras: tuple[np.ndarray, np.ndarray] | None = None,
    **options: Any,
) -> FusedCloud:
    """Optional pose refinement, statistical outlier removal, optional voxel down-sampling
    (per laser), oriented normals: :func:`fuse_columns` on these arrays (its options)."""
    cols = {"xyz": points, "laser": laser, "frame": frame, "points_cam": points_cam,
            "width": widths, "cameras": cameras, "owned": False}
    del points, laser, frame, points_cam, widths, cameras
    return fuse_columns(cols, **options)


def fuse_columns(
    cols: dict[str, Any],
    *,
    neighbours: int = 20,
    std_ratio: float = 3.0,
    voxel_mm: float = 0.0,
    normal_radius_mm: float = 0.5,
    refine_prior: ArmPrior | None = None,
    frame_table: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    crossing_half_mm: float = HALF_MM,
    crossing_min_angle_deg: float = MIN_ANGLE_DEG,
    crossing_max_width_ratio: float = MAX_WIDTH_RATIO,
    threads: int = 1,
    arm_draws: int = 0,
    arm_prior: ArmPrior | None = None,
) -> FusedCloud:
    """Optional pose refinement, statistical outlier removal, optional voxel down-sampling
    (per laser), oriented normals, of the columns ``cols`` (popped: the dict's arrays are let
    go as soon as they are used, which a long scan's memory needs: an array passed as an
    argument stays referenced by the caller for the whole call).

    ``cols["xyz"]`` (N, 3) mm, ``cols["laser"]`` codes (1 = A, 2 = B) or labels ("A"/"B"),
    ``cols["frame"]`` (N,); optional: ``cols["points_cam"]`` (N, 3), the same points in the
    camera frame, orients the normals towards the camera. With
    ``refine_prior`` (and ``points_cam``, which gives each frame's camera centre) every
    frame's pose is refined first (:func:`crossline.scan.refine.refine_frames`); ``frame_table``
    = (frame numbers, times in s, reported flange positions (M, 3)) from the scan's
    frames.csv gives the prior its time correlation and the rotations their centre;
    ``crossing_half_mm`` and ``crossing_min_angle_deg`` are the refinement's stripe length
    fitted either side of a crossing and the smallest crossing angle it uses; with
    ``cols["width"]`` (N,), each centre's column cut in px, centres cut over
    ``crossing_max_width_ratio`` x their laser's median make no crossings
    (:func:`crossline.scan.refine.usable_centres`). ``cols["cameras"]`` = (sorted frames,
    camera centres (F, 3) in the base frame, e.g. from :class:`FrameMoments`) stands in for
    ``points_cam`` where the scan is too long to hold those. ``arm_draws`` > 0 draws the arm's
    pose errors left in the cloud (``FusedCloud.arm``): from the refinement's posterior, or
    where the poses are not refined from ``arm_prior`` (default ``refine_prior``).
    ``cols["owned"]`` (default True) says the arrays are handed over: the refined points are
    then written over ``cols["xyz"]`` (:func:`fuse_cloud` passes False: its caller's arrays are
    left as they were).
    """
    points, laser, frame = cols.pop("xyz"), cols.pop("laser"), cols.pop("frame")
    points_cam, widths = cols.pop("points_cam", None), cols.pop("width", None)
    cameras = cols.pop("cameras", None)
    # the columns are the caller's to keep (fuse_cloud) or handed over (run_fuse's, read here)
    owned = bool(cols.pop("owned", True))
    p = np.ascontiguousarray(points, dtype=np.float64)
    lab = np.asarray(laser)
    if lab.dtype.kind in "OUS":
        lab = np.select([lab.astype(str) == "A", lab.astype(str) == "B"], [1, 2], 0)
    lab = lab.astype(np.uint8)
    fr = np.asarray(frame)
    if fr.dtype.kind not in "iu":
        fr = fr.astype(np.int64)
    # a long scan's arrays are large: hold each once (the caller may hand them over)
    del points, laser, frame
    if cameras is None and points_cam is not None:
        cameras = camera_centres(fr, points_cam, p)
    del points_cam
    if cameras is not None and not np.isfinite(cameras[1]).all():
        cameras = None
    stats: dict[str, Any] = {"n_input": len(p), "by_laser_input": _by_laser(lab)}
    if len(p) == 0:
        raise StageError("no points to fuse")
    lacking = [L for L, code in (("A", 1), ("B", 2)) if not (lab == code).any()]
    if refine_prior is not None and lacking:
        # the refinement fits where a line A of one frame crosses a line B of another
        stats["refine"] = {"skipped": f"no laser {' or '.join(lacking)} points: the pose "
                                      "refinement needs stripes of both lasers to cross "
                                      "(arm poses used as reported)"}
        log.info("pose refinement skipped: %s", stats["refine"]["skipped"])
    if len(p) < 2**31 and len(fr) and 0 <= fr.min() and fr.max() < 2**31:
        fr = fr.astype(np.int32, copy=False)  # what the cloud keeps; 4 B a point less from here on
    arm = None
    if refine_prior is not None and not lacking:
        mask = None if widths is None else usable_centres(lab, widths, crossing_max_width_ratio)
        widths = None
        p, cameras, stats["refine"], arm = _refine(
            p, lab, fr, cameras, refine_prior, frame_table, threads, crossing_half_mm,
            crossing_min_angle_deg, mask, draws=arm_draws,
            overwrite_points=owned and p.flags.writeable)
        del mask
    elif arm_draws > 0 and (arm_prior is not None or refine_prior is not None):
        arm = _prior_draws(fr, cameras, arm_prior if arm_prior is not None else refine_prior,
                           frame_table, arm_draws, 0)

    widths = None
    if neighbours > 0 and len(p) > neighbours:
        # Open3D's test, slab by slab (crossline.tiles): the same points kept, a bounded memory
        keep = statistical_inliers(p, int(neighbours), float(std_ratio), normal_radius_mm,
                                   threads=threads)
    else:
        keep = np.ones(len(p), dtype=bool)
    stats["n_outliers"] = int((~keep).sum())
    stats["n_after_outlier_removal"] = int(keep.sum())
    if not keep.all():
        if owned and p.flags.writeable:
            # the kept points moved to the front of the arrays they are in: a long scan's
            # points are not held twice (24 B a point at the stage's peak)
            p, lab, fr = (_compact(a, keep) for a in (p, lab, fr))
        else:
            kept = np.flatnonzero(keep)
            p, lab, fr = p[kept], lab[kept], fr[kept]
            del kept
    del keep

    if voxel_mm > 0:
        vp, vlab, vfr = voxel_down_sample(p, lab, fr, voxel_mm)
    else:
        vp, vlab, vfr = p, lab, fr.astype(np.int32, copy=False)
    stats["n_output"] = len(vp)
    stats["by_laser_output"] = _by_laser(vlab)

    del fr, p
    if cameras is not None:
        normals, degenerate = _normals_towards_camera(vp, normal_radius_mm, *cameras, vfr,
                                                      threads)
    else:
        normals, degenerate = estimate_normals(vp, normal_radius_mm, threads=threads)
        normals = orient_normals(vp, normals, None).astype(np.float32)
    stats["normals_oriented_to"] = "camera" if cameras is not None else "dominant direction"
    stats["normals_from_view"] = int(degenerate.sum())
    stats["frames"] = len(np.unique(vfr))
    if len(vp):
        stats["bbox_min_mm"] = vp.min(0).tolist()
        stats["bbox_max_mm"] = vp.max(0).tolist()
    if arm is not None:
        stats["arm_draws"] = {"draws": len(arm.draws), "frames": len(arm.frames), "kind": arm.kind}
    return FusedCloud(vp, normals, vlab, vfr.astype(np.int32, copy=False), stats, arm)


def _compact(a: np.ndarray, keep: np.ndarray, block: int = 1 << 20) -> np.ndarray:
    """``a[keep]`` written over the front of ``a`` itself, a block of rows at a time (each
    block's kept rows land at or before where they were read): the view of those rows."""
    n = 0
    for r0 in range(0, len(a), block):
        rows = a[r0:r0 + block][keep[r0:r0 + block]]
        a[n:n + len(rows)] = rows
        n += len(rows)
    return a[:n]


def _by_laser(codes: np.ndarray) -> dict[str, int]:
    c = np.bincount(np.asarray(codes, dtype=np.int64), minlength=3)
    out = {"A": int(c[1]), "B": int(c[2])}
    if c[0]:
        out["unknown"] = int(c[0])
    return out


# ----------------------------------------------------------------------------- stage


def run_fuse(
    points: Path,
    out: Path,
    *,
    stats: Path | None = None,
    neighbours: int = 20,
    std_ratio: float = 3.0,
    voxel_mm: float = 0.0,
    normal_radius_mm: float = 0.5,
    mesh: str = "none",
    mesh_out: Path | None = None,
    threads: int = 1,
    refine_poses: bool = False,
    frames: Path | None = None,
    arm_precision_mm: float | str = 0.02,
    arm_precision_rad: float | None = None,
    handeye: Path | None = None,
    arm_smooth_fraction: float = 0.9,
    arm_corr_time_s: float = 0.3,
    crossing_half_mm: float = HALF_MM,
    crossing_min_angle_deg: float = MIN_ANGLE_DEG,
    crossing_max_width_ratio: float = MAX_WIDTH_RATIO,
    arm_draws: int = 64,
    arm_draws_out: Path | None = None,
) -> FusedCloud:
    """The ``fuse`` stage: points parquet -> fused PLY (+ stats JSON, + STL mesh if asked).

    ``refine_poses`` refines every frame's arm pose from the scan first, with the arm's
    precision as prior: ``arm_precision_mm`` (and ``arm_precision_rad``, default the mm
    figure over 300 mm) read as 2 sigma of the 3-D error, or ``arm_precision_mm="auto"``: the
    arm's noise that the hand-eye calibration ``handeye`` (its handeye.json) estimated from its
    views (:func:`arm_prior`); split into a drift correlated in
    time over ``arm_corr_time_s`` (sigma ``arm_smooth_fraction`` of the whole) and a white
    part (the rest of the variance); ``frames`` (the scan's
    frames.csv) gives the frame times and the flange positions; ``crossing_half_mm`` is the
    stripe length fitted either side of a crossing, ``crossing_min_angle_deg`` the smallest
    crossing angle used, ``crossing_max_width_ratio`` the longest column cut (over its
    laser's median) whose centre may make a crossing (0: any; needs the points' ``width``).
    With ``arm_draws_out``, the arm's pose errors left in the cloud are drawn ``arm_draws``
    times (the refinement's posterior, or the prior above where the poses are not refined) and
    written there (:mod:`crossline.io.arm_draws`), for the report's uncertainty.
    """
    points = Path(points)
    if not points.is_file():
        raise StageError(f"{points}: points file not found (run triangulate first)")
    if mesh != "none" and mesh_out is None:
        raise StageError(f"--mesh {mesh} needs --mesh-out (the STL to write)")
    if neighbours < 0 or std_ratio <= 0 or voxel_mm < 0 or normal_radius_mm <= 0:
        raise StageError(
            f"fuse parameters out of range: neighbours={neighbours} (>= 0), std_ratio={std_ratio} "
            f"(> 0), voxel_mm={voxel_mm} (>= 0), normal_radius_mm={normal_radius_mm} (> 0)"
        )
    if arm_draws < 0:
        raise StageError(f"fuse parameters out of range: arm_draws={arm_draws} (>= 0)")
    if arm_draws_out is None:
        arm_draws = 0  # nowhere to write them: not drawn
    prior, prior_info = None, None
    if refine_poses or arm_draws > 0:
        try:
            prior, prior_info = arm_prior(arm_precision_mm, arm_precision_rad, handeye,
                                          smooth_fraction=arm_smooth_fraction,
                                          corr_time_s=arm_corr_time_s)
        except (ValueError, TypeError):  # the prior checks its own ranges; say it in the config's terms
            raise StageError(
                f"pose refinement parameters out of range: arm_precision_mm={arm_precision_mm} "
                f"(> 0), arm_precision_rad={arm_precision_rad} (> 0 or auto), "
                f"arm_smooth_fraction={arm_smooth_fraction} (0..1), "
                f"arm_corr_time_s={arm_corr_time_s} (> 0)") from None
        if not (crossing_half_mm > 0 and 0 < crossing_min_angle_deg < 90
                and crossing_max_width_ratio >= 0):
            raise StageError(
                f"pose refinement parameters out of range: crossing_half_mm={crossing_half_mm} "
                f"(> 0), crossing_min_angle_deg={crossing_min_angle_deg} (0..90), "
                f"crossing_max_width_ratio={crossing_max_width_ratio} (>= 0, 0 = off)")
    table = _read_frames(frames) if (refine_poses or arm_draws > 0) and frames is not None else None
    cols = read_points_columns(points)
    if table is not None:
        _same_scan(points, Path(frames), len(table[0]))
        _frames_in_table(points, Path(frames), cols["frame"], table[0])
    n_non_finite = int(cols["non_finite"])
    # the dict handed over, so that fuse_columns holds the only reference to each array and
    # can let it go (arguments stay referenced by the calling frame until the call returns)
    cloud = fuse_columns(
        cols, neighbours=neighbours, std_ratio=std_ratio, voxel_mm=voxel_mm,
        normal_radius_mm=normal_radius_mm, refine_prior=prior if refine_poses else None,
        frame_table=table, arm_draws=arm_draws, arm_prior=prior,
        crossing_half_mm=crossing_half_mm, crossing_min_angle_deg=crossing_min_angle_deg,
        crossing_max_width_ratio=crossing_max_width_ratio,
        threads=threads,
    )
    cloud.stats["n_non_finite"] = n_non_finite
    cloud.stats["parameters"] = {"neighbours": neighbours, "std_ratio": std_ratio,
                                 "voxel_mm": voxel_mm, "normal_radius_mm": normal_radius_mm,
                                 "mesh": mesh, "refine_poses": bool(refine_poses)}
    if prior is not None:
        cloud.stats["parameters"].update(
            arm_precision_mm=arm_precision_mm, arm_precision_rad=arm_precision_rad,
            arm_smooth_fraction=arm_smooth_fraction, arm_corr_time_s=arm_corr_time_s)
        cloud.stats["arm_prior"] = {**prior_info, "sigma_mm": prior.sigma_mm,
                                    "sigma_rad": prior.sigma_rad,
                                    "precision_mm": prior.sigma_mm * 2.0 * np.sqrt(3.0)}
        if prior_info.get("handeye_ratio", 0.0) > ARM_PRIOR_WARN:
            log.warning("the hand-eye views put the arm's noise at %.1fx the stated precision "
                        "(%.4f mm per axis against %.4f): %s", prior_info["handeye_ratio"],
                        prior_info["handeye_sigma_mm"], prior.sigma_mm, ARM_PRIOR_ADVICE)
    if refine_poses:
        cloud.stats["parameters"].update(
            crossing_half_mm=crossing_half_mm, crossing_min_angle_deg=crossing_min_angle_deg,
            crossing_max_width_ratio=crossing_max_width_ratio,
            frames_file=None if frames is None else Path(frames).name)
    cloud.stats["points_file"] = points.name
    if arm_draws_out is not None:
        cloud.stats["parameters"]["arm_draws"] = arm_draws
        if cloud.arm is None and arm_draws > 0:
            cloud.stats["arm_draws"] = {"skipped": "no frame could be placed (neither a frames "
                                                   "table nor the points' camera coordinates)"}
        # written even without draws (none asked, or none possible): the workflow's output
        write_arm_draws(arm_draws_out, cloud.arm if cloud.arm is not None else ArmDraws(
            np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 0, 6), np.float32), "prior"))
    write_ply(out, cloud)
    if mesh != "none":
        V, F = make_mesh(cloud, mesh, threads=threads)
        write_stl(mesh_out, V, F)
        cloud.stats["mesh_vertices"] = len(V)
        cloud.stats["mesh_triangles"] = len(F)
    log.info("fused %s: %d points in, %d outliers, %d out", points.name, cloud.stats["n_input"],
             cloud.stats["n_outliers"], cloud.stats["n_output"])
    if stats is not None:
        write_json(stats, cloud.stats)
    return cloud


# the hand-eye's estimate of the arm's noise this many times the stated figure is worth a word
ARM_PRIOR_WARN = 3.0
ARM_PRIOR_ADVICE = ("if the arm is that noisy, set fuse.arm_precision_mm to auto or to the arm's "
                    "true figure (a prior too tight keeps the refinement from correcting the poses)")


def arm_prior(
    precision_mm: float | str, precision_rad: float | None = None, handeye: Path | None = None, *,
    smooth_fraction: float = 0.9, corr_time_s: float = 0.3,
) -> tuple[ArmPrior, dict[str, Any]]:
    """The pose refinement's prior from the config's figures, and where it came from.

    ``precision_mm`` is the arm's stated precision (2 sigma of the 3-D error; ``precision_rad``
    the orientation's, None: over 300 mm; with ``handeye``, the info gives the hand-eye's
    estimate beside it and their ratio), or ``"auto"``: the arm's noise per axis that the
    hand-eye calibration ``handeye`` estimated from its views (variance components of its
    refinement), the rotation kept at least the position's over 300 mm. A hand-eye view is a
    static pose in its own arm configuration, as a datasheet's precision is; from 8 views the
    estimate was within a factor of 2 of the truth on 36 of 40 random rigs, where a stated
    0.02 mm is 10x off on an arm 10x worse (docs/method.md).
    """
    if precision_mm != "auto":
        prior = ArmPrior.from_precision(precision_mm, precision_rad, smooth_fraction=smooth_fraction,
                                        corr_time_s=corr_time_s)
        info: dict[str, Any] = {"source": "stated (arm_precision_mm)"}
        if handeye is not None:  # beside the stated figure, what the hand-eye views measured
            try:
                s_mm = _handeye_sigmas(handeye)[0]
            except StageError:
                pass
            else:
                info.update(handeye_sigma_mm=s_mm, handeye_ratio=s_mm / prior.sigma_mm)
        return prior, info
    s_mm, s_rad, info = _handeye_sigmas(handeye)
    return ArmPrior.from_estimate(s_mm, s_rad, smooth_fraction=smooth_fraction,
                                  corr_time_s=corr_time_s), info


def _handeye_sigmas(handeye: Path | None) -> tuple[float, float, dict[str, Any]]:
    """The arm's per-axis sigmas (mm, rad) in a handeye.json, and where they came from."""
    from crossline.calibrate.handeye import HandEye, HandEyeFileError

    if handeye is None:
        raise StageError("arm_precision_mm auto takes the arm's noise from the hand-eye calibration: "
                         "give its handeye.json (--handeye), or state the arm's precision in mm")
    try:
        noise = HandEye.load(handeye).arm_noise()
    except (OSError, HandEyeFileError) as exc:
        raise StageError(f"{handeye}: cannot read the hand-eye calibration ({exc})") from exc
    if noise is None:
        raise StageError(f"{handeye}: holds no estimate of the arm's noise (a hand-eye file of an "
                         "older version?); run calibrate-handeye again, or state arm_precision_mm")
    info = {"source": f"hand-eye calibration ({noise['views']} views)"}
    return noise["sigma_mm"], noise["sigma_rad"], info


def load_stats(path: str | Path) -> dict[str, Any] | None:
    """The stats JSON of a fuse run, or None if the file is absent or unreadable."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None

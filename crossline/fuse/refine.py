"""The fuse stage's pose refinement: each frame's arm pose refined from the scan, and its stats.

``_refine`` joins the points to the scan's frames table (times, flange positions), runs
:func:`crossline.scan.refine.refine_frames`, moves each frame's camera centre with its
points and returns the refinement's stats for the stats JSON (``refine``). It logs under
the fuse stage's logger (``crossline.fuse``). Split from the fuse stage's module (issue 21.3;
now :mod:`crossline.fuse.cloud`).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from crossline.errors import StageError
from crossline.io.arm_draws import ArmDraws
from crossline.scan.refine import ArmPrior

log = logging.getLogger("crossline.fuse")


def _frame_times(frames: np.ndarray,
                 frame_table: tuple[np.ndarray, np.ndarray, np.ndarray] | None, what: str,
                 ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Times (F,) and flange origins (F, 3) of ``frames`` from the frames table (None, None
    without one); StageError naming ``what`` needed them where a frame is not in the table."""
    if frame_table is None:
        return None, None
    tf, tt, to = (np.asarray(a) for a in frame_table)
    order = np.argsort(tf, kind="stable")
    tf, tt, to = tf[order], tt[order], to[order]
    pos = np.clip(np.searchsorted(tf, frames), 0, max(len(tf) - 1, 0))
    missing = frames if len(tf) == 0 else frames[tf[pos] != frames]
    if len(missing):
        raise StageError(f"{what}: frame(s) {missing[:5].tolist()} of the points are not in the "
                         "scan's frames table")
    return tt[pos].astype(np.float64), to[pos].astype(np.float64)


def _prior_draws(fr: np.ndarray, cameras: tuple[np.ndarray, np.ndarray] | None, prior: ArmPrior,
                 frame_table: tuple[np.ndarray, np.ndarray, np.ndarray] | None, draws: int,
                 seed: int) -> ArmDraws | None:
    """The arm's pose errors drawn from its prior, for a scan whose poses were not refined
    (None where no frame can be placed: neither a frames table nor camera centres)."""
    from crossline.scan.refine_prior import prior_draws

    frames = np.unique(fr) if cameras is None else np.asarray(cameras[0])
    times, origins = _frame_times(frames, frame_table, "the arm's uncertainty draws")
    centre = "flange"
    if origins is None:
        if cameras is None:
            return None
        origins = np.asarray(cameras[1], dtype=np.float64)  # the camera centre stands in
        centre = "camera"
    d = prior_draws(times, prior, len(frames), draws, np.random.default_rng(seed)) * prior.sigmas()
    return ArmDraws(frames, origins, d.astype(np.float32), "prior", centre)


def _refine(
    p: np.ndarray, lab: np.ndarray, fr: np.ndarray, cameras: tuple[np.ndarray, np.ndarray] | None,
    prior: ArmPrior, frame_table: tuple[np.ndarray, np.ndarray, np.ndarray] | None, threads: int,
    half_mm: float, min_angle_deg: float, crossing_mask: np.ndarray | None, draws: int = 0,
    seed: int = 0, overwrite_points: bool = False,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], dict[str, Any], ArmDraws | None]:
    """Points with refined per-frame poses, the camera centres moved with them, the stats
    of the refinement (JSON-ready) and ``draws`` of the errors it leaves (its posterior)."""
    from crossline.scan.refine import correction_transforms, refine_frames

    if cameras is None:
        raise StageError("pose refinement needs the points in the camera frame (x_cam, y_cam, "
                         "z_cam) to place each frame's camera, and a frame with enough "
                         "non-collinear points to place it; the points file has neither")
    frames, views = cameras
    times, origins = _frame_times(frames, frame_table, "pose refinement")
    ref = refine_frames(fr, lab, p, views, prior, frames=frames, times=times, origins=origins,
                        half_mm=half_mm, min_angle_deg=min_angle_deg, crossing_mask=crossing_mask,
                        threads=threads, draws=draws, seed=seed,
                        overwrite_points=overwrite_points)
    d = dict(ref.diagnostics)
    # timings go to the log, not to the stats: the same points must give the same bytes
    log.info("pose refinement: %d crossings, %d frames, %.2f s (crossings %.2f s)", d["crossings"],
             d["frames"], d.pop("seconds"), d.pop("seconds_crossings"))
    info: dict[str, Any] = {
        "method": "A-B stripe crossings between frames, MAP per-frame rigid corrections",
        "prior": {**dataclasses.asdict(prior),
                  "time_correlated": times is not None,
                  "rotation_centre": "flange (frames table)" if origins is not None
                  else "camera centre"},
        **{k: (float(v) if isinstance(v, np.floating) else v) for k, v in d.items()},
        "per_frame": {
            "frame": frames.tolist(),
            # estimated error of the reported pose (reported minus true), base frame: rotation
            # about the flange (or camera) origin, and the origin's position error
            "rotation_rad": ref.rotation.tolist(),
            "translation_mm": ref.translation.tolist(),
            "origin_mm": ref.origins.tolist(),
            "correction_rms_mm": ref.frame_rms.tolist(),
        },
    }
    # every point of a frame moves with it, so its camera centre does too
    C = correction_transforms(ref.rotation, ref.translation, ref.origins)
    moved = np.einsum("fij,fj->fi", C[:, :3, :3], views) + C[:, :3, 3]
    post = None if ref.posterior is None else ArmDraws(
        frames, ref.origins, ref.posterior, "posterior", "flange" if origins is not None else "camera")
    return ref.points, (frames, moved), info, post

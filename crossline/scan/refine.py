"""Refine the arm's reported pose of every frame from the scan itself (maximum a posteriori).

A cross-line scanner sees each surface point twice: once with line A and once with line B,
usually from frames far apart in time. Where the A stripe of frame f crosses the B stripe
of frame g, both stripes should pass through the same surface point; the gap between the
two curves along the surface normal is, up to measurement noise, the difference of the two
frames' pose errors seen along that normal:

    gap = n · (δ_f(x) − δ_g(x)) + β + noise,   δ_f(x) = ω_f × (x − o_f) + t_f,

where (ω_f, t_f) is frame f's pose error (reported minus true) as a small rotation about its
flange origin o_f and a translation, both in the base frame, and β is one constant A-minus-B
offset along the normal (a slight disagreement of the two laser-plane calibrations, which
must not be pushed into the poses). Every crossing is a point where two independent pose
errors are compared on a surface that needs no model: the two local stripe curves (each a
quadratic fitted along its own stripe) meet at the surface point whatever its curvature.

The errors get the arm's error model as prior (``ArmPrior``): per axis a Gauss-Markov
(AR(1)) process in time plus a white part, as a measuring arm's error changes smoothly with
its joint configuration along a sweep. The MAP estimate of all frames' errors at once is a
sparse linear least-squares problem (one scalar per crossing against 6 unknowns per frame,
and a prior whose information is banded once the drift is an unknown of its own), solved
directly (dense Cholesky up to ``DENSE_MAX_FRAMES`` frames, sparse LDL^T beyond); robust
(Huber) weights are re-estimated a few times.
What a frame's crossings do not constrain (on a plane: the two in-plane shifts and the
turn about the normal; for a single stripe also the tilt about the stripe) stays at what
the prior and the neighbouring frames say, and an error common to all frames (the whole
scan rigidly moved) is unobservable and stays at zero.

The code is split by idea (issue 21.3): ``refine_prior`` (the arm's error model, the prior's
covariance between frames), ``refine_crossings`` (the A-B stripe crossings and their gaps),
``refine_solve`` (the MAP solve). This module keeps the result (``Refinement``,
``correction_transforms``) and ``refine_frames``, and re-exports the names its importers use.

Pure numerics: arrays in, arrays out; mm, radians, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from crossline.geometry import make_transform, rotvec_to_matrix, transform_points
from crossline.scan.refine_crossings import HALF_MM, MIN_ANGLE_DEG, Crossings, find_crossings, usable_centres
from crossline.scan.refine_crossings import MAX_WIDTH_RATIO as MAX_WIDTH_RATIO
from crossline.scan.refine_prior import ArmPrior
from crossline.scan.refine_prior import _prior_sparse as _prior_sparse
from crossline.scan.refine_prior import prior_covariance as prior_covariance
from crossline.scan.refine_solve import solve_errors

__all__ = [
    "ArmPrior",
    "Crossings",
    "Refinement",
    "correction_transforms",
    "find_crossings",
    "refine_frames",
    "solve_errors",
    "usable_centres",
]


@dataclass
class Refinement:
    """Per-frame pose errors found, the corrected points and what the solve saw."""

    frames: np.ndarray  # (F,) frame numbers
    rotation: np.ndarray  # (F, 3) estimated orientation error ω (base frame), rad
    translation: np.ndarray  # (F, 3) estimated flange position error t (base frame), mm
    origins: np.ndarray  # (F, 3) rotation centres used (flange origins), base frame
    points: np.ndarray  # (N, 3) corrected points
    frame_rms: np.ndarray  # (F,) RMS of the correction over each frame's points, mm
    crossings: Crossings
    diagnostics: dict[str, Any] = field(default_factory=dict)
    # (D, F, 6) the errors left after the solve, drawn from its posterior (ω rad, t mm), or None
    posterior: np.ndarray | None = None

    def transforms(self) -> np.ndarray:
        """Corrections (F, 4, 4): refined p_base = C @ reported p_base; refined T_base_tool = C @ T."""
        return correction_transforms(self.rotation, self.translation, self.origins)


# ----------------------------------------------------------------------------- solve


def correction_transforms(rotation: np.ndarray, translation: np.ndarray,
                          origins: np.ndarray) -> np.ndarray:
    """Corrections C (F, 4, 4) undoing errors (ω, t) about ``origins``: p_true = C @ p_reported."""
    Rinv = np.swapaxes(rotvec_to_matrix(np.asarray(rotation, dtype=np.float64)), 1, 2)
    o = np.asarray(origins, dtype=np.float64)
    # p_rep − o_rep = R(ω) (p_true − o_rep + t)  =>  p_true = R^T (p_rep − o_rep) + o_rep − t
    return make_transform(Rinv, o - np.asarray(translation) - np.einsum("fij,fj->fi", Rinv, o))


# ----------------------------------------------------------------------------- all of it


def refine_frames(
    frame: np.ndarray,
    laser: np.ndarray,
    points: np.ndarray,
    viewpoints: np.ndarray,
    prior: ArmPrior,
    *,
    frames: np.ndarray | None = None,
    times: np.ndarray | None = None,
    origins: np.ndarray | None = None,
    half_mm: float = HALF_MM,
    min_angle_deg: float = MIN_ANGLE_DEG,
    crossing_mask: np.ndarray | None = None,
    huber: float = 2.0,
    threads: int = 1,
    draws: int = 0,
    seed: int = 0,
    overwrite_points: bool = False,
) -> Refinement:
    """Refine every frame's pose from the crossings of its stripes with other frames' stripes.

    ``frame`` (N,) frame numbers, ``laser`` (N,) codes (1 = A, 2 = B, others only moved),
    ``points`` (N, 3) base frame. ``frames`` (F,) sorted frame numbers to solve for (default:
    those of the points), ``viewpoints`` (F, 3) their camera centres, ``times`` (F,) their
    times in s (None: the frames' errors are taken as independent), ``origins`` (F, 3) their
    flange origins (the centre of the orientation error; default the camera centres).
    ``half_mm`` is the half-length of stripe fitted either side of a crossing and
    ``min_angle_deg`` the smallest angle at which two stripes may cross to be used;
    ``crossing_mask`` (N,) bool, if given, says which points may make crossings (e.g.
    :func:`usable_centres`); every point is moved with its frame all the same. ``draws`` > 0
    draws the errors left after the solve from its posterior (``Refinement.posterior``, for the
    report's uncertainty), reproducibly from ``seed``. With ``overwrite_points`` the moved
    points are written over ``points`` (a float64 array the caller gives up: a long scan's
    points are not held twice).
    """
    import time

    t0 = time.perf_counter()
    frame = np.asarray(frame)
    if frame.dtype.kind not in "iu":  # an int32 frame column stays one: no copy of it
        frame = frame.astype(np.int64)
    p = np.asarray(points, dtype=np.float64)
    frames = np.unique(frame) if frames is None else np.asarray(frames, dtype=np.int64)
    F = len(frames)
    fpos = np.searchsorted(frames, frame)
    if len(frame) < 2**31:
        fpos = fpos.astype(np.int32)  # an index per point, held to the end: 4 B a point less
    if F == 0 or (fpos >= F).any() or (frames[np.clip(fpos, 0, F - 1)] != frame).any():
        raise ValueError("every point's frame must be one of `frames`")
    if times is not None and (len(times) != F or np.any(np.diff(np.asarray(times, float)) <= 0)):
        # the prior's correlation is a function of the time between frames in frame order
        raise ValueError("`times` must give one increasing time per frame of `frames`")
    views = np.asarray(viewpoints, dtype=np.float64)
    org = views if origins is None else np.asarray(origins, dtype=np.float64)
    lab = np.asarray(laser)
    if lab.dtype.kind not in "iu":
        lab = lab.astype(np.int64)
    ab = (lab == 1) | (lab == 2)
    use = ab
    if crossing_mask is not None:
        mask = np.asarray(crossing_mask, dtype=bool)
        if mask.shape != lab.shape:
            raise ValueError(f"crossing_mask has shape {mask.shape}, the points {lab.shape}")
        use = ab & mask
    # the points that may cross by index: no copies of a long scan's arrays
    subset = None if use.all() else np.flatnonzero(use).astype(np.int32 if len(p) < 2**31 else np.int64)
    not_crossing = int((ab & ~use).sum())
    del ab, use  # 2 B a point less while the crossings are searched
    cr = find_crossings(fpos, lab, p, views, half_mm=half_mm, min_angle_deg=min_angle_deg,
                        threads=threads, subset=subset)
    del subset
    t1 = time.perf_counter()
    e, beta, info = solve_errors(cr, org, prior, times, huber=huber, draws=draws, seed=seed)
    posterior = info.pop("posterior", None)
    C = correction_transforms(e[:, :3], e[:, 3:], org)
    # a block of rows at a time: (out - p) ** 2 of a long scan would be two more copies of it,
    # and the squared shifts are summed per frame as they come (not held: 8 B a point)
    out = p if overwrite_points else np.empty_like(p)
    sum2 = np.zeros(F)
    max2 = 0.0
    for r0 in range(0, len(p), 1 << 20):
        rows = slice(r0, r0 + (1 << 20))
        moved = transform_points(C, p[rows], fpos[rows])
        d = moved - p[rows]
        d2 = np.einsum("ij,ij->i", d, d)
        sum2 += np.bincount(fpos[rows], d2, F)
        max2 = max(max2, float(d2.max(initial=0.0)))
        out[rows] = moved
    cnt = np.bincount(fpos, minlength=F)
    frame_rms = np.sqrt(sum2 / np.maximum(cnt, 1))
    seen = np.zeros(F, bool)
    seen[cr.frame_a] = True
    seen[cr.frame_b] = True
    info.update(
        frames=F,
        frames_with_crossings=int(seen.sum()),
        same_frame_crossings=int((cr.frame_a == cr.frame_b).sum()),
        centres_not_crossing=not_crossing,
        candidates=cr.counts,
        ab_offset_mm=beta,
        correction_rms_mm=float(np.sqrt(sum2.sum() / max(len(p), 1))),
        correction_max_mm=float(np.sqrt(max2)),
        seconds_crossings=t1 - t0,
        seconds=time.perf_counter() - t0,
    )
    return Refinement(frames, e[:, :3], e[:, 3:], org, out, frame_rms, cr, info, posterior)

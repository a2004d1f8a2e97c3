"""The arm's pose errors left in a fused scan, as draws: written by fuse, read by the report.

Each draw gives every frame of the scan an error (ω, t) of its arm pose, a small rotation
about the frame's flange origin and a translation, both in the base frame (as
:mod:`crossline.scan.refine` defines them): drawn from the pose refinement's posterior where
the scan was refined, else from the arm's prior. The report's Monte Carlo moves each point by
its frame's drawn error (its ``arm`` contributor: the errors that the frames of a pass share,
which resampling the frames does not see).

File: ``data/processed/<capture>/<scan>.arm.npz`` (NumPy ``savez``): ``frames`` (F,) int64,
``origins`` (F, 3) mm, ``sigmas`` (6,) the draws' RMS per axis (rad, mm), ``scaled``
(D, F, 6) float16, each draw in units of that RMS (3 significant digits are more than an
uncertainty needs, and halve the file of a long scan), ``kind`` "posterior" or "prior", and
``centre`` "flange" (each origin the flange position of its row of the scan's frames.csv) or
"camera" (the camera centres stood in: fused without a frames table); files written before it
was recorded have none. The frames and the flange origins are how the report knows the draws
are of the scan it measures (:func:`crossline.report.scan_data._same_scan_arm`).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crossline.errors import CrosslineError
from crossline.io.atomic import atomic_path

__all__ = ["ArmDraws", "read_arm_draws", "write_arm_draws"]

KINDS = ("posterior", "prior")
CENTRES = ("flange", "camera")


@dataclass(frozen=True)
class ArmDraws:
    """Draws (D, F, 6) of every frame's remaining pose error (ω rad, t mm), base frame."""

    frames: np.ndarray  # (F,) sorted frame numbers
    origins: np.ndarray  # (F, 3) the rotations' centres (flange origins), base frame, mm
    draws: np.ndarray  # (D, F, 6) float32
    kind: str  # "posterior" (after pose refinement) or "prior" (the arm's poses as reported)
    centre: str | None = None  # "flange" (frames.csv's), "camera" (stood in) or None (not known)

    def displacements(self, frame: np.ndarray, points: np.ndarray, d: int) -> np.ndarray:
        """How draw ``d`` moves each point (N, 3) of frame ``frame`` (N,): ω × (p − o) + t."""
        k = np.searchsorted(self.frames, frame)
        e = self.draws[d][k]
        return np.cross(e[:, :3], points - self.origins[k]) + e[:, 3:]


def write_arm_draws(path: str | Path, a: ArmDraws) -> None:
    """Write the draws atomically (a complete file or none)."""
    d = np.asarray(a.draws, dtype=np.float64).reshape(-1, 6)
    sig = np.sqrt(np.mean(d * d, axis=0)) if d.size else np.ones(6)
    sig = np.where(sig > 0, sig, 1.0)  # an axis of zeros stays zeros
    more = {} if a.centre is None else {"centre": np.array(a.centre)}
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, frames=np.asarray(a.frames, np.int64), origins=np.asarray(a.origins, np.float64),
                 sigmas=sig, scaled=(a.draws / sig).astype(np.float16), kind=np.array(a.kind), **more)


def read_arm_draws(path: str | Path) -> ArmDraws:
    """The draws of ``path``; CrosslineError naming the file and what is wrong."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            frames, origins = np.asarray(z["frames"]), np.asarray(z["origins"], np.float64)
            sig, scaled, kind = np.asarray(z["sigmas"], np.float64), z["scaled"], str(z["kind"])
            centre = str(z["centre"]) if "centre" in z.files else None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise CrosslineError(f"{path}: not an arm-draws file of the fuse stage ({exc})") from None
    F = len(frames)
    if (frames.ndim != 1 or frames.dtype.kind not in "iu" or origins.shape != (F, 3)
            or sig.shape != (6,) or scaled.ndim != 3 or scaled.shape[1:] != (F, 6)
            or kind not in KINDS or np.any(np.diff(frames) <= 0) or centre not in (*CENTRES, None)):
        raise CrosslineError(
            f"{path}: arm draws malformed: frames {frames.shape} {frames.dtype} (increasing whole "
            f"numbers), origins {origins.shape} (F, 3), sigmas {sig.shape} (6,), draws "
            f"{scaled.shape} (D, F, 6), kind {kind!r} ({' or '.join(KINDS)}), centre {centre!r} "
            f"({' or '.join(CENTRES)})")
    for name, a in (("origins", origins), ("sigmas", sig), ("draws", scaled)):
        if not np.isfinite(a).all():  # fuse writes finite draws (their RMS > 0) only
            raise CrosslineError(f"{path}: arm draws malformed: '{name}' holds non-finite values; "
                                 "the fuse stage writes finite ones only")
    return ArmDraws(frames.astype(np.int64), origins, (scaled.astype(np.float32) * sig).astype(
        np.float32), kind, centre)

"""Camera centres in the base frame from points known in both the camera and the base frame.

Split from the fuse stage's module (issue 21.3; now :mod:`crossline.fuse.cloud`). Each point
of a scan is known in the camera frame and in the base frame, and one rigid motion (Kabsch)
maps the first to the second, its translation being the camera centre; frames whose points
are collinear borrow the centre of the nearest frame that has one. :class:`FrameMoments`
gathers the same per-frame sums chunk by chunk, so that a long scan need not hold its
camera-frame points.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FrameMoments", "camera_centres"]


def camera_centres(
    frame: np.ndarray, p_cam: np.ndarray, p_base: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (base frame) per frame from points known in both frames.

    Returns the sorted unique frames (F,) and their centres (F, 3); frames whose points are
    too few or collinear get the centre of the nearest frame (by number) that has one. If no
    frame has one, the centres are NaN.
    """
    frame = np.asarray(frame, dtype=np.int64)
    frames, inv, counts = np.unique(frame, return_inverse=True, return_counts=True)
    F = len(frames)
    pc = np.asarray(p_cam, dtype=np.float64)
    pb = np.asarray(p_base, dtype=np.float64)
    def per_frame(w: np.ndarray) -> np.ndarray:
        return np.bincount(inv, weights=w, minlength=F)

    mc = np.stack([per_frame(pc[:, i]) for i in range(3)], 1) / counts[:, None]
    mb = np.stack([per_frame(pb[:, i]) for i in range(3)], 1) / counts[:, None]
    # one centred column at a time: a long scan's (N, 3) copies would cost 24 B a point each
    qb = [pb[:, j] - mb[inv, j] for j in range(3)]
    H = np.empty((F, 3, 3))
    for i in range(3):
        qc = pc[:, i] - mc[inv, i]
        for j in range(3):
            H[:, i, j] = per_frame(qc * qb[j])
    del qb, qc
    return frames, _kabsch_centres(frames, counts, mc, mb, H)


def _kabsch_centres(frames: np.ndarray, counts: np.ndarray, mc: np.ndarray, mb: np.ndarray,
                    H: np.ndarray) -> np.ndarray:
    """Camera centres (F, 3) from each frame's point means in cam and base (F, 3) and their
    centred cross-covariance H (F, 3, 3); see :func:`camera_centres`."""
    F = len(frames)
    U, s, Vt = np.linalg.svd(H)
    ok = (counts >= 3) & (s[:, 1] > 1e-6 * np.maximum(s[:, 0], 1e-300))
    D = np.ones((F, 3))
    D[:, 2] = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    R = np.swapaxes(Vt, 1, 2) @ (D[:, :, None] * np.swapaxes(U, 1, 2))
    centres = mb - np.einsum("fij,fj->fi", R, mc)
    if not ok.any():
        return np.full((F, 3), np.nan)
    good = np.flatnonzero(ok)
    pos = np.searchsorted(frames[good], frames)
    lo = good[np.clip(pos - 1, 0, len(good) - 1)]
    hi = good[np.clip(pos, 0, len(good) - 1)]
    nearest = np.where(np.abs(frames[hi] - frames) <= np.abs(frames - frames[lo]), hi, lo)
    return centres[nearest]


class FrameMoments:
    """Per-frame means and centred cross-covariances of points known in cam and base,
    gathered chunk by chunk, that give :func:`camera_centres` without holding the
    camera-frame points (a long scan's (N, 3) array of them is 24 B a point). Each chunk's
    moments are centred on its own frame means and chunks are merged by the parallel-axis
    rule, so the result is the one-pass-over-all answer to rounding."""

    def __init__(self) -> None:
        self._parts: list[tuple[np.ndarray, ...]] = []

    def add(self, frame: np.ndarray, p_cam: np.ndarray, p_base: np.ndarray) -> None:
        """Take in one chunk of points: frames (n,), cam (n, 3), base (n, 3)."""
        if len(frame) == 0:
            return
        frames, inv, counts = np.unique(np.asarray(frame, np.int64), return_inverse=True,
                                        return_counts=True)
        F = len(frames)
        pc = np.asarray(p_cam, dtype=np.float64)
        pb = np.asarray(p_base, dtype=np.float64)
        mc = np.stack([np.bincount(inv, pc[:, i], F) for i in range(3)], 1) / counts[:, None]
        mb = np.stack([np.bincount(inv, pb[:, i], F) for i in range(3)], 1) / counts[:, None]
        qc, qb = pc - mc[inv], pb - mb[inv]
        H = np.stack([np.stack([np.bincount(inv, qc[:, i] * qb[:, j], F) for j in range(3)], 1)
                      for i in range(3)], 1)
        self._parts.append((frames, counts, mc, mb, H))

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Sorted frames (F,) and camera centres (F, 3) in the base frame, as
        :func:`camera_centres` gives them."""
        if not self._parts:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        fr, cnt, mc, mb, H = (np.concatenate(a) for a in zip(*self._parts, strict=True))
        frames, inv = np.unique(fr, return_inverse=True)
        F = len(frames)
        counts = np.bincount(inv, cnt, F)
        Mc = np.stack([np.bincount(inv, cnt * mc[:, i], F) for i in range(3)], 1) / counts[:, None]
        Mb = np.stack([np.bincount(inv, cnt * mb[:, i], F) for i in range(3)], 1) / counts[:, None]
        dc, db = mc - Mc[inv], mb - Mb[inv]
        HH = np.empty((F, 3, 3))
        for i in range(3):
            for j in range(3):
                HH[:, i, j] = np.bincount(inv, H[:, i, j] + cnt * dc[:, i] * db[:, j], F)
        return frames, _kabsch_centres(frames, counts.round().astype(np.int64), Mc, Mb, HH)

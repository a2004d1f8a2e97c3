"""The room's light in scan frames, taken out with the scan's own laser-off frames (issue 18.5).

A rig whose laser pattern holds ``off`` frames (``A, B, AB, off``) records the scene under the
room's light alone every few frames. The extraction already takes out what of that light is
broader than the widest stripe: where it stands above the threshold, runs are found in the
frame less its local background (a grey opening, :mod:`crossline.scan.stripe_frame`). What it
cannot take out is the room's light on structure as narrow as a stripe: print, tool marks, a
bright edge under a lamp, found as stripes or pulling a centre towards them. That is what the
off frames give, and all that is subtracted:

- each off frame is median-filtered over 3 x 3 px (it keeps edges and structure of 2 px and
  more, and cuts the noise to about 0.4 of a pixel's) and its narrow structure taken as its
  white top-hat by the stage's own opening (:func:`structure_of`), kept where it stands
  ``STRUCTURE_SIGMAS`` of the pixel's noise above the opening, 0 elsewhere: a laser frame
  whose room's light holds nothing narrow is extracted exactly as without off frames, with
  no noise added;
- a laser frame has subtracted the smaller of the structure of the last off frame before it
  and of the first after it, and only where the two agree within ``AGREE_SIGMAS`` of the
  pixel's noise everywhere: a scanner that moves between its off frames shifts every edge of
  the room's light, and whatever is subtracted then (the smaller, the mean, either one) leaves
  a ridge as wide as the shift, which is found as a stripe. Frames before the scan's first off
  frame and after its last have one neighbour only, which cannot show that nothing moved;
  they too are extracted as without off frames, and the stage counts them all.

The noise is read and shot noise, ``var = v0 + g * level``, fitted to the differences of
neighbouring pixels of each off frame (:func:`noise_of`). Pixels clipped in the laser frame
stay clipped. :func:`read_order` gives the order in which a slice of the scan is read so that
every off frame is read once, before the laser frames that need it; :class:`OffFrames` holds
the off frames' structure while the stage's worker threads need it, and no longer.
"""

from __future__ import annotations

import threading
from collections import Counter

import cv2
import numpy as np

from crossline.errors import StageError
from crossline.robust import MAD_TO_SIGMA
from crossline.scan.stripe_frame import remove_local_background

__all__ = ["AGREE_SIGMAS", "OFF_MODES", "STRUCTURE_SIGMAS", "OffFrames", "agree", "brackets",
           "noise_of", "read_order", "structure_of", "subtract_structure"]

OFF_MODES = ("subtract", "ignore")
STRUCTURE_SIGMAS = 4.0  # narrow room light is kept where it stands this many noise sigmas out
AGREE_SIGMAS = 6.0  # two off frames agree where their structure differs by less than this
Structure = tuple[np.ndarray, np.ndarray]  # an off frame's narrow room light, and its level


def brackets(states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every frame, the index of the last ``off`` frame before it and of the first after
    it (-1 where there is none); ``states`` is the scan's laser state per frame."""
    off = np.flatnonzero(np.asarray(states).astype(str) == "off")
    i = np.arange(len(states))
    if off.size == 0:
        return np.full(i.size, -1, np.int64), np.full(i.size, -1, np.int64)
    k = np.searchsorted(off, i)  # off frames before i
    kn = np.searchsorted(off, i, side="right")  # off frames up to i
    prev = np.where(k > 0, off[np.maximum(k - 1, 0)], -1)
    nxt = np.where(kn < off.size, off[np.minimum(kn, off.size - 1)], -1)
    return prev.astype(np.int64), nxt.astype(np.int64)


def read_order(lo: int, hi: int, states: np.ndarray) -> list[tuple[int, bool]]:
    """The scan indices to read for the slice ``[lo, hi)``, as ``(index, extract)`` pairs.

    Each off frame comes before the laser frames whose *next* off frame it is; the off frames
    just outside the slice that its first and last laser frames need are read as well, with
    ``extract`` False (their centres are the neighbouring slice's). Every index of the slice
    appears once with ``extract`` True.
    """
    states = np.asarray(states).astype(str)
    prev, nxt = brackets(states)
    out: list[tuple[int, bool]] = []
    group: list[int] = []
    lasers = [i for i in range(lo, hi) if states[i] != "off"]
    if lasers and prev[lasers[0]] >= 0 and prev[lasers[0]] < lo:
        out.append((int(prev[lasers[0]]), False))
    for i in range(lo, hi):
        if states[i] == "off":
            out.append((i, True))
            out.extend((g, True) for g in group)
            group = []
        else:
            group.append(i)
    if group:
        n = nxt[group[-1]]
        if n >= hi:
            out.append((int(n), False))
        out.extend((g, True) for g in group)
    return out


def noise_of(img: np.ndarray) -> tuple[float, float]:
    """The sensor's noise in a frame as ``var = v0 + g * level`` (read noise and shot noise),
    fitted to the robust variance of neighbouring pixels' differences in eight bins of level
    (every 32nd line: enough for a robust spread). Returns ``(v0, g)``."""
    x = img[::32].astype(np.float32)
    d = np.abs(np.diff(x, axis=1)).ravel()
    lev = (0.5 * (x[:, 1:] + x[:, :-1])).ravel()
    edges = np.unique(np.quantile(lev, np.linspace(0.0, 1.0, 9)))
    which = np.clip(np.searchsorted(edges, lev, side="right") - 1, 0, max(edges.size - 2, 0))
    lv, var = [], []
    for k in np.unique(which):
        sel = which == k
        lv.append(float(np.median(lev[sel])))
        var.append(float((MAD_TO_SIGMA * np.median(d[sel])) ** 2 / 2.0))  # d: absolute differences
    if len(lv) < 2:
        return max(var[0], 0.25), 0.0
    g = max(float(np.polyfit(lv, var, 1)[0]), 0.0)  # the slope; the intercept robustly below
    return max(float(np.median(np.asarray(var) - g * np.asarray(lv))), 0.25), g


def structure_of(off: np.ndarray, max_width: float, noise: tuple[float, float]) -> Structure:
    """The room's light on structure narrower than ``max_width`` in one off frame, and the
    level it stands on (both float32, the frame's layout): the 3 x 3 median's white top-hat,
    kept where it is ``STRUCTURE_SIGMAS`` of the noise (:func:`noise_of`) or more."""
    med = cv2.medianBlur(np.ascontiguousarray(off), 3)  # integer frames: exact, and fast
    top = remove_local_background(med, max_width).astype(np.float32)
    med = med.astype(np.float32)
    v0, g = noise
    k2 = STRUCTURE_SIGMAS**2
    faint = cv2.compare(cv2.multiply(top, top), cv2.addWeighted(med, k2 * g, med, 0.0, k2 * v0), cv2.CMP_LT)
    np.copyto(top, 0.0, where=faint.view(bool))
    return top, med


def agree(a: Structure, b: Structure, noise: tuple[float, float]) -> bool:
    """Whether the room's narrow light stood still between two off frames (each
    :func:`structure_of`): nowhere do their structures differ by ``AGREE_SIGMAS`` of a pixel's
    noise at the brighter one's level (``noise`` from :func:`noise_of`)."""
    v0, g = noise
    k2 = AGREE_SIGMAS**2
    level = cv2.max(a[1], b[1])
    d = cv2.absdiff(a[0], b[0])
    moved = cv2.compare(cv2.multiply(d, d), cv2.addWeighted(level, k2 * g, level, 0.0, k2 * v0), cv2.CMP_GE)
    return cv2.countNonZero(moved) == 0


def subtract_structure(img: np.ndarray, structure: np.ndarray, data_max: float) -> np.ndarray:
    """``img`` less ``structure`` (the laser frame's room light on narrow structure, rounded to
    ``img``'s type), saturating at 0; pixels at ``data_max`` (clipped) stay there."""
    top = int(min(data_max, np.iinfo(img.dtype).max))
    img = np.ascontiguousarray(img)
    out = cv2.subtract(img, structure)
    out[img >= top] = top
    return out


class OffFrames:
    """The off frames' narrow room light of one slice ``[lo, hi)`` of a scan, for the stage's
    worker threads.

    Frames are read in :func:`read_order`, so an off frame is handed in (:meth:`put`, or
    :meth:`failed` if it could not be read) before any laser frame that waits for it in
    :meth:`subtract`; each off frame's structure is dropped once the last laser frame between
    it and its neighbour is done, so at most a few are held at any time.
    """

    def __init__(self, states: np.ndarray, lo: int, hi: int, names: list[str], max_width: float):
        states = np.asarray(states).astype(str)
        self.prev, self.next = brackets(states)
        self._names = names
        self._max_width = max_width
        pairs = Counter((int(self.prev[i]), int(self.next[i])) for i in range(lo, hi) if states[i] != "off")
        self._pair_refs = dict(pairs)
        self._off_refs = Counter(k for pair in pairs if min(pair) >= 0 for k in pair)
        self._ready = {k: threading.Event() for k in self._off_refs}
        self._light: dict[int, tuple[Structure, tuple[float, float]]] = {}
        self._rooms: dict[tuple[int, int], np.ndarray | None] = {}
        self._lock = threading.Lock()

    def put(self, k: int, off: np.ndarray) -> None:
        """Off frame ``k`` (scan index), as read."""
        if k in self._ready:
            try:
                noise = noise_of(off)
                self._light[k] = structure_of(off, self._max_width, noise), noise
            finally:
                self._ready[k].set()

    def failed(self, k: int) -> None:
        """Off frame ``k`` could not be read: the laser frames waiting for it stop with an error."""
        if k in self._ready:
            self._ready[k].set()

    def subtract(self, i: int, img: np.ndarray, data_max: float) -> tuple[np.ndarray, bool]:
        """Laser frame ``i`` less the narrow room light of its neighbouring off frames, and
        whether it was subtracted (see the module's notes for when it is not)."""
        pair = (int(self.prev[i]), int(self.next[i]))
        if min(pair) < 0:
            return img, False
        try:
            with self._lock:
                room = self._rooms.get(pair, False)
            if room is False:
                light = []
                for k in pair:
                    self._ready[k].wait()
                    if k not in self._light:
                        raise StageError(f"off frame {self._names[k]} could not be read, and the room's "
                                         f"light of frame {self._names[i]} is taken from it")
                    light.append(self._light[k])
                (a, na), (b, nb) = light
                noise = (max(na[0], nb[0]), max(na[1], nb[1]))
                room = None
                if agree(a, b, noise):
                    room = np.rint(cv2.min(a[0], b[0])).clip(0, np.iinfo(img.dtype).max).astype(img.dtype)
                with self._lock:
                    room = self._rooms.setdefault(pair, room)
            return (img, False) if room is None else (subtract_structure(img, room, data_max), True)
        finally:
            self._release(pair)

    def _release(self, pair: tuple[int, int]) -> None:
        with self._lock:
            self._pair_refs[pair] -= 1
            if self._pair_refs[pair]:
                return
            self._rooms.pop(pair, None)
            for k in pair:
                self._off_refs[k] -= 1
                if not self._off_refs[k]:
                    self._light.pop(k, None)

"""Which laser made each stripe centre: the paper's periodic A, B, AB rule (eq. 14-15), hardened.

A-frame and B-frame centres belong to their laser. A centre of an AB frame at column ``u`` and
row ``v`` is compared with the references: the centres of the latest A frame and of the
latest B frame in the same column. The paper labels it with the laser whose reference is
within ``T`` px (the nearest if both are). Beyond the paper:

- **no stale references**: a reference frame more than ``max_frame_gap`` frames before the AB
  frame is not used; an AB frame without both references (a missing A or B frame, an ``off``
  frame in its place, the start of the scan) is dropped whole and counted, because with one
  reference only a centre of the other laser near the crossing would be mislabelled silently;
- **prediction** (``predict``): the stripe moves between frames as the arm moves; each
  reference is extrapolated to the AB frame from the last two frames of its laser (same
  column, nearest row, at most ``T`` px per frame apart), so ``T`` can stay tight at any
  scanning speed (the first AB frame of a scan has a single frame per laser: not predicted);
- **unique match** (``ambiguity_px``): where both references are within ``T`` and the two
  distances differ by less than ``ambiguity_px`` (near the crossing of the stripes, where A and
  B are only a few pixels apart) the centre is dropped as ambiguous instead of guessed;
  ``ambiguity_px = 0`` is the paper's rule;
- **one centre per reference centre**: if two AB centres of one column are matched to the same
  reference centre, only the nearer keeps the label (the other is a conflict, dropped); two
  segments of one laser in one column (at a step) have two reference centres and both stay;
- **one laser per stripe**: the AB centres are linked into stripe traces by position alone; a
  run of up to ``ISLAND_MAX`` centres with one label next to the other label, or of up to
  ``ISOLATED_MAX`` between centres left unlabelled, is dropped as inconsistent: a stale
  reference of one laser can lie on the other's stripe for a few columns (an occlusion edge, a
  limb, a steep flank), never along a whole stripe;
- **no single-laser frames** (``order``, a :class:`~crossline.scan.cross_order.CrossOrder`):
  in a scan without A or without B frames (a scanner that lights both lines in every frame),
  AB frames are told apart by the order of the cross that the calibration fixes, and once
  told apart the stripes are followed from AB frame to AB frame;
- merged segments (flag ``MERGED`` from the extractor: two stripes in one blob) of AB frames
  are dropped, centres of ``off`` frames are dropped; every drop is counted by reason.

Everything is vectorised per frame; the frame loop carries the last two frames of each laser,
so a long scan is processed batch by batch with :class:`Disambiguator`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from crossline.errors import StageError
from crossline.jit import jit
from crossline.scan.centreline import link_traces, trace_position
from crossline.scan.cross_order import CrossOrder
from crossline.scan.stripes import MERGED

__all__ = ["DROP_REASONS", "Disambiguator", "bridge_gaps", "disambiguate", "nearest_in_column",
           "reference_gap"]

DROP_REASONS = ("off_frame", "merged", "no_reference", "unmatched", "ambiguous", "conflict",
                "inconsistent")
_BIG = 1.0e6  # key = u * _BIG + v orders centres by column, then row (|v| < 1e5 px)
ISLAND_MAX = 3  # longest run of one label inside a stripe trace of the other that is dropped
ISOLATED_MAX = 8  # the same between centres left unlabelled (the end trimming would take most of it)
FOLLOW_MIN = 0.3  # share of a stripe piece the frames before label for it to follow them
FOLLOW_AGREE = 0.8  # and the share of those labels that must agree


def nearest_in_column(
    ref_u: np.ndarray, ref_v: np.ndarray, u: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For each query (u, v): the nearest reference row in the same column, and its distance.

    References must be sorted by (u, v). A query whose column has no reference gets
    index -1 and distance inf.
    """
    n = ref_u.size
    if n == 0 or u.size == 0:
        return np.full(u.size, -1, np.int64), np.full(u.size, np.inf)
    ref_u = np.asarray(ref_u, dtype=np.float64)
    ref_v = np.asarray(ref_v, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    j = np.searchsorted(ref_u * _BIG + ref_v, u * _BIG + v)
    return _nearest_of_two(ref_u, ref_v, u, v, j)


@jit
def _nearest_of_two(ref_u, ref_v, u, v, j):  # pragma: no cover - compiled
    """Of the references at j - 1 and j (same column only), the nearer; ties to j - 1."""
    n = ref_u.size
    idx = np.full(u.size, -1, np.int64)
    best = np.full(u.size, np.inf)
    for i in range(u.size):
        for jj in (j[i] - 1, j[i]):
            if 0 <= jj < n and ref_u[jj] == u[i]:
                d = abs(ref_v[jj] - v[i])
                if d < best[i]:
                    best[i] = d
                    idx[i] = jj
    return idx, best


@dataclass
class _Ref:
    """One reference frame of a laser: its number and its centres sorted by (u, v)."""

    frame: int
    u: np.ndarray
    v: np.ndarray


def _sorted_ref(frame: int, u: np.ndarray, v: np.ndarray, bridge: int = 0) -> _Ref:
    o = np.lexsort((v, u))
    u, v = u[o], v[o]
    if bridge >= 1:
        u, v = bridge_gaps(u, v, bridge)
    return _Ref(frame, u, v)


def bridge_gaps(
    u: np.ndarray, v: np.ndarray, max_gap: int, step_px: float = 2.5, kink_px: float = 1.5
) -> tuple[np.ndarray, np.ndarray]:
    """A reference line with its short gaps filled: centres (sorted by u, v) plus the rows,
    linearly interpolated, of the columns missing between two centres of the same stripe.

    A faint or speckled stripe falls below the threshold in a column here and there; without
    a reference in that column an AB centre there could not be labelled. A centre with no
    successor in the next column is joined to the first centre beyond a gap of up to
    ``max_gap`` missing columns whose step per column continues its own (within ``kink_px``
    rows per column) or, with no step known, is at most ``step_px`` per column; a jump (an
    edge, a step, another surface) is not bridged. Returns (u, v) sorted by (u, v).
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if u.size < 2 or max_gap < 1:
        return u, v
    fu, fv = _bridge_nb(u, v, int(max_gap), float(step_px), float(kink_px))
    if fu.size == 0:
        return u, v
    uu = np.concatenate([u, fu])
    vv = np.concatenate([v, fv])
    o = np.lexsort((vv, uu))
    return uu[o], vv[o]


@jit
def _nearest_in(u, v, end, p, col, target):  # pragma: no cover - compiled
    """Index of the centre of column ``col`` nearest to row ``target``, and its distance.

    ``u`` is sorted; ``end[i]`` is where the column of centre i ends; the search walks on
    from ``p``, the first centre of a column at or before ``col`` (-1, inf if there is none).
    """
    n = u.size
    while p < n and u[p] < col:
        p = end[p]
    if p >= n or u[p] != col:
        return -1, np.inf
    best = np.inf
    idx = -1
    for j in range(p, end[p]):
        d = abs(v[j] - target)
        if d < best:
            best = d
            idx = j
    return idx, best


@jit
def _bridge_nb(u, v, max_gap, step_px, kink_px):  # pragma: no cover - compiled
    """The filled columns of :func:`bridge_gaps` (u, v of the new centres only)."""
    n = u.size
    start = np.empty(n, np.int64)  # first and one past the last centre of each one's column
    end = np.empty(n, np.int64)
    a = 0
    for i in range(1, n + 1):
        if i == n or u[i] != u[a]:
            for k in range(a, i):
                start[k] = a
                end[k] = i
            a = i
    fu = np.empty(n * max_gap)
    fv = np.empty(n * max_gap)
    k = 0
    near = step_px + kink_px
    for i in range(n):
        nxt = end[i]  # the next column's first centre, if it is the next column
        _, d_next = _nearest_in(u, v, end, nxt, u[i] + 1.0, v[i])
        if d_next <= near:
            continue
        q = start[i] - 1  # back, column by column, to the one at u - 1
        while q >= 0 and u[q] > u[i] - 1.0:
            q = start[q] - 1
        jp, d_prev = -1, np.inf
        if q >= 0:
            jp, d_prev = _nearest_in(u, v, end, start[q], u[i] - 1.0, v[i])
        known = d_prev <= near
        step = v[i] - v[jp] if known else 0.0
        for g in range(2, max_gap + 2):  # the next centre g columns on: g - 1 missing
            j, d = _nearest_in(u, v, end, nxt, u[i] + g, v[i] + g * step)
            if d <= (kink_px if known else step_px) * g:
                for m in range(1, g):
                    fu[k] = u[i] + m
                    fv[k] = v[i] + (v[j] - v[i]) * m / g
                    k += 1
                break
    return fu[:k], fv[:k]


@dataclass
class Disambiguator:
    """Labels the centres of a scan frame by frame, carrying the latest A and B frames."""

    threshold_px: float = 10.0
    max_frame_gap: int = 3
    ambiguity_px: float = 3.0
    predict: bool = True
    bridge_columns: int = 0
    track: bool = False
    order: CrossOrder | None = None
    refs: dict[str, list[_Ref]] = field(default_factory=lambda: {"A": [], "B": []})
    tracked: dict[str, _Ref] = field(default_factory=dict)
    ordered: dict[str, list[_Ref]] = field(default_factory=lambda: {"A": [], "B": []})
    counts: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.threshold_px > 0:
            raise ValueError(f"threshold_px must be > 0, got {self.threshold_px}")
        if self.max_frame_gap < 1:
            raise ValueError(f"max_frame_gap must be >= 1, got {self.max_frame_gap}")
        if self.ambiguity_px < 0:
            raise ValueError(f"ambiguity_px must be >= 0, got {self.ambiguity_px}")
        c = self.counts
        c.setdefault("centres_in", 0)
        c.setdefault("frames", {"A": 0, "B": 0, "AB": 0, "off": 0})
        c.setdefault("centres_by_state", {"A": 0, "B": 0, "AB": 0, "off": 0})
        c.setdefault("labelled", {"A": 0, "B": 0})
        c.setdefault("labelled_in_AB", {"A": 0, "B": 0})
        c.setdefault("dropped", dict.fromkeys(DROP_REASONS, 0))
        c.setdefault("AB_frames_without_reference", {"A": 0, "B": 0})
        if self.order is not None:
            c.setdefault("labelled_by_order", {"frames": 0, "by_order": 0, "by_previous_frames": 0})

    def _reference(self, laser: str, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The laser's reference centres for ``frame`` (predicted if asked), or None if stale.

        With ``track``, the labelled stripe of the latest AB frame (when newer than the laser's
        own latest frame) is the reference where it has centres, the prediction from the
        laser's own frames filling the other columns, and all of it is moved on to ``frame``
        at its rate since the laser's latest frame.
        """
        refs = self.refs[laser]
        if not refs or frame - refs[-1].frame > self.max_frame_gap:
            return None
        t = self.tracked.get(laser)
        if not (self.track and t is not None and t.frame > refs[-1].frame):
            return self._predicted(refs, frame)
        # the tracked stripe, completed where it has no centre by the prediction at its frame,
        # then moved on at its rate since the laser's own latest frame
        pu, pv = self._predicted(refs, t.frame)
        free = ~np.isin(pu, t.u)
        last = _sorted_ref(t.frame, np.concatenate([t.u, pu[free]]), np.concatenate([t.v, pv[free]]))
        return self._predicted([refs[-1], last], frame)

    def _predicted(self, refs: list[_Ref], frame: int) -> tuple[np.ndarray, np.ndarray]:
        """The latest frame of a laser, each centre moved on at its rate since the frame before."""
        last = refs[-1]
        if not self.predict or len(refs) < 2 or last.u.size == 0:
            return last.u, last.v
        prev = refs[-2]
        if last.frame - prev.frame > 2 * self.max_frame_gap or prev.u.size == 0:
            return last.u, last.v
        j, d = nearest_in_column(prev.u, prev.v, last.u, last.v)
        # the same stripe in the two frames: it may move up to T px per frame between them
        ok = d <= self.threshold_px * (last.frame - prev.frame)
        rate = np.where(ok, (last.v - prev.v[np.maximum(j, 0)]) / (last.frame - prev.frame), 0.0)
        pv = last.v + rate * (frame - last.frame)
        o = np.lexsort((pv, last.u))
        return last.u[o], pv[o]

    def process(
        self, frame: int, state: str, u: np.ndarray, v: np.ndarray, flags: np.ndarray,
        image: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Label one frame's centres: (label per centre: 'A', 'B' or '' if dropped, distance px).

        The distance is to the matched (predicted) reference for AB frames, NaN otherwise.
        Frames must come in time order, every frame of the scan, with or without centres.
        ``u, v`` are where the centres are matched, column by column: the image's, or the
        trace space of :func:`crossline.scan.centreline.trace_space`, with the image's own
        ``(u, v)`` in ``image`` (the cross's order is a matter of the image).
        """
        c = self.counts
        n = u.size
        if state not in c["frames"]:
            raise StageError(f"frame {frame}: unknown laser state {state!r}")
        c["frames"][state] += 1
        c["centres_in"] += n
        c["centres_by_state"][state] += n
        label = np.full(n, "", dtype="<U2")
        dist = np.full(n, np.nan)
        if state in ("A", "B"):
            label[:] = state
            c["labelled"][state] += n
            self.refs[state] = [*self.refs[state][-1:], _sorted_ref(frame, u, v, self.bridge_columns)]
            return label, dist
        if state == "off":
            c["dropped"]["off_frame"] += n
            return label, dist
        # an AB frame
        ref = {laser: self._reference(laser, frame) for laser in ("A", "B")}
        missing = [laser for laser, r in ref.items() if r is None]
        for laser in missing:
            c["AB_frames_without_reference"][laser] += 1
        if missing and self.order is None:
            c["dropped"]["no_reference"] += n
            return label, dist
        merged = (flags & MERGED) != 0
        c["dropped"]["merged"] += int(merged.sum())
        if missing:  # no single-laser frame to go by: the order of the cross decides
            return self._by_order(frame, u, v, merged, label, dist, (u, v) if image is None else image)
        lab, d = self._match(u, v, merged, ref)
        if self.track:  # this frame's labelled stripes: the freshest reference for the next
            for laser, code in (("A", 1), ("B", 2)):
                mine = lab == code
                self.tracked[laser] = _sorted_ref(frame, u[mine], v[mine], self.bridge_columns)
        return self._finish(lab, d, label, dist)

    def _match(self, u: np.ndarray, v: np.ndarray, merged: np.ndarray,
               ref: dict[str, tuple[np.ndarray, np.ndarray] | None],
               count: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Codes (1 = A, 2 = B, 0 = dropped) and distances of AB centres matched to references."""
        c = self.counts if count else {"dropped": dict.fromkeys(DROP_REASONS, 0)}
        n = u.size
        (ua, va), (ub, vb) = ref["A"], ref["B"]
        ja, da = nearest_in_column(ua, va, u, v)
        jb, db = nearest_in_column(ub, vb, u, v)
        T = self.threshold_px
        in_a = (da <= T) & ~merged
        in_b = (db <= T) & ~merged
        both = in_a & in_b
        with np.errstate(invalid="ignore"):  # inf - inf where neither reference is in the column
            ambiguous = both & (np.abs(da - db) < self.ambiguity_px)
        is_a = in_a & ~ambiguous & (~in_b | (da < db))
        is_b = in_b & ~ambiguous & ~is_a
        unmatched = ~merged & ~in_a & ~in_b
        # tie (da == db) with ambiguity_px == 0: the paper gives no rule; drop as ambiguous
        tie = both & ~ambiguous & (da == db)
        is_b &= ~tie
        ambiguous |= tie
        c["dropped"]["unmatched"] += int(unmatched.sum())
        c["dropped"]["ambiguous"] += int(ambiguous.sum())
        d = np.where(is_a, da, np.where(is_b, db, np.inf))
        # one centre per reference centre: two AB centres matched to the same reference centre
        # cannot both be that stripe, the nearer keeps it (two segments of one laser in one
        # column, at a step or an occlusion, have two reference centres and both stay)
        lab = np.where(is_a, 1, np.where(is_b, 2, 0))
        ref_idx = np.where(is_a, ja, np.where(is_b, jb, -1))
        if n > 1:
            o = np.lexsort((d, ref_idx, lab, u))
            dup = np.zeros(n, bool)
            dup[o[1:]] = ((u[o[1:]] == u[o[:-1]]) & (lab[o[1:]] == lab[o[:-1]]) & (lab[o[1:]] > 0)
                          & (ref_idx[o[1:]] == ref_idx[o[:-1]]))
            c["dropped"]["conflict"] += int(dup.sum())
            lab = np.where(dup, 0, lab)
        inconsistent = _trace_minority(u, v, lab, merged)
        c["dropped"]["inconsistent"] += int(inconsistent.sum())
        lab = np.where(inconsistent, 0, lab)
        return lab, d

    def _by_order(self, frame: int, u: np.ndarray, v: np.ndarray, merged: np.ndarray,
                  label: np.ndarray, dist: np.ndarray,
                  image: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Label an AB frame without single-laser references: the cross's order and the frames before.

        The stripe pieces of :meth:`CrossOrder.labels` are one laser each. A piece whose
        centres the latest AB frames labelled (carried on as references) for at least
        ``FOLLOW_MIN`` of it, by ``FOLLOW_AGREE`` or more one way, keeps that laser: once
        told apart, the stripes are followed from frame to frame as they move, where the order
        of the cross can flip (a surface turned past the crossing line) or be silent (one
        branch hidden). Any other piece takes the label of the order, or none. A centre whose
        own reference label contradicts its piece's is dropped as inconsistent.
        """
        c = self.counts
        co = c["labelled_by_order"]
        co["frames"] += 1
        n = u.size
        by_order, piece = self.order.labels(*image, ~merged, link=(u, v))
        ref = {laser: self._ordered_reference(laser, frame) for laser in ("A", "B")}
        if any(r is not None for r in ref.values()):  # one laser's stripe may not be seen yet
            none = (np.empty(0), np.empty(0))
            prior, d = self._match(u, v, merged, {k: none if r is None else r for k, r in ref.items()},
                                   count=False)
        else:
            prior, d = np.zeros(n, np.int64), np.full(n, np.inf)
        lab = np.zeros(n, np.int64)
        has = piece >= 0
        if has.any():
            n_piece = int(piece.max()) + 1
            pa = np.bincount(piece[has], prior[has] == 1, n_piece)
            pb = np.bincount(piece[has], prior[has] == 2, n_piece)
            size = np.bincount(piece[has], minlength=n_piece)
            follow = (pa + pb >= FOLLOW_MIN * size)
            code_prior = np.where(follow & (pa >= FOLLOW_AGREE * (pa + pb)), 1,
                                  np.where(follow & (pb >= FOLLOW_AGREE * (pa + pb)), 2, 0))
            code_order = np.zeros(n_piece, np.int64)
            np.maximum.at(code_order, piece[has], by_order[has])
            code = np.where(code_prior > 0, code_prior, code_order)
            lab[has] = code[piece[has]]
            followed = np.zeros(n, bool)
            followed[has] = code_prior[piece[has]] > 0
        else:
            followed = np.zeros(n, bool)
        contra = (lab > 0) & (prior > 0) & (prior != lab)
        c["dropped"]["inconsistent"] += int(contra.sum())
        lab[contra] = 0
        co["by_previous_frames"] += int((followed & (lab > 0)).sum())
        co["by_order"] += int((~followed & (lab > 0)).sum())
        c["dropped"]["unmatched"] += int(((lab == 0) & ~merged & ~contra).sum())
        for laser, code in (("A", 1), ("B", 2)):
            mine = lab == code
            if mine.any():  # a frame without the laser's stripe leaves its last one standing
                self.ordered[laser] = [*self.ordered[laser][-1:],
                                       _sorted_ref(frame, u[mine], v[mine], self.bridge_columns)]
        d = np.where(prior == lab, d, np.nan)
        return self._finish(lab, d, label, dist)

    def _ordered_reference(self, laser: str, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The laser's stripe in the latest AB frames labelled without references, moved on."""
        refs = self.ordered[laser]
        if not refs or frame - refs[-1].frame > self.max_frame_gap:
            return None
        return self._predicted(refs, frame)

    def _finish(self, lab: np.ndarray, d: np.ndarray, label: np.ndarray,
                dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Labels and distances from codes; count them."""
        c = self.counts
        label[lab == 1] = "A"
        label[lab == 2] = "B"
        dist[lab > 0] = d[lab > 0]
        for laser, code in (("A", 1), ("B", 2)):
            k = int((lab == code).sum())
            c["labelled"][laser] += k
            c["labelled_in_AB"][laser] += k
        return label, dist


def _trace_minority(u: np.ndarray, v: np.ndarray, lab: np.ndarray, merged: np.ndarray) -> np.ndarray:
    """AB-frame centres whose label (1 = A, 2 = B) is a short island inside a stripe of the other.

    A stripe is one laser along its length. The centres (labelled or dropped, 0) are linked
    into traces by position alone; along a trace, a run of at most ``ISLAND_MAX`` centres with
    one label next to the other label, or of at most ``ISOLATED_MAX`` between centres left
    unlabelled, is an island: a stale reference of one laser lying on the other's stripe for
    a few columns (an occlusion edge, a limb, a steep flank the references lag behind).
    Where two stripes really meet at a shallow angle and a trace passes from one to the
    other, the label changes once, with long runs on both sides: nothing is dropped there.
    Merged centres (``merged``) link the traces but are skipped in the runs.
    """
    out = np.zeros(u.size, bool)
    if u.size < 3 or not (lab > 0).any():
        return out
    # merged centres link the traces but hold no run: a wide stripe at grazing incidence is
    # flagged merged here and there along its length, which must not cut it into pieces too
    # short to show an island
    prev = link_traces(np.zeros(u.size, np.int64), np.zeros(u.size, "<U1"), u, v)
    trace_all, _, _ = trace_position(prev, u)
    idx = np.flatnonzero(~merged)
    trace = trace_all[idx]
    order = np.lexsort((u[idx], trace))
    t, la = trace[order], lab[idx][order]
    new_run = np.r_[True, (t[1:] != t[:-1]) | (la[1:] != la[:-1])]
    run = np.cumsum(new_run) - 1
    starts = np.flatnonzero(new_run)
    length = np.diff(np.r_[starts, t.size])
    run_trace, run_lab = t[starts], la[starts]
    same_trace_before = np.r_[False, run_trace[1:] == run_trace[:-1]]
    same_trace_after = np.r_[run_trace[:-1] == run_trace[1:], False]
    before = np.r_[0, run_lab[:-1]]
    after = np.r_[run_lab[1:], 0]
    other = 3 - run_lab  # the other laser's code
    limit = np.where((before == other) | (after == other), ISLAND_MAX, ISOLATED_MAX)
    island = (run_lab > 0) & (length <= limit) & same_trace_before & same_trace_after \
        & (before != run_lab) & (after != run_lab)
    out[idx[order]] = island[run]
    return out


def disambiguate(
    frame: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    flags: np.ndarray,
    scan_frames: np.ndarray,
    scan_states: np.ndarray,
    *,
    threshold_px: float = 10.0,
    max_frame_gap: int = 3,
    ambiguity_px: float = 3.0,
    predict: bool = True,
    scan: str = "scan",
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Label every centre of a scan A, B or '' (dropped); also return distances and counts.

    ``frame, u, v, flags`` are the centres (rows of a stripes table, in frame order);
    ``scan_frames, scan_states`` every frame of the scan in time order with its laser state.
    Raises :class:`StageError` if the scan has AB frames but no A or no B frame.
    """
    check_pattern(scan_states, scan)
    d = Disambiguator(threshold_px, max_frame_gap, ambiguity_px, predict)
    label = np.full(frame.size, "", dtype="<U2")
    dist = np.full(frame.size, np.nan)
    bounds = np.searchsorted(frame, scan_frames, side="left")
    ends = np.searchsorted(frame, scan_frames, side="right")
    if frame.size and np.any(np.diff(frame) < 0):
        raise StageError(f"scan {scan}: centres are not in frame order")
    for f, s, a, b in zip(scan_frames.tolist(), list(scan_states), bounds, ends, strict=True):
        lab, dd = d.process(int(f), str(s), u[a:b], v[a:b], flags[a:b])
        label[a:b] = lab
        dist[a:b] = dd
    return label, dist, d.counts


def reference_gap(period: list[str]) -> int:
    """Frames from an AB frame back to its older reference (A or B), at worst, in a periodic pattern.

    ``["A", "B", "AB"]`` gives 2, ``["A", "B", "AB", "AB"]`` 3; a pattern without AB frames 1.
    """
    n = len(period)
    gap = 1
    for i, state in enumerate(period):
        if state != "AB":
            continue
        for laser in ("A", "B"):
            back = [k for k in range(1, n + 1) if period[(i - k) % n] == laser]
            if back:
                gap = max(gap, back[0])
    return gap


def check_pattern(states: np.ndarray, scan: str) -> None:
    """Raise :class:`StageError` if a scan has AB frames but lacks A or B frames to label them."""
    s = set(map(str, states))
    if "AB" in s:
        lacking = [laser for laser in ("A", "B") if laser not in s]
        if lacking:
            raise StageError(
                f"scan {scan}: has AB frames but no {' and no '.join(lacking)} frame; the "
                f"crossed stripes of its AB frames cannot be told apart (the periodic pattern "
                f"A, B, AB of the paper needs both single-laser frames)"
            )

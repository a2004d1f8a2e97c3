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
directly (dense Cholesky up to ``DENSE_MAX_FRAMES`` frames, sparse LU beyond); robust
(Huber) weights are re-estimated a few times.
What a frame's crossings do not constrain (on a plane: the two in-plane shifts and the
turn about the normal; for a single stripe also the tilt about the stripe) stays at what
the prior and the neighbouring frames say, and an error common to all frames (the whole
scan rigidly moved) is unobservable and stays at zero.

Pure numerics: arrays in, arrays out; mm, radians, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from crossline.geometry import make_transform, rotvec_to_matrix, transform_points
from crossline.report.fitting import robust_sigma

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

LEVER_MM = 300.0  # rotation prior from the position figure: the error spread over one arm link
HALF_MM = 0.6  # stripe fitted either side of a crossing, mm
MIN_ANGLE_DEG = 30.0  # stripes crossing at a smaller angle are not used
MIN_SPACINGS = 6  # a crossing's stripe curves reach at least this many point spacings either side
_QUERY_ROWS = 500_000  # seeds searched for B neighbours at a time
MAX_WIDTH_RATIO = 2.0  # centres of column cuts longer than this x their laser's median: no crossings


@dataclass(frozen=True)
class ArmPrior:
    """The arm's reported-pose error model: per-axis sigmas, their smooth share and correlation time."""

    sigma_mm: float  # per axis, 1 sigma, flange position (base frame)
    sigma_rad: float  # per axis, 1 sigma, flange orientation
    smooth_fraction: float = 0.9  # the Gauss-Markov part's sigma over the whole (variances add)
    corr_time_s: float = 0.3  # correlation time of the smooth part

    def __post_init__(self) -> None:
        if not (self.sigma_mm > 0 and self.sigma_rad > 0 and 0 <= self.smooth_fraction <= 1
                and self.corr_time_s > 0):
            raise ValueError(
                f"arm prior out of range: sigma_mm={self.sigma_mm} (> 0), sigma_rad={self.sigma_rad} "
                f"(> 0), smooth_fraction={self.smooth_fraction} (0..1), "
                f"corr_time_s={self.corr_time_s} (> 0)")

    @classmethod
    def from_precision(
        cls, precision_mm: float, precision_rad: float | None = None, *,
        smooth_fraction: float = 0.9, corr_time_s: float = 0.3,
    ) -> ArmPrior:
        """Prior from datasheet figures read as 2 sigma of the 3-D error (so sigma = p / (2 sqrt 3)).

        Without a rotation figure, the rotation sigma is the position sigma over ``LEVER_MM``
        (300 mm, about one link of a portable arm): the wrist's position error spread over
        the last link is what tilts the flange.
        """
        s = float(precision_mm) / (2.0 * np.sqrt(3.0))
        r = s / LEVER_MM if precision_rad is None else float(precision_rad) / (2.0 * np.sqrt(3.0))
        return cls(s, r, float(smooth_fraction), float(corr_time_s))

    def sigmas(self) -> np.ndarray:
        """Per-dof 1-sigma (6,): rotation x, y, z (rad), then translation x, y, z (mm)."""
        return np.array([self.sigma_rad] * 3 + [self.sigma_mm] * 3)


@dataclass(frozen=True)
class Crossings:
    """Where an A stripe of one frame crosses a B stripe of another (K crossings)."""

    frame_a: np.ndarray  # (K,) index into the refinement's frames of the A stripe's frame
    frame_b: np.ndarray  # (K,) likewise for the B stripe
    x: np.ndarray  # (K, 3) crossing point, base frame
    n: np.ndarray  # (K, 3) unit surface normal (A tangent x B tangent), towards the camera
    gap: np.ndarray  # (K,) A curve minus B curve along n, mm
    # (K,) the gap's noise per unit point noise: root of the two fits' prediction variances
    sigma: np.ndarray
    angle: np.ndarray  # (K,) crossing angle between the stripes, rad
    counts: dict[str, int] = field(default_factory=dict)  # candidates lost at each step


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

    def transforms(self) -> np.ndarray:
        """Corrections (F, 4, 4): refined p_base = C @ reported p_base; refined T_base_tool = C @ T."""
        return correction_transforms(self.rotation, self.translation, self.origins)


# ----------------------------------------------------------------------------- stripes


def usable_centres(laser: np.ndarray, width: np.ndarray,
                   max_ratio: float = MAX_WIDTH_RATIO) -> np.ndarray:
    """Centres (N,) bool whose column cut is at most ``max_ratio`` x their laser's median cut.

    A cut much longer than its laser's typical one crosses the stripe where it runs steeply
    through the column (or two stripes merged), and a centre fitted along the column is
    biased there, several times more than the centres of shorter cuts
    (``python benchmarks/bench_refine_bias.py`` prints the centres' mean and RMS error in px,
    along the column, against the true centre line by cut length). The Gaussian extractor's
    fit across steep stripes (``stripes.fit_across``) removes most of that bias, and with it
    this filter hardly changes the refined ball (docs/method.md, pose refinement); it stays
    for the other extractors and for merged stripes. Such centres may still be measured
    points, but must not decide a crossing. ``max_ratio`` 0 (or inf) keeps all; a NaN width is kept.
    """
    lab = np.asarray(laser)
    w = np.asarray(width, dtype=np.float64)
    keep = np.ones(len(w), bool)
    if not max_ratio or not np.isfinite(max_ratio):
        return keep
    for code in np.unique(lab):
        sel = lab == code
        known = sel & np.isfinite(w)
        if known.any():
            keep[sel] = ~(w[sel] > max_ratio * np.median(w[known]))
    return keep


def _stripes(frame_pos: np.ndarray, laser: np.ndarray, p: np.ndarray):
    """Order points by stripe (frame, laser), then along the stripe's principal direction.

    Returns the order (N,), stripe id of each ordered point, and per stripe its start and end
    in the ordered arrays.
    """
    key = frame_pos.astype(np.int64) * 4 + laser.astype(np.int64)
    ukey, sid, cnt = np.unique(key, return_inverse=True, return_counts=True)
    del key
    S = len(ukey)
    mean = np.stack([np.bincount(sid, p[:, i], S) for i in range(3)], 1) / cnt[:, None]
    # one centred column at a time: (N, 3) temporaries cost a long scan 24 B a point each
    q = [p[:, i] - mean[sid, i] for i in range(3)]
    C = np.empty((S, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            C[:, i, j] = C[:, j, i] = np.bincount(sid, q[i] * q[j], S)
    axis = np.linalg.eigh(C)[1][:, :, 2]
    along = q[0] * axis[sid, 0]
    for i in (1, 2):
        along += q[i] * axis[sid, i]
    del q
    order = np.lexsort((along, sid))
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    return order, sid[order], start, start + cnt


def _curves(p: np.ndarray, seeds: np.ndarray, lo: np.ndarray, hi: np.ndarray,
            half_mm: float, width: int):
    """Quadratic space curves x(s) = c0 + c1 s + c2 s^2 fitted along a stripe around each seed.

    ``p`` are the ordered points, ``seeds`` positions in it, ``lo``/``hi`` the stripe's
    bounds; the window is the stripe's points within ``half_mm`` (3-D) of the seed among the
    ``width`` neighbours either side in stripe order; ``s`` is the distance along the
    window's principal direction. Returns c (K, 3, 3) with rows c0, c1, c2, the inverse
    normal matrix (K, 3, 3) (the prediction variance of the fit) and whether it is usable
    (enough points, on both sides of the seed).
    """
    off = np.arange(-width, width + 1)
    idx = seeds[:, None] + off[None, :]
    inside = (idx >= lo[:, None]) & (idx < hi[:, None])
    idx = np.clip(idx, lo[:, None], hi[:, None] - 1)
    d = p[idx] - p[seeds][:, None, :]  # (K, W, 3), relative to the seed for conditioning
    m = inside & (np.sum(d * d, axis=2) <= half_mm * half_mm)
    w = m.astype(np.float64)
    n = w.sum(1)
    mu = np.matmul(w[:, None, :], d)[:, 0] / np.maximum(n, 1)[:, None]
    dq = (d - mu[:, None, :]) * w[:, :, None]
    t0 = np.linalg.eigh(np.matmul(np.swapaxes(dq, 1, 2), dq))[1][:, :, 2]
    s = np.matmul(d, t0[:, :, None])[:, :, 0]
    M = np.stack([w, s * w, s * s * w], axis=2)  # (K, W, 3), masked rows are zero
    A = np.matmul(np.swapaxes(M, 1, 2), M)
    s_in = np.where(m, s, np.nan)
    with np.errstate(all="ignore"):
        ok = (n >= 8) & (np.nanmin(s_in, 1) < -0.4 * half_mm) & (np.nanmax(s_in, 1) > 0.4 * half_mm)
    A[~ok] = np.eye(3)
    Ainv = np.linalg.inv(A)
    c = np.matmul(Ainv, np.matmul(np.swapaxes(M, 1, 2), d))
    c[:, 0, :] += p[seeds]
    return c, Ainv, ok


def _closest(ca: np.ndarray, cb: np.ndarray, iters: int = 5):
    """Closest points of pairs of quadratic curves (Gauss-Newton from s = r = 0)."""
    K = len(ca)
    s = np.zeros(K)
    r = np.zeros(K)
    for _ in range(iters):
        xa = ca[:, 0] + s[:, None] * ca[:, 1] + (s * s)[:, None] * ca[:, 2]
        xb = cb[:, 0] + r[:, None] * cb[:, 1] + (r * r)[:, None] * cb[:, 2]
        ta = ca[:, 1] + 2 * s[:, None] * ca[:, 2]
        tb = cb[:, 1] + 2 * r[:, None] * cb[:, 2]
        d = xa - xb
        J = np.stack([ta, -tb], axis=2)  # (K, 3, 2)
        JtJ = np.einsum("kia,kib->kab", J, J)
        det = JtJ[:, 0, 0] * JtJ[:, 1, 1] - JtJ[:, 0, 1] ** 2
        g = np.einsum("kia,ki->ka", J, d)
        safe = np.abs(det) > 1e-12
        det = np.where(safe, det, 1.0)
        ds = (JtJ[:, 1, 1] * g[:, 0] - JtJ[:, 0, 1] * g[:, 1]) / det
        dr = (JtJ[:, 0, 0] * g[:, 1] - JtJ[:, 0, 1] * g[:, 0]) / det
        s = np.where(safe, s - ds, s)
        r = np.where(safe, r - dr, r)
    xa = ca[:, 0] + s[:, None] * ca[:, 1] + (s * s)[:, None] * ca[:, 2]
    xb = cb[:, 0] + r[:, None] * cb[:, 1] + (r * r)[:, None] * cb[:, 2]
    ta = ca[:, 1] + 2 * s[:, None] * ca[:, 2]
    tb = cb[:, 1] + 2 * r[:, None] * cb[:, 2]
    return s, r, xa, xb, ta, tb


def find_crossings(
    frame_pos: np.ndarray,
    laser: np.ndarray,
    points: np.ndarray,
    viewpoints: np.ndarray,
    *,
    half_mm: float = HALF_MM,
    radius_mm: float | None = None,
    min_angle_deg: float = MIN_ANGLE_DEG,
    threads: int = 1,
) -> Crossings:
    """Every crossing of an A stripe with a B stripe (of any frame, the same one included).

    ``frame_pos`` (N,) is each point's frame as an index 0..F-1, ``laser`` (N,) its laser
    code (1 = A, 2 = B), ``viewpoints`` (F, 3) the camera centre of each frame (orients the
    normals). Candidates are A points (every other one along the stripe) with a B point
    within ``radius_mm`` (default: 3 point spacings, at least 0.1 mm and one spacing of the
    sparser laser); each pair of stripes keeps its closest candidate per 2 mm cell, the two
    stripes are fitted locally by quadratic curves over ``half_mm`` either side (at least
    ``MIN_SPACINGS`` of that laser's point spacings) and the crossing is the closest approach
    of the two curves; it is kept if it lies within half a window of both seeds, the
    stripes cross at ``min_angle_deg`` or more and the gap is under ``radius_mm``.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    fp = np.asarray(frame_pos, dtype=np.int64)
    lab = np.asarray(laser, dtype=np.int64)
    order, sid, start, end = _stripes(fp, lab, p)
    # a long scan's per-point arrays in the narrowest type that holds them (tens of millions
    # of points: each int64 array is 8 B a point)
    small = len(p) < 2**31 and (len(fp) == 0 or int(fp.max()) < 2**31)
    itype = np.int32 if small else np.int64
    order, sid = order.astype(itype), sid.astype(itype)
    po, fo, lo_ = p[order], fp[order].astype(itype), lab[order].astype(np.int8)
    del order
    a = np.flatnonzero(lo_ == 1).astype(itype)
    b = np.flatnonzero(lo_ == 2).astype(itype)
    empty = Crossings(*(np.zeros(0, np.int64),) * 2, np.zeros((0, 3)), np.zeros((0, 3)),
                      np.zeros(0), np.zeros(0), np.zeros(0))
    if len(a) < 8 or len(b) < 8:
        return empty
    # distance between neighbours in the order, a column at a time (no (N, 3) temporaries)
    step = np.diff(po[:, 0]) ** 2
    for i in (1, 2):
        step += np.diff(po[:, i]) ** 2
    np.sqrt(step, out=step)
    along = sid[1:] == sid[:-1]
    spacing = float(np.median(step[along])) if along.any() else 0.05
    # each laser's own point spacing (mm, between neighbouring points of a stripe): a
    # stripe that runs steeply through the image, or meets the surface at a grazing angle,
    # is sampled more sparsely than the other, by a factor of a few on some rigs
    # (docs/method.md, pose refinement)
    sp = {}
    for code in (1, 2):
        m = along & (lo_[1:] == code)
        sp[code] = float(np.median(step[m])) if m.any() else spacing
    if radius_mm is None:
        radius_mm = max(0.1, 3.0 * spacing, sp[1], sp[2])
    # a quadratic needs its points: where a stripe is sampled sparsely (a camera of coarse
    # resolution, or the steeper laser) its window grows to MIN_SPACINGS of them either side,
    # else a HALF_MM window holds too few and no crossing of such a rig is ever fitted
    half = {code: max(half_mm, MIN_SPACINGS * sp[code]) for code in (1, 2)}
    tree = cKDTree(po[b])
    # every other A point is enough to seed: the crossing itself is found by the curve fits
    a = a[::2]
    ia_, ib_, dd_ = [], [], []
    for c0 in range(0, len(a), _QUERY_ROWS):  # in blocks: k distances a row are 64 B
        ac = a[c0:c0 + _QUERY_ROWS]
        dist, jj = tree.query(po[ac], k=4, distance_upper_bound=radius_mm, workers=threads)
        hit = np.isfinite(dist)
        ia_.append(np.broadcast_to(ac[:, None], dist.shape)[hit].astype(np.int64))
        ib_.append(b[jj[hit]].astype(np.int64))
        dd_.append(dist[hit])
    del tree
    ia, ib, dd = np.concatenate(ia_), np.concatenate(ib_), np.concatenate(dd_)
    if len(ia) == 0:
        return empty
    # one seed per stripe pair and 2 mm cell: the closest A-B point pair there
    cell = np.floor(po[ia] / 2.0).astype(np.int64)
    cell -= cell.min(0)
    dims = cell.max(0) + 1
    ck = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    pair = sid[ia].astype(np.int64) * (sid.max() + 1) + sid[ib]
    o = np.lexsort((dd, ck, pair))
    first = np.ones(len(o), bool)
    first[1:] = (pair[o][1:] != pair[o][:-1]) | (ck[o][1:] != ck[o][:-1])
    ia, ib = ia[o[first]], ib[o[first]]
    # window slots either side: the half-length in median point spacings, with room for
    # sparser stretches and for a second segment of the stripe interleaved in the order
    width = {code: int(np.clip(np.ceil(1.6 * half[code] / max(min(spacing, sp[code]), 1e-3)), 8, 200))
             for code in (1, 2)}
    ca, Ainv_a, ok_a = _curves(po, ia, start[sid[ia]], end[sid[ia]], half[1], width[1])
    cb, Ainv_b, ok_b = _curves(po, ib, start[sid[ib]], end[sid[ib]], half[2], width[2])
    ok = ok_a & ok_b
    ia, ib, ca, cb, Ainv_a, Ainv_b = ia[ok], ib[ok], ca[ok], cb[ok], Ainv_a[ok], Ainv_b[ok]
    s, r, xa, xb, ta, tb = _closest(ca, cb)
    nrm = np.cross(ta, tb)
    sin = np.linalg.norm(nrm, axis=1) / np.maximum(
        np.linalg.norm(ta, axis=1) * np.linalg.norm(tb, axis=1), 1e-300)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    x = 0.5 * (xa + xb)
    fa, fb = fo[ia], fo[ib]
    view = np.asarray(viewpoints, dtype=np.float64)[fa] - x
    nrm *= np.where(np.sum(nrm * view, axis=1) < 0, -1.0, 1.0)[:, None]
    gap = np.sum((xa - xb) * nrm, axis=1)
    lev_a = np.einsum("ka,kab,kb->k", np.stack([np.ones_like(s), s, s * s], 1), Ainv_a,
                      np.stack([np.ones_like(s), s, s * s], 1))
    lev_b = np.einsum("ka,kab,kb->k", np.stack([np.ones_like(r), r, r * r], 1), Ainv_b,
                      np.stack([np.ones_like(r), r, r * r], 1))
    keep = ((np.abs(s) <= 0.5 * half[1]) & (np.abs(r) <= 0.5 * half[2])
            & (sin >= np.sin(np.radians(min_angle_deg))) & (np.abs(gap) <= radius_mm))
    # the same crossing found from two cells: keep the one whose seeds were closest to it
    k = np.flatnonzero(keep)
    pr = (sid[ia[k]].astype(np.int64) * (sid.max() + 1) + sid[ib[k]])
    o = np.lexsort((np.abs(s[k]) + np.abs(r[k]), pr))
    k, pr = k[o], pr[o]
    dup = np.zeros(len(k), bool)
    for lag in (1, 2, 3):
        same = pr[lag:] == pr[:-lag]
        close = np.linalg.norm(x[k[lag:]] - x[k[:-lag]], axis=1) < 2 * max(half[1], half[2])
        dup[lag:] |= same & close & ~dup[:-lag]
    k = np.sort(k[~dup])
    # how many candidates survive each step, for the stats: seeds (closest A-B point pairs),
    # both curve fits usable, crossing inside both windows at a fair angle, not a duplicate
    counts = {"seeds": len(ok), "fitted": int(ok.sum()), "kept": int(keep.sum()), "unique": len(k)}
    return Crossings(fa[k].astype(np.int64), fb[k].astype(np.int64), x[k], nrm[k], gap[k],
                     np.sqrt(lev_a[k] + lev_b[k]),
                     np.arcsin(np.clip(sin[k], 0, 1)), counts)


# ----------------------------------------------------------------------------- solve


DENSE_MAX_FRAMES = 800  # up to here the normal equations are solved dense (6F unknowns)
MIN_GAP_SIGMA_MM = 1e-4  # the best a crossing's gap is ever taken to be known (0.1 µm)


def prior_covariance(times: np.ndarray | None, prior: ArmPrior, F: int) -> np.ndarray:
    """Prior correlation (F, F) of each scaled error component between frames.

    Per axis the error is a Gauss-Markov process of sigma ``smooth_fraction`` times the whole
    (correlation exp(-|t_k - t_l| / corr_time_s)) plus an independent part carrying the rest
    of the variance (sigma ``sqrt(1 - smooth_fraction^2)`` times the whole); without times
    the frames are independent.
    """
    rho = prior.smooth_fraction
    if times is None or rho == 0.0:
        return np.eye(F)
    t = np.asarray(times, dtype=np.float64)
    phi = np.exp(-np.abs(t[:, None] - t[None, :]) / prior.corr_time_s)
    return rho * rho * phi + (1.0 - rho * rho) * np.eye(F)


def _prior_sparse(times: np.ndarray | None, prior: ArmPrior, F: int):
    """Square-root information of the same prior, sparse, on [e, s] (s: the smooth part).

    The Gauss-Markov part is Markov, so with it as extra unknowns the information is banded:
    what lets long scans be solved without a dense F x F matrix.
    """
    import scipy.sparse as sp

    rho = prior.smooth_fraction
    eye = sp.identity(6 * F, format="csr")
    if times is None or rho == 0.0:
        return eye, 6 * F
    t = np.asarray(times, dtype=np.float64)
    phi = np.exp(-np.diff(t) / prior.corr_time_s)
    # AR(1) rows on s: s_0 / rho, (s_k - phi s_{k-1}) / (rho sqrt(1 - phi^2))
    q = rho * np.sqrt(np.maximum(1.0 - phi * phi, 1e-12))
    main = sp.diags(np.repeat(np.concatenate([[1.0 / rho], 1.0 / q]), 6), 0, shape=(6 * F, 6 * F))
    lower = sp.diags(np.repeat(-phi / q, 6), -6, shape=(6 * F, 6 * F))
    Ls = (main + lower).tocsr()
    if rho == 1.0:
        return Ls, 6 * F  # e = s
    w = 1.0 / np.sqrt(1.0 - rho * rho)
    # white rows (e - s) / sqrt(1 - rho^2); unknowns ordered [e, s]
    return sp.vstack([sp.hstack([eye * w, -eye * w]),
                      sp.hstack([sp.csr_matrix((6 * F, 6 * F)), Ls])]).tocsr(), 12 * F


def solve_errors(
    cr: Crossings,
    origins: np.ndarray,
    prior: ArmPrior,
    times: np.ndarray | None = None,
    *,
    huber: float = 2.0,
    reject: float = 5.0,
    max_iter: int = 6,
    dense: bool | None = None,
) -> tuple[np.ndarray, float, dict[str, Any]]:
    """MAP pose errors (F, 6) = (ω, t) per frame from the crossings, and the A-minus-B offset β.

    Unknowns are scaled by the prior sigmas. The noise of each crossing is its curve-fit
    prediction variance times one global scale, estimated robustly (MAD) from the residuals
    at each iteration; residuals beyond ``huber`` scaled sigmas get Huber weights, beyond
    ``reject`` none. ``dense`` (default: up to ``DENSE_MAX_FRAMES`` frames) solves the
    normal equations by dense Cholesky, otherwise sparse LU on the banded augmented form.
    """
    import scipy.linalg as sla
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    F = len(origins)
    K = len(cr.gap)
    sig = prior.sigmas()
    info: dict[str, Any] = {"crossings": K}
    if K == 0:
        return np.zeros((F, 6)), 0.0, {**info, "iterations": 0, "used": 0, "rejected": 0}
    dense = F <= DENSE_MAX_FRAMES if dense is None else dense
    if dense:
        # only frames that some crossing sees are unknowns: the prior of the others is
        # marginalised out (a Gaussian's marginal is the sub-block of its covariance) and
        # their errors are predicted afterwards from the solved ones
        seen = np.zeros(F, bool)
        seen[cr.frame_a] = True
        seen[cr.frame_b] = True
        cov = prior_covariance(times, prior, F)
        obs = np.flatnonzero(seen)
        lam = sla.cho_solve(sla.cho_factor(cov[np.ix_(obs, obs)]), np.eye(len(obs)))
        col = np.full(F, -1)
        col[obs] = np.arange(len(obs))
        nu = 6 * len(obs)
        P = np.zeros((nu + 1, nu + 1))
        P[:nu, :nu] = np.kron(lam, np.eye(6))  # frame-major: unknown f * 6 + axis
    else:
        col = np.arange(F)
        L, nu = _prior_sparse(times, prior, F)
        P = sp.block_diag([(L.T @ L), sp.csr_matrix((1, 1))]).tocsc()
    beta_info = 1e-6  # the A-minus-B offset is nearly free (a 1000-sigma prior)
    # Jacobian of the gap: n·(ω_f × (x − o_f) + t_f) − n·(ω_g × (x − o_g) + t_g); on
    # same-frame crossings the two cancel and only beta is seen
    ja = np.hstack([np.cross(cr.x - origins[cr.frame_a], cr.n), cr.n]) * sig
    jb = np.hstack([np.cross(cr.x - origins[cr.frame_b], cr.n), cr.n]) * sig
    rows = np.repeat(np.arange(K), 6)
    J = sp.csr_matrix(
        (np.concatenate([ja.ravel(), -jb.ravel(), np.ones(K)]),
         (np.concatenate([rows, rows, np.arange(K)]),
          np.concatenate([(col[cr.frame_a][:, None] * 6 + np.arange(6)).ravel(),
                          (col[cr.frame_b][:, None] * 6 + np.arange(6)).ravel(), np.full(K, nu)]))),
        shape=(K, nu + 1),
    )
    s0 = np.maximum(cr.sigma, np.median(cr.sigma) * 0.5)
    # no crossing is known better than MIN_GAP_SIGMA_MM: on perfect data the scale would go to
    # zero and the data outweigh the prior by so much that the normal equations lose the
    # unobservable directions to rounding
    floor = MIN_GAP_SIGMA_MM / float(np.median(s0))
    w = np.ones(K)
    scale = max(robust_sigma(cr.gap) / float(np.median(s0)), floor)
    z = np.zeros(nu + 1)
    iterations = 0
    for iterations in range(1, max_iter + 1):  # noqa: B007 (the count is reported)
        wi = w / (scale * s0) ** 2
        JtW = J.T.multiply(wi[None, :]).tocsr()
        g = JtW @ cr.gap
        if dense:
            H = (JtW @ J).toarray() + P
            H[nu, nu] += beta_info
            z_new = sla.cho_solve(sla.cho_factor(H, check_finite=False), g, check_finite=False)
        else:
            H = (JtW @ J + P).tolil()
            H[nu, nu] += beta_info
            z_new = splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A").solve(g)
        res = (cr.gap - J @ z_new) / s0
        new_scale = max(1.4826 * float(np.median(np.abs(res[w > 0]))), floor)
        u = np.abs(res) / new_scale
        w_new = np.where(u <= huber, 1.0, np.where(u <= reject, huber / np.maximum(u, 1e-300), 0.0))
        # converged: the unknowns moved by less than a twentieth of their prior sigma
        done = float(np.max(np.abs(z_new - z))) < 0.05 and np.array_equal(w_new > 0, w > 0)
        z, w, scale = z_new, w_new, new_scale
        if done:
            break
    if dense:
        a = np.zeros((F, 6))
        a[obs] = z[:nu].reshape(-1, 6)
        # the unseen frames: their conditional mean given the seen ones, C_uo C_oo^-1 a_o
        a[~seen] = cov[np.ix_(~seen, obs)] @ (lam @ a[obs])
    else:
        a = z[: 6 * F].reshape(F, 6)
    e = a * sig
    res_mm = cr.gap - J @ z
    used = w > 0
    info.update(
        iterations=iterations, used=int(used.sum()), rejected=int((~used).sum()),
        solver="dense" if dense else "sparse",
        noise_scale=scale,
        gap_rms_before_mm=float(np.sqrt(np.mean((cr.gap[used] - z[nu]) ** 2))),
        gap_rms_after_mm=float(np.sqrt(np.mean(res_mm[used] ** 2))),
    )
    return e, float(z[nu]), info


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
    :func:`usable_centres`); every point is moved with its frame all the same.
    """
    import time

    t0 = time.perf_counter()
    frame = np.asarray(frame, dtype=np.int64)
    p = np.asarray(points, dtype=np.float64)
    frames = np.unique(frame) if frames is None else np.asarray(frames, dtype=np.int64)
    F = len(frames)
    fpos = np.searchsorted(frames, frame)
    if F == 0 or (fpos >= F).any() or (frames[np.clip(fpos, 0, F - 1)] != frame).any():
        raise ValueError("every point's frame must be one of `frames`")
    if times is not None and (len(times) != F or np.any(np.diff(np.asarray(times, float)) <= 0)):
        # the prior's correlation is a function of the time between frames in frame order
        raise ValueError("`times` must give one increasing time per frame of `frames`")
    views = np.asarray(viewpoints, dtype=np.float64)
    org = views if origins is None else np.asarray(origins, dtype=np.float64)
    lab = np.asarray(laser, dtype=np.int64)
    ab = (lab == 1) | (lab == 2)
    use = ab
    if crossing_mask is not None:
        mask = np.asarray(crossing_mask, dtype=bool)
        if mask.shape != lab.shape:
            raise ValueError(f"crossing_mask has shape {mask.shape}, the points {lab.shape}")
        use = ab & mask
    if use.all():  # no copies of a long scan's arrays when every point may cross
        cr = find_crossings(fpos, lab, p, views, half_mm=half_mm, min_angle_deg=min_angle_deg,
                            threads=threads)
    else:
        cr = find_crossings(fpos[use], lab[use], p[use], views, half_mm=half_mm,
                            min_angle_deg=min_angle_deg, threads=threads)
    t1 = time.perf_counter()
    e, beta, info = solve_errors(cr, org, prior, times, huber=huber)
    C = correction_transforms(e[:, :3], e[:, 3:], org)
    out = transform_points(C, p, fpos)
    shift2 = np.sum((out - p) ** 2, axis=1)
    cnt = np.bincount(fpos, minlength=F)
    frame_rms = np.sqrt(np.bincount(fpos, shift2, F) / np.maximum(cnt, 1))
    seen = np.zeros(F, bool)
    seen[cr.frame_a] = True
    seen[cr.frame_b] = True
    info.update(
        frames=F,
        frames_with_crossings=int(seen.sum()),
        same_frame_crossings=int((cr.frame_a == cr.frame_b).sum()),
        centres_not_crossing=int((ab & ~use).sum()),
        candidates=cr.counts,
        ab_offset_mm=beta,
        correction_rms_mm=float(np.sqrt(np.mean(shift2))),
        correction_max_mm=float(np.sqrt(shift2.max())),
        seconds_crossings=t1 - t0,
        seconds=time.perf_counter() - t0,
    )
    return Refinement(frames, e[:, :3], e[:, 3:], org, out, frame_rms, cr, info)

"""Pose refinement from A-B stripe crossings: against injected pose errors on exact scans.

The scans are analytic (tests/test_report_synthetic.py: laser sheets intersected with a
plate and a ball, no renderer), the arm's true flange poses come from the camera poses and
a hand-eye matrix, and known per-frame errors (a Gauss-Markov drift plus white, like a
measuring arm's) are put into the reported poses. What the crossings can see of each
frame's error is its displacement along the surface normal at its stripes; an error common
to the whole scan (the scan moved rigidly) is unobservable, so the figures below are taken
after removing the best rigid motion of the whole cloud, as a fit to the truth would.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from crossline.fuse import camera_centres
from crossline.geometry import (
    fit_sphere,
    invert_transform,
    make_transform,
    orthonormalize,
    rotvec_to_matrix,
    transform_points,
)
from crossline.scan import refine as R
from tests.test_report_synthetic import X_PAPER, scan_points, scene

FPS = 80.0
# the paper's hand-eye matrix, made exactly rigid (its printed digits are not)
X = make_transform(orthonormalize(np.array(X_PAPER)[:3, :3]), np.array(X_PAPER)[:3, 3])
PRIOR = R.ArmPrior.from_precision(0.02)  # the paper's arm: 5.8 µm, 19 µrad per axis


def arm_errors(n: int, prior: R.ArmPrior, seed: int, scale: float = 1.0) -> np.ndarray:
    """(n, 6) errors (ω rad, t mm) drawn from the prior's own model: AR(1) drift + white."""
    rng = np.random.default_rng(seed)
    rho = prior.smooth_fraction
    phi = np.exp(-1.0 / FPS / prior.corr_time_s)
    s = np.empty((n, 6))
    s[0] = rng.standard_normal(6)
    for k in range(1, n):
        s[k] = phi * s[k - 1] + np.sqrt(1 - phi**2) * rng.standard_normal(6)
    return scale * (rho * s + np.sqrt(1 - rho**2) * rng.standard_normal((n, 6))) * prior.sigmas()


def reported(df: pd.DataFrame, T_base_cam: np.ndarray, e: np.ndarray):
    """Reported points and flange origins when the arm's poses carry errors e (reported - true)."""
    Tt = T_base_cam @ invert_transform(X)  # true flange poses
    Rt = Tt[:, :3, :3]
    dth = np.einsum("fji,fj->fi", Rt, e[:, :3])  # the base-frame ω as a flange-frame rotation
    Trep = make_transform(Rt @ rotvec_to_matrix(dth), Tt[:, :3, 3] + e[:, 3:]) @ X
    fr = df["frame"].to_numpy()
    pc = df[["x_cam", "y_cam", "z_cam"]].to_numpy()
    p = transform_points(Trep[fr], pc)
    return p, (Trep @ invert_transform(X))[:, :3, 3]


class Scan:
    """An analytic scan with its truth: points, normals, frames, lasers."""

    def __init__(self, kind: str, noise: float = 0.0, frames: int = 90, rays: int = 1500):
        prims, self.truth = scene(kind)
        self.df, self.T, _ = scan_points(prims, frames=frames, rays=rays, noise=0.0, seed=0)
        self.kind = kind
        self.p_true = self.df[["x", "y", "z"]].to_numpy()
        self.frame = self.df["frame"].to_numpy()
        self.laser = np.where(self.df["laser"] == "A", 1, 2)
        self.times = np.arange(frames) / FPS
        self.normal = np.tile([0.0, 0.0, 1.0], (len(self.p_true), 1))
        if kind == "sphere":
            c = np.array(self.truth["center_base"])
            on = np.abs(np.linalg.norm(self.p_true - c, axis=1) - 12.5) < 1e-6
            self.normal[on] = (self.p_true[on] - c) / 12.5
        if noise:  # measurement noise along the camera ray, as triangulation has it
            rng = np.random.default_rng(7)
            pc = self.df[["x_cam", "y_cam", "z_cam"]].to_numpy()
            pc = pc * (1 + noise * rng.standard_normal(len(pc)) / np.linalg.norm(pc, axis=1))[:, None]
            self.df[["x_cam", "y_cam", "z_cam"]] = pc
            self.p_true = transform_points(self.T[self.frame], pc)

    def refine(self, e: np.ndarray | None, **kw) -> tuple[np.ndarray, R.Refinement]:
        """Reported points with errors e (None: exact poses) and their refinement."""
        e = np.zeros((len(self.T), 6)) if e is None else e
        p, origins = reported(self.df, self.T, e)
        frames, views = camera_centres(self.frame, self.df[["x_cam", "y_cam", "z_cam"]].to_numpy(), p)
        kw.setdefault("times", self.times)
        ref = R.refine_frames(self.frame, self.laser, p, views, PRIOR, frames=frames,
                              origins=origins, **kw)
        return p, ref

    def normal_error(self, q: np.ndarray) -> tuple[float, np.ndarray]:
        """RMS (mm) of the error along the true normal after the best rigid motion of the whole
        cloud is taken out, and the per-point residual errors."""
        dn = np.sum((q - self.p_true) * self.normal, axis=1)
        c = self.p_true.mean(0)
        A = np.hstack([np.cross(self.p_true - c, self.normal), self.normal])
        x, *_ = np.linalg.lstsq(A, dn, rcond=None)
        r = dn - A @ x
        return float(np.sqrt(np.mean(r**2))), r


@pytest.fixture(scope="module")
def ball() -> Scan:
    return Scan("sphere")


@pytest.fixture(scope="module")
def plate() -> Scan:
    return Scan("plane")


def test_prior_from_the_datasheet_figure():
    p = R.ArmPrior.from_precision(0.02)
    assert p.sigma_mm == pytest.approx(0.02 / (2 * np.sqrt(3)))  # 2 sigma of the 3-D error
    assert p.sigma_rad == pytest.approx(p.sigma_mm / 300.0)  # the position figure over one 300 mm link
    q = R.ArmPrior.from_precision(0.03, 1e-4, smooth_fraction=0.5, corr_time_s=1.0)
    assert q.sigma_rad == pytest.approx(1e-4 / (2 * np.sqrt(3)))
    assert q.sigmas().tolist() == [q.sigma_rad] * 3 + [q.sigma_mm] * 3
    for bad in ({"smooth_fraction": 1.5}, {"corr_time_s": 0.0}):
        with pytest.raises(ValueError, match="arm prior out of range"):
            R.ArmPrior.from_precision(0.02, **bad)
    with pytest.raises(ValueError, match=r"sigma_mm=0\.0 "):
        R.ArmPrior.from_precision(0.0)


def test_dense_and_banded_priors_are_the_same_model():
    # the e-block of the banded [e, s] information's inverse is the AR(1)+white covariance
    t = np.cumsum(np.r_[0.0, np.full(9, 0.0125), 0.1, np.full(5, 0.0125)])  # with a gap
    C = R.prior_covariance(t, PRIOR, len(t))
    phi = np.exp(-np.abs(t[:, None] - t[None]) / PRIOR.corr_time_s)
    assert np.allclose(C, 0.81 * phi + 0.19 * np.eye(len(t)))
    L, nu = R._prior_sparse(t, PRIOR, len(t))
    cov = np.linalg.inv((L.T @ L).toarray())
    assert nu == 12 * len(t)
    assert np.allclose(cov[: 6 * len(t): 6, : 6 * len(t): 6], C, atol=1e-9)
    assert np.array_equal(R.prior_covariance(None, PRIOR, 4), np.eye(4))


def test_crossings_of_an_exact_scan_meet_on_the_surface(ball):
    frames, views = camera_centres(ball.frame, ball.df[["x_cam", "y_cam", "z_cam"]].to_numpy(),
                                   ball.p_true)
    cr = R.find_crossings(np.searchsorted(frames, ball.frame), ball.laser, ball.p_true, views)
    assert len(cr.gap) > 1500
    assert np.abs(cr.gap).max() < 2e-5  # quadratic stripe curves meet to 0.02 µm on the ball
    c = np.array(ball.truth["center_base"])
    rad = np.linalg.norm(cr.x - c, axis=1)
    on = rad < 13.0
    assert on.sum() > 500 and (~on).sum() > 500  # crossings on the ball and on the plate
    assert np.abs(rad[on] - 12.5).max() < 2e-5
    assert np.abs(cr.x[~on, 2]).max() < 2e-5
    nb = (cr.x[on] - c) / rad[on, None]
    assert np.degrees(np.arccos(np.clip(np.sum(cr.n[on] * nb, 1), -1, 1))).max() < 0.05
    assert np.all(cr.n[~on, 2] > 0.99999)  # the plate's normal, towards the camera
    assert np.degrees(cr.angle).min() >= 30


def test_crossings_by_slabs_are_those_of_the_whole_scan(ball):
    # a long scan is searched a slab of space at a time (bounded memory): the same crossings,
    # those on a slab's edge included, none twice
    frames, views = camera_centres(ball.frame, ball.df[["x_cam", "y_cam", "z_cam"]].to_numpy(),
                                   ball.p_true)
    fpos = np.searchsorted(frames, ball.frame)
    rng = np.random.default_rng(3)
    p = ball.p_true + 0.002 * rng.standard_normal(ball.p_true.shape)  # gaps that differ
    whole = R.find_crossings(fpos, ball.laser, p, views)
    cr = R.find_crossings(fpos, ball.laser, p, views, slab_points=len(p) // 5)
    assert cr.counts["slabs"] == 5 and "slabs" not in whole.counts
    key = lambda c: np.c_[c.frame_a, c.frame_b, np.round(c.x / 0.2)]  # noqa: E731
    assert len(cr.gap) == len(np.unique(key(cr), axis=0))  # none twice
    # each crossing of the whole search found by slabs, at the same place with the same gap
    pairs = {}
    for i, (a, b) in enumerate(zip(cr.frame_a, cr.frame_b, strict=True)):
        pairs.setdefault((a, b), []).append(i)
    dx, dg = [], []
    for i, (a, b) in enumerate(zip(whole.frame_a, whole.frame_b, strict=True)):
        j = pairs.get((a, b), [])
        d = np.linalg.norm(cr.x[j] - whole.x[i], axis=1) if j else np.array([np.inf])
        k = int(np.argmin(d))
        dx.append(d[k])
        dg.append(abs(cr.gap[j[k]] - whole.gap[i]) if j else np.inf)
    dx, dg = np.array(dx), np.array(dg)
    assert len(whole.gap) > 1500 and abs(len(cr.gap) - len(whole.gap)) <= 0.01 * len(whole.gap)
    assert np.mean(dx < 1e-3) > 0.99 and np.median(dg) < 1e-4


def test_gap_is_the_normal_displacement_of_the_a_frame(plate):
    # lift one AB frame's points by 3 µm: its crossings open by +3 µm (A) or -3 µm (B)
    frames, views = camera_centres(plate.frame, plate.df[["x_cam", "y_cam", "z_cam"]].to_numpy(),
                                   plate.p_true)
    fpos = np.searchsorted(frames, plate.frame)
    f = 47  # pattern A, B, AB: an AB frame
    p = plate.p_true.copy()
    p[fpos == f, 2] += 0.003
    cr = R.find_crossings(fpos, plate.laser, p, views)
    a, b = (cr.frame_a == f) & (cr.frame_b != f), (cr.frame_b == f) & (cr.frame_a != f)
    assert a.sum() > 10 and b.sum() > 10
    assert np.allclose(cr.gap[a], 0.003, atol=1e-6)
    assert np.allclose(cr.gap[b], -0.003, atol=1e-6)
    assert np.abs(cr.gap[~a & ~b]).max() < 1e-6


def test_crossings_of_sparsely_sampled_stripes_are_found(plate):
    # a coarse camera samples its stripes 3x (A) and 5x (B) further apart than this scan's
    # 0.059 mm: the stripe curves' windows widen to 6 spacings of their own laser (before,
    # a fixed 0.6 mm held under 8 points and no crossing of such a rig was ever fitted)
    frames, views = camera_centres(plate.frame, plate.df[["x_cam", "y_cam", "z_cam"]].to_numpy(),
                                   plate.p_true)
    fpos = np.searchsorted(frames, plate.frame)
    key = fpos * 4 + plate.laser
    o = np.lexsort((plate.df["u"].to_numpy(), key))
    first = np.r_[0, np.flatnonzero(np.diff(key[o])) + 1]
    rank = np.empty(len(key), np.int64)
    rank[o] = np.arange(len(o)) - np.repeat(first, np.diff(np.r_[first, len(o)]))
    keep = np.where(plate.laser == 1, rank % 3 == 0, rank % 5 == 0)
    dense = R.find_crossings(fpos, plate.laser, plate.p_true, views)
    cr = R.find_crossings(fpos[keep], plate.laser[keep], plate.p_true[keep], views)
    assert len(cr.gap) == len(dense.gap) > 3000
    assert np.abs(cr.gap).max() < 1e-9 and np.abs(cr.x[:, 2]).max() < 1e-9


def test_exact_scan_stays_exact(ball):
    # nothing to correct: what moves is the quadratic stripe model's own error at the
    # crossings (0.02 µm), a few hundredths of a µm, against the arm's 5.8 µm
    p, ref = ball.refine(None)
    assert np.abs(ref.points - p).max() < 3e-5
    c = np.array(ball.truth["center_base"])
    on = np.linalg.norm(p - c, axis=1) < 12.6
    _, r0, res0 = fit_sphere(p[on])
    _, r1, res1 = fit_sphere(ref.points[on])
    assert abs(r1 - r0) < 1e-5 and np.ptp(res1) < np.ptp(res0) + 5e-5


def test_injected_pose_errors_are_recovered_where_observable(ball):
    e = arm_errors(len(ball.T), PRIOR, seed=1)
    p, ref = ball.refine(e)
    before, _ = ball.normal_error(p)
    after, r = ball.normal_error(ref.points)
    assert before > 0.003  # the arm's error: several µm along the normals
    assert after < 0.0006  # recovered to better than 0.6 µm (noise-free stripes)
    fpos = np.searchsorted(ref.frames, ball.frame)
    per_frame = np.sqrt(np.bincount(fpos, r**2) / np.bincount(fpos))
    seen = np.bincount(ref.crossings.frame_a, minlength=len(ref.frames)) + np.bincount(
        ref.crossings.frame_b, minlength=len(ref.frames))
    assert per_frame[seen >= 20].max() < 0.001  # a frame crossed 20 times: within 1 µm
    assert per_frame.max() < 0.003  # and even a frame crossed 4 times is better than reported
    d = ref.diagnostics
    assert d["frames_with_crossings"] == len(ref.frames) and d["rejected"] < 0.02 * d["crossings"]
    assert d["gap_rms_after_mm"] < 0.05 * d["gap_rms_before_mm"]
    assert abs(d["ab_offset_mm"]) < 1e-4
    # the sphere is the true one again (size from the ball's points alone)
    c = np.array(ball.truth["center_base"])
    on = np.linalg.norm(ball.p_true - c, axis=1) < 12.6
    _, _, res_rep = fit_sphere(p[on])
    _, r_ref, res_ref = fit_sphere(ref.points[on])
    assert abs(2 * r_ref - 25.0) < 0.001 and np.ptp(res_ref) < 0.35 * np.ptp(res_rep)


def test_a_plane_leaves_the_in_plane_motions_at_the_prior(plate):
    # on a plane z = 0 nothing sees a frame's shift along x, y or its turn about z: those
    # stay at the prior's mean (zero) while the height and the tilts are corrected
    e = arm_errors(len(plate.T), PRIOR, seed=2)
    p, ref = plate.refine(e)
    assert np.abs(ref.translation[:, :2]).max() < 0.01 * PRIOR.sigma_mm
    assert np.abs(ref.rotation[:, 2]).max() < 0.01 * PRIOR.sigma_rad
    before, _ = plate.normal_error(p)
    after, _ = plate.normal_error(ref.points)
    assert after < 0.1 * before


def test_noisy_scan_no_pose_error_is_not_distorted():
    s = Scan("sphere", noise=0.002)
    p, ref = s.refine(None)
    c = np.array(s.truth["center_base"])
    on = np.linalg.norm(p - c, axis=1) < 12.6
    _, r0, res0 = fit_sphere(p[on])
    _, r1, res1 = fit_sphere(ref.points[on])
    # corrections from noise alone: well under the arm's sigma, and the ball keeps its size
    assert ref.diagnostics["correction_rms_mm"] < 0.25 * PRIOR.sigma_mm
    assert abs(r1 - r0) < 0.0005
    assert np.std(res1) < np.std(res0) * 1.02
    # and with pose errors on top, the noisy scan comes back near the noise-only one
    e = arm_errors(len(s.T), PRIOR, seed=3)
    p2, ref2 = s.refine(e)
    assert s.normal_error(ref2.points)[0] < 0.35 * s.normal_error(p2)[0]
    _, r2, res2 = fit_sphere(ref2.points[on])
    assert abs(r2 - r0) < 0.002 and np.std(res2) < 1.15 * np.std(res0)


def test_banded_solver_agrees_with_the_dense_one(ball):
    e = arm_errors(len(ball.T), PRIOR, seed=4)
    p, origins = reported(ball.df, ball.T, e)
    frames, views = camera_centres(ball.frame, ball.df[["x_cam", "y_cam", "z_cam"]].to_numpy(), p)
    cr = R.find_crossings(np.searchsorted(frames, ball.frame), ball.laser, p, views)
    ed, bd, _ = R.solve_errors(cr, origins, PRIOR, ball.times, dense=True)
    es, bs, _ = R.solve_errors(cr, origins, PRIOR, ball.times, dense=False)
    assert np.abs(ed - es).max() < 1e-9 and abs(bd - bs) < 1e-9


def test_corrections_undo_known_rigid_errors_exactly():
    rng = np.random.default_rng(0)
    om, t = rng.normal(0, 1e-3, (5, 3)), rng.normal(0, 0.1, (5, 3))
    o = rng.uniform(-300, 300, (5, 3))
    p_true = rng.uniform(-50, 50, (5, 3))
    # reported: p_rep - o = R(ω) (p_true - o + t), o being the reported flange origin
    p_rep = np.einsum("fij,fj->fi", rotvec_to_matrix(om), p_true - o + t) + o
    C = R.correction_transforms(om, t, o)
    back = transform_points(C, p_rep)
    assert np.abs(back - p_true).max() < 1e-10


def test_without_crossings_nothing_moves():
    # one laser only: no crossing, every frame keeps its reported pose
    s = Scan("plane", frames=30, rays=600)
    p, origins = reported(s.df, s.T, arm_errors(30, PRIOR, seed=5))
    only_a = s.laser == 1
    frames, views = camera_centres(s.frame[only_a], s.df[["x_cam", "y_cam", "z_cam"]].to_numpy()[only_a],
                                   p[only_a])
    ref = R.refine_frames(s.frame[only_a], s.laser[only_a], p[only_a], views, PRIOR, frames=frames,
                          origins=origins[frames])
    assert ref.diagnostics["crossings"] == 0
    assert np.array_equal(ref.points, p[only_a])


# ----------------------------------------------------------------------------- rendered


@pytest.mark.slow
def test_rendered_stripes_recover_injected_pose_errors(quick_capture: Path, tmp_path: Path):
    """Real rendered stripes (the quick capture's plate, true calibration), known pose errors.

    The capture's own arm errors are removed (true poses from truth/) and independent ones of
    3x the arm's sigma are put in; a prior of the same (white) model must find their
    observable part through the extraction noise of real images.
    """
    from crossline.geometry import transform_from_pose
    from crossline.scan.stripes import run_extract_stripes
    from crossline.scan.triangulate import run_triangulate
    from crossline.sim import write_true_calibration

    cap = tmp_path / "cap"
    shutil.copytree(quick_capture, cap)
    truth = json.loads((cap / "truth.json").read_text())
    cal = write_true_calibration(cap, tmp_path)
    run_extract_stripes(cap, "plate", tmp_path / "stripes.parquet", extractor="gaussian", threads=2)
    run_triangulate(cap, "plate", tmp_path / "stripes.parquet", *cal, tmp_path / "points.parquet",
                    smooth_px=5)
    df = pd.read_parquet(tmp_path / "points.parquet")
    tp = pd.read_parquet(cap / truth["scans"]["plate"]["poses"]).sort_values("frame")
    X = np.array(truth["T_tool_cam"])
    Tt = transform_from_pose(tp[["x", "y", "z"]].to_numpy(), tp[["qw", "qx", "qy", "qz"]].to_numpy())
    n = len(tp)
    prior = R.ArmPrior(3 * PRIOR.sigma_mm, 3 * PRIOR.sigma_rad, smooth_fraction=0.0)
    e = prior.sigmas() * np.random.default_rng(11).standard_normal((n, 6))
    Rt = Tt[:, :3, :3]
    dth = np.einsum("fji,fj->fi", Rt, e[:, :3])
    Trep = make_transform(Rt @ rotvec_to_matrix(dth), Tt[:, :3, 3] + e[:, 3:])
    pos = np.searchsorted(tp["frame"].to_numpy(), df["frame"].to_numpy())
    pc = df[["x_cam", "y_cam", "z_cam"]].to_numpy()
    M_true, M_rep = (Tt @ X)[pos], (Trep @ X)[pos]
    p_true = transform_points(M_true, pc)
    p_rep = transform_points(M_rep, pc)
    frames, views = camera_centres(df["frame"].to_numpy(), pc, p_rep)
    lab = np.where(df["laser"] == "A", 1, 2)
    ref = R.refine_frames(df["frame"].to_numpy(), lab, p_rep, views, prior, frames=frames,
                          origins=Trep[np.searchsorted(tp["frame"].to_numpy(), frames), :3, 3])
    nt = np.array(truth["scans"]["plate"]["plane_base"][:3])
    nt /= np.linalg.norm(nt)

    def err(q):  # along the plate's normal, without the unobservable common height and tilt
        dn = (q - p_true) @ nt
        A = np.column_stack([np.ones(len(q)), p_true[:, 0], p_true[:, 1]])
        return np.sqrt(np.mean((dn - A @ np.linalg.lstsq(A, dn, rcond=None)[0]) ** 2))

    assert ref.diagnostics["crossings"] > 100
    assert err(p_rep) > 0.01
    assert err(ref.points) < 0.25 * err(p_rep)


def test_usable_centres_keeps_cuts_up_to_the_ratio_of_each_lasers_median():
    laser = np.array([1] * 5 + [2] * 5)
    width = np.array([4, 4, 4, 8, 9, 10, 10, 10, 20, 21], float)
    keep = R.usable_centres(laser, width, 2.0)
    # A's median is 4 (cut 8 kept, 9 not), B's is 10 (20 kept, 21 not)
    assert keep.tolist() == [True] * 4 + [False] + [True] * 4 + [False]
    assert R.usable_centres(laser, width, 0.0).all()
    with_nan = width.copy()
    with_nan[0] = np.nan  # no cut length: nothing to judge by, kept
    assert R.usable_centres(laser, with_nan, 2.0)[0]


def test_biased_long_cut_centres_do_not_move_the_frames():
    # on an exact ball, a patch of laser A's centres comes from long column cuts and lies
    # 5 µm inside the surface (as steep stripes' per-column centres do on rendered scans):
    # used as crossings it moves frames by µm; kept out of them the exact scan stays exact
    s = Scan("sphere")
    c = np.array(s.truth["center_base"])
    on = np.abs(np.linalg.norm(s.p_true - c, axis=1) - 12.5) < 1e-6
    f = s.frame
    patch = on & (s.laser == 1) & (f >= 30) & (f < 50) & (s.p_true[:, 0] > c[0])
    assert patch.sum() > 200
    shift_base = -0.005 * s.normal[patch]  # mm, into the ball
    R_cam = s.T[f[patch], :3, :3]
    s.df.loc[patch, ["x_cam", "y_cam", "z_cam"]] += np.einsum("kji,kj->ki", R_cam, shift_base)
    width = np.where(patch, 15.0, 5.0)
    _, plain = s.refine(None)
    _, masked = s.refine(None, crossing_mask=R.usable_centres(s.laser, width))
    assert plain.diagnostics["correction_rms_mm"] > 0.001
    assert masked.diagnostics["correction_rms_mm"] < 0.0002
    assert masked.diagnostics["centres_not_crossing"] == patch.sum()
    with pytest.raises(ValueError, match="crossing_mask has shape"):
        s.refine(None, crossing_mask=np.ones(3, bool))


def test_posterior_draws_predict_the_error_left_after_refinement():
    """The refinement's posterior draws (perturb-and-MAP) say how large the pose error left
    after the solve is: on a noisy ball scan with arm errors drawn from the prior, the RMS
    error along the surface normals (the whole scan's rigid motion taken out) that the draws
    predict matches the one left, seed by seed; the dense and banded solvers draw the same
    distribution; without crossings the draws are the prior's."""
    s = Scan("sphere", noise=0.002)
    fpos = None
    ratios = []
    for seed in range(3):
        e = arm_errors(len(s.T), PRIOR, seed=seed)
        _, ref = s.refine(e, draws=60, seed=seed)
        fpos = np.searchsorted(ref.frames, s.frame)
        left, _ = s.normal_error(ref.points)
        pred = []
        for d in ref.posterior:
            move = np.cross(d[fpos, :3], ref.points - ref.origins[fpos]) + d[fpos, 3:]
            pred.append(s.normal_error(s.p_true + move)[0])
        ratios.append(left / np.sqrt(np.mean(np.square(pred))))
    # measured 1.13-1.19 over 8 seeds: the Huber weights and the stripes' quadratic model
    # leave a little more than the Gaussian posterior says
    assert 0.8 < np.mean(ratios) < 1.4, ratios
    cr = ref.crossings
    sd = [R.solve_errors(cr, ref.origins, PRIOR, s.times, dense=dn, draws=200, seed=9)[2][
        "posterior"].std(0) for dn in (True, False)]
    assert np.median(np.abs(sd[0] / sd[1] - 1)) < 0.1  # 200 draws: 5 % sampling error each
    none = dataclasses.replace(cr, frame_a=cr.frame_a[:0], frame_b=cr.frame_b[:0], x=cr.x[:0],
                               n=cr.n[:0], gap=cr.gap[:0], sigma=cr.sigma[:0], angle=cr.angle[:0])
    prior = R.solve_errors(none, ref.origins, PRIOR, s.times, draws=400, seed=1)[2]["posterior"]
    assert np.allclose(prior.std(axis=(0, 1)) / PRIOR.sigmas(), 1.0, atol=0.1)


def _stripes_by_one_sort(fp, lab, q):
    """The stripes' order as one sort of the whole scan would give it (an independent
    reference): ids by np.unique, sums by bincount, then lexsort by stripe and position along."""
    ukey, sid, cnt = np.unique(fp.astype(np.int64) * 4 + lab, return_inverse=True,
                               return_counts=True)
    S = len(ukey)
    mean = np.stack([np.bincount(sid, q[:, i], S) for i in range(3)], 1) / cnt[:, None]
    d = [q[:, i] - mean[sid, i] for i in range(3)]
    C = np.empty((S, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            C[:, i, j] = C[:, j, i] = np.bincount(sid, d[i] * d[j], S)
    axis = np.linalg.eigh(C)[1][:, :, 2]
    along = d[0] * axis[sid, 0]
    for i in (1, 2):
        along += d[i] * axis[sid, i]
    order = np.lexsort((along, sid))
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    return order, sid[order], start, start + cnt


def test_stripes_in_runs_are_the_sorted_stripes(monkeypatch):
    """Points that come stripe after stripe are ordered by blocks of whole stripes: the same
    order, stripe ids and bounds, bit for bit, as the sort of the whole scan."""
    import crossline.scan.refine_crossings as rc

    rng = np.random.default_rng(5)
    frames = np.repeat(np.arange(300), rng.integers(20, 90, 300))
    laser = np.where(rng.uniform(size=len(frames)) < 0.5, 1, 2).astype(np.uint8)
    p = rng.normal(size=(len(frames), 3)) * [5.0, 0.3, 0.1] + frames[:, None] * 0.4
    subset = np.flatnonzero(rng.uniform(size=len(frames)) < 0.9)
    by_stripe = np.lexsort((laser, frames))
    # lasers mixed within each frame (as triangulate writes them), and stripe after stripe
    for fr, la in ((frames, laser), (frames[by_stripe], laser[by_stripe])):
        for sub in (None, subset):
            fp, lab = (fr, la) if sub is None else (fr[sub], la[sub])
            assert rc._runs(fp, lab) is not None
            fast = rc._stripes(fp, lab, p, sub)
            whole = _stripes_by_one_sort(fp, lab, p if sub is None else p[sub])
            with monkeypatch.context() as m:  # the fallback for frames out of order
                m.setattr(rc, "_runs", lambda *a, **k: None)
                for x, y in zip(rc._stripes(fp, lab, p, sub), whole, strict=True):
                    assert np.array_equal(np.asarray(x, np.int64), np.asarray(y, np.int64))
            for x, y in zip(fast, whole, strict=True):
                assert np.array_equal(np.asarray(x, np.int64), np.asarray(y, np.int64))
            # blocks much smaller than the scan: the same again
            small = rc._stripes_in_runs(rc._runs(fp, lab, block=700), p, sub, block=1000)
            for x, y in zip(small, whole, strict=True):
                assert np.array_equal(np.asarray(x, np.int64), np.asarray(y, np.int64))
    assert rc._runs(frames[::-1], laser) is None  # frames out of order: the whole sort


def test_refined_points_overwrite_only_what_is_handed_over(plate):
    from crossline.fuse import fuse_cloud

    e = np.random.default_rng(4).normal(size=(len(plate.T), 6)) * ([1e-5] * 3 + [4e-3] * 3)
    p, ref = plate.refine(e)
    q = p.copy()
    frames, views = camera_centres(plate.frame, plate.df[["x_cam", "y_cam", "z_cam"]].to_numpy(), q)
    again = R.refine_frames(plate.frame, plate.laser, q, views, PRIOR, frames=frames,
                            origins=reported(plate.df, plate.T, e)[1], times=plate.times,
                            overwrite_points=True)
    assert again.points is q and np.array_equal(q, ref.points)  # the same points, in place
    assert not np.array_equal(q, p)
    # the public fuse_cloud leaves its caller's arrays as they were
    before = p.copy()
    c = fuse_cloud(p, plate.laser, plate.frame, plate.df[["x_cam", "y_cam", "z_cam"]].to_numpy(),
                   neighbours=0, refine_prior=PRIOR)
    assert np.array_equal(p, before) and c.stats["refine"]["crossings"] > 0


def test_crossing_where_a_stripe_is_sparse(monkeypatch):
    """A stripe sampled densely elsewhere (a steep stripe's rows on the table) and sparsely at
    its crossing (on the ball): its laser's median spacing gives a window holding 7 points
    there, too few for the curve; the window is fitted again from the spacing about the seed.
    Without that (``MAX_GROWTH`` 1: no growth), no crossing is found."""
    import crossline.scan.refine_crossings as RC

    ax = np.arange(-5.0, 5.0001, 0.05)
    a = np.column_stack([ax, np.zeros_like(ax), np.zeros_like(ax)])
    by = np.r_[np.arange(-3.0, 3.0001, 0.2), np.arange(5.0, 40.0, 0.03)]
    b = np.column_stack([np.zeros_like(by), by, np.zeros_like(by)])
    p = np.vstack([a, b])
    frame = np.r_[np.zeros(len(a), np.int64), np.ones(len(b), np.int64)]
    laser = np.r_[np.ones(len(a), np.int8), np.full(len(b), 2, np.int8)]
    views = np.array([[0.0, 0.0, 100.0], [0.0, 0.0, 100.0]])
    cr = R.find_crossings(frame, laser, p, views)
    assert len(cr.gap) == 1
    assert np.linalg.norm(cr.x[0]) < 1e-9 and abs(cr.gap[0]) < 1e-12
    monkeypatch.setattr(RC, "MAX_GROWTH", 1.0)
    assert len(R.find_crossings(frame, laser, p, views).gap) == 0


def test_local_spacing_of_a_one_point_stripe_at_the_end_of_the_order():
    """A seed on a stripe of a single point, the last in stripe order, has no spacing (NaN)
    and does not read past the points (random rig 8's ball after the speckle fix: an
    IndexError in fuse); the other seeds' spacings are their stripes' own."""
    from crossline.scan.refine_crossings import _local_spacing, _Ordered

    # stripe 0: points 0..9, 0.1 mm apart; stripe 1: the single point 10
    p = np.c_[np.r_[np.arange(10) * 0.1, 5.0], np.zeros(11), np.zeros(11)]
    po = _Ordered(p, np.arange(11))
    out = _local_spacing(po, np.array([5, 10]), np.array([0, 10]), np.array([10, 11]))
    assert out[0] == pytest.approx(0.1) and np.isnan(out[1])


def test_noise_scale_counts_the_unknowns_the_fit_spends():
    """A few frames, few crossings a frame and a prior 10x looser than the arm: the fit spends
    most of the crossings on the poses, and the residuals left are smaller than the gaps' noise.
    The noise scale takes that out (the hat matrix's trace); taken from the residuals as they
    are it shrank, the data outweighed the prior and the refinement fitted noise as pose."""
    from crossline.robust import robust_sigma
    from crossline.scan.refine_solve import solve_errors

    s = Scan("sphere", noise=0.002, frames=24, rays=400)
    frames, views = camera_centres(s.frame, s.df[["x_cam", "y_cam", "z_cam"]].to_numpy(), s.p_true)
    cr = R.find_crossings(np.searchsorted(frames, s.frame), s.laser, s.p_true, views)
    loose = R.ArmPrior.from_precision(0.2)
    origins = (s.T @ invert_transform(X))[:, :3, 3]
    _, _, info = solve_errors(cr, origins, loose, s.times)
    # exact poses: the gaps are the stripes' noise alone, and the fit should say so
    s0 = np.maximum(cr.sigma, np.median(cr.sigma) * 0.5)
    noise = robust_sigma(cr.gap / s0)
    assert info["effective_parameters"] > 0.3 * info["used"]
    assert 0.75 < info["noise_scale"] / noise < 1.3

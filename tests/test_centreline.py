"""Centre-line traces: linking, end trimming and smoothing along the stripe."""

from __future__ import annotations

import numpy as np
import pytest

from crossline.scan.centreline import (
    blocked_ends,
    half_amplitude_columns,
    join_traces,
    link_traces,
    smooth_along,
    trace_position,
    trace_space,
)


def _stripe(frame, laser, u0, u1, v_of_u):
    u = np.arange(u0, u1, dtype=float)
    return np.full(u.size, frame), np.full(u.size, laser), u, v_of_u(u)


def _cat(*parts):
    return [np.concatenate(x) for x in zip(*parts, strict=True)]


def test_traces_split_at_gaps_jumps_frames_and_lasers() -> None:
    frame, laser, u, v = _cat(
        _stripe(0, "A", 100, 120, lambda u: 0.8 * u),        # trace 1
        _stripe(0, "A", 125, 140, lambda u: 0.8 * u),        # gap of 5 columns: trace 2
        _stripe(0, "A", 140, 150, lambda u: 0.8 * u + 30),   # a step of 30 px: trace 3
        _stripe(0, "A", 150, 170, lambda u: 0.8 * u + 34),   # a step of 4 px (a kink): trace 4
        _stripe(0, "B", 100, 120, lambda u: 500 - u),        # the other laser: trace 4
        _stripe(1, "A", 100, 120, lambda u: 0.8 * u),        # the next frame: trace 5
    )
    rng = np.random.default_rng(0)
    order = rng.permutation(len(u))  # input order must not matter
    frame, laser, u, v = frame[order], laser[order], u[order], v[order]
    prev = link_traces(frame, laser, u, v)
    trace, start, end = trace_position(prev, u)
    assert len(np.unique(trace)) == 6
    i = np.flatnonzero((frame == 0) & (laser == "A") & (u == 119))[0]
    assert start[i] == 19 and end[i] == 0
    _, start_px, _ = trace_position(prev, u, v)
    assert start_px[i] == pytest.approx(19 * np.hypot(1, 0.8))  # px along a 0.8-slope stripe
    i = np.flatnonzero((frame == 0) & (laser == "A") & (u == 140) & (v > 130))[0]
    assert start[i] == 0 and end[i] == 9
    # two centres of the same laser in one column (a step seen twice) stay in their traces
    assert np.all(prev[prev >= 0] != np.arange(len(u))[prev >= 0])


def test_smoothing_keeps_quadratics_and_reduces_noise() -> None:
    frame, laser, u, v = _stripe(3, "A", 0, 400, lambda u: 200 + 0.5 * u + 2e-4 * (u - 150) ** 2)
    steep = _stripe(4, "A", 0, 50, lambda u: 3.0 * u)  # 3 rows per column: still one trace
    assert (link_traces(*steep) >= 0).sum() == 49
    trace, _, _ = trace_position(link_traces(frame, laser, u, v), u)
    vs, full = smooth_along(trace, u, v, 9)
    # every centre is fitted, the ends with the part of the window that exists (one-sided)
    assert full.all()
    np.testing.assert_allclose(vs, v, atol=1e-9)  # a local quadratic is exact, ends included
    noisy = v + np.random.default_rng(1).normal(0, 0.1, v.size)
    vs, full = smooth_along(trace, u, noisy, 15)
    inner = np.zeros(v.size, bool)
    inner[7:-7] = True
    before = np.std(noisy[inner] - v[inner])
    after = np.std(vs[inner] - v[inner])
    assert after < 0.45 * before  # white noise: factor ~0.4 for a 15-column quadratic
    # at the very ends the one-sided fit is no noisier than the raw rows (factor ~0.94)
    ends = ~inner
    assert np.std(vs[ends] - v[ends]) < 1.2 * np.std(noisy[ends] - v[ends])
    vs, full = smooth_along(trace, u, noisy, 1)
    assert full.all() and np.array_equal(vs, noisy)
    with pytest.raises(ValueError, match="odd number of columns"):
        smooth_along(trace, u, noisy, 4)


def test_empty_input() -> None:
    e = np.empty(0)
    prev = link_traces(e.astype(int), e.astype(str), e, e)
    trace, a, b = trace_position(prev, e)
    assert trace.size == a.size == b.size == 0


def test_smoothing_across_a_trace_with_missing_columns_and_too_short_traces() -> None:
    _, _, u, v = _stripe(0, "A", 0, 60, lambda u: 100 + 0.3 * u + 1e-3 * u**2)
    keep = ~np.isin(u, [20, 21, 40])  # columns missing (the trace is one trace id here)
    u, v = u[keep], v[keep]
    trace = np.zeros(u.size, dtype=np.int64)
    vs, ok = smooth_along(trace, u, v, 7)
    assert ok.all()
    np.testing.assert_allclose(vs, v, atol=1e-9)  # windows with holes still fit the quadratic
    vs, ok = smooth_along(np.arange(2), np.array([5.0, 6.0]), np.array([1.0, 2.0]), 5)
    assert not ok.any() and np.array_equal(vs, [1.0, 2.0])  # two columns: nothing to fit


def test_ends_against_a_merged_crossing_are_not_stripe_ends() -> None:
    # stripe A stops at u = 50 where a merged blob (both stripes) sits in columns 50..55,
    # and resumes at u = 56; its outer ends (u = 0, u = 99) are real ends
    frame, laser, u, v = _stripe(0, "A", 0, 100, lambda u: 300 + 0.5 * u)
    gap = (u >= 50) & (u <= 55)
    frame, laser, u, v = frame[~gap], laser[~gap], u[~gap], v[~gap]
    trace, _, _ = trace_position(link_traces(frame, laser, u, v), u)
    assert len(np.unique(trace)) == 2
    bu = np.arange(50.0, 56.0)
    start_blocked, end_blocked = blocked_ends(trace, frame, u, v, np.zeros(6, int), bu, 300 + 0.5 * bu)
    left, right = u < 50, u > 55
    assert np.all(end_blocked[left]) and not np.any(start_blocked[left])
    assert np.all(start_blocked[right]) and not np.any(end_blocked[right])
    # a blob in another frame, or far from the trace's row, blocks nothing
    for f, dv in ((1, 0.0), (0, 40.0)):
        s, e = blocked_ends(trace, frame, u, v, np.full(6, f), bu, 300 + 0.5 * bu + dv)
        assert not s.any() and not e.any()


def test_a_trace_does_not_fork_where_two_stripes_meet() -> None:
    """Two stripes leave one centre (an X seen by one laser's position alone): each centre is
    continued by the nearest centre of the next column only, the other starts a trace."""
    u = np.array([10.0, 11.0, 11.0, 12.0, 12.0])
    v = np.array([100.0, 100.5, 104.0, 101.0, 108.0])
    prev = link_traces(np.zeros(5, int), np.full(5, "A"), u, v)
    assert prev.tolist() == [-1, 0, -1, 1, 2]


@pytest.mark.parametrize("window", [5, 7, 9, 15])
def test_half_amplitude_period_is_what_the_smoothing_passes_at_half(window) -> None:
    """A ripple of the stated period comes out of smooth_along at half its amplitude."""
    period = half_amplitude_columns(window)
    u = np.arange(4000, dtype=np.float64)
    v = 100.0 + np.sin(2 * np.pi * u / period)
    vs, _ = smooth_along(np.zeros(u.size, np.int64), u, v, window)
    mid = slice(window, -window)  # away from the trace's ends
    gain = np.sqrt(2 * np.mean((vs[mid] - 100.0) ** 2))
    assert gain == pytest.approx(0.5, abs=2e-3)
    # and scipy's Savitzky-Golay filter (same local quadratic) agrees
    from scipy.signal import savgol_filter

    ref = savgol_filter(v, window, 2)
    np.testing.assert_allclose(vs[mid], ref[mid], atol=1e-9)


def test_half_amplitude_period_without_smoothing_is_infinite() -> None:
    assert half_amplitude_columns(1) == np.inf and half_amplitude_columns(3) == np.inf


def _profiled(u_img, v_img):
    """A curve's points sampled as the extractor profiles it: per integer column where it runs
    shallower than 45 deg, per integer row where steeper; returns u, v, axis."""
    du, dv = np.gradient(u_img), np.gradient(v_img)
    steep = np.abs(dv) > np.abs(du)
    us, vs, axs = [], [], []
    for seg in np.split(np.arange(u_img.size), np.flatnonzero(np.diff(steep.astype(int))) + 1):
        ax = int(steep[seg[0]])
        s = np.stack([u_img[seg], v_img[seg]], axis=1)
        o = np.argsort(s[:, ax])
        grid = np.arange(np.ceil(s[:, ax].min()), np.floor(s[:, ax].max()) + 1)
        other = np.interp(grid, s[o, ax], s[o, 1 - ax])
        us.append(grid if ax == 0 else other)
        vs.append(other if ax == 0 else grid)
        axs.append(np.full(grid.size, ax))
    return np.concatenate(us), np.concatenate(vs), np.concatenate(axs)


def test_a_curve_through_the_row_switch_is_joined_into_one_trace() -> None:
    t = np.linspace(np.radians(200), np.radians(340), 20001)  # an arc: steep, shallow, steep
    u, v, axis = _profiled(500 + 150 * np.cos(t), 500 + 150 * np.sin(t))
    tu, tv = trace_space(u, v, axis)
    trace, _, _ = trace_position(link_traces(np.zeros(u.size), np.zeros(u.size), tu, tv), tu)
    assert len(np.unique(trace)) >= 3  # split where the profiles change direction
    joined = join_traces(trace, tu, u, v)
    long_ = np.isin(trace, [k for k in np.unique(trace) if (trace == k).sum() >= 5])
    assert len(np.unique(joined[long_])) == 1
    rng = np.random.default_rng(1)
    order = rng.permutation(u.size)  # input order must not matter
    assert np.array_equal(join_traces(trace[order], tu[order], u[order], v[order]), joined[order])


@pytest.mark.parametrize("angle_deg", [8.0, 25.0, 60.0])
def test_two_stripes_meeting_at_a_crossing_are_not_joined(angle_deg) -> None:
    """Two lines crossing at ``angle_deg``, the merged run at the crossing left out: their ends
    there lie side by side (same side) or face each other across the gap (opposite sides),
    and no trace of one is joined to a trace of the other."""
    x = np.arange(300.0, 701.0)
    ya = 400 + 0.1 * (x - 500)
    yb = 400 + np.tan(np.arctan(0.1) + np.radians(angle_deg)) * (x - 500)
    u, v, lab = np.r_[x, x], np.r_[ya, yb], np.r_[np.zeros(x.size), np.ones(x.size)]
    keep = np.abs(np.r_[ya - yb, yb - ya]) >= 5.0  # where the two runs overlap: one merged run
    keep &= (v >= 0) & (v < 800)
    u, v, lab = u[keep], v[keep], lab[keep]
    axis = np.zeros(u.size, int)
    tu, tv = trace_space(u, v, axis)
    trace, _, _ = trace_position(link_traces(np.zeros(u.size), np.zeros(u.size), tu, tv), tu)
    joined = join_traces(trace, tu, u, v)
    for g in np.unique(joined):
        assert np.unique(lab[joined == g]).size == 1

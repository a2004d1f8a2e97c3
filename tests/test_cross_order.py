"""The order of the cross labels AB frames without single-laser frames: against the true lasers.

Stripes are the exact images of the laser planes on planar surfaces (no rendering): the
geometry alone is under test. The cameras, planes and surfaces are drawn at random.
"""

from __future__ import annotations

import numpy as np
import pytest

from crossline.camera import Camera
from crossline.geometry import plane_line_intersection
from crossline.laser import LaserPlane, LaserPlanes
from crossline.scan.cross_order import CrossOrder
from crossline.scan.labels import Disambiguator

W, H, F = 900, 700, 1200.0


def _rig(rng: np.random.Generator, theta: float | None = None) -> tuple[Camera, LaserPlanes, np.ndarray]:
    """A camera and two laser planes through a point at about 200 mm, crossing in the image
    (laser A's stripe at ``theta`` rad to the image's u axis, if given)."""
    cam = Camera(np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]]), np.zeros(5), (W, H))
    X = np.array([rng.uniform(-10, 10), rng.uniform(-10, 10), 200.0])
    planes = []
    theta = rng.uniform(0, np.pi) if theta is None else theta
    for k, turn in enumerate((0.0, np.radians(rng.uniform(50, 130)))):
        t = np.array([np.cos(theta + turn), np.sin(theta + turn), 0.0])  # stripe direction, fronto
        emitter = np.array([0.0, 0.0, 0.0]) + rng.uniform(60, 120) * np.cross(t, [0, 0, 1]) * (-1) ** k
        n = np.cross(t, X - emitter)
        n /= np.linalg.norm(n)
        planes.append(LaserPlane(n, -float(n @ X)))
    return cam, LaserPlanes(*planes), X


def _stripes(cam: Camera, planes: LaserPlanes, n_s: np.ndarray, p_s: np.ndarray):
    """Per-column image rows of each laser's line on the plane through ``p_s`` with normal ``n_s``."""
    u_all, v_all, lab = [], [], []
    d_s = -float(n_s @ p_s)
    for code, k in ((1, "A"), (2, "B")):
        p, d = plane_line_intersection(planes[k].normal, planes[k].d, n_s, d_s)
        pts = p + np.linspace(-400, 400, 20001)[:, None] * d
        pts = pts[pts[:, 2] > 10]
        uv = cam.project(pts)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        uv = uv[inside]
        if len(uv) < 2:
            continue
        order = np.argsort(uv[:, 0])
        cols = np.arange(np.ceil(uv[:, 0].min()), np.floor(uv[:, 0].max()) + 1)
        v = np.interp(cols, uv[order, 0], uv[order, 1])
        u_all.append(cols)
        v_all.append(v)
        lab.append(np.full(cols.size, code))
    if not u_all:
        return np.empty(0), np.empty(0), np.empty(0, int)
    u, v, lab = np.concatenate(u_all), np.concatenate(v_all), np.concatenate(lab)
    # where the stripes come within 6 px in a column the extractor finds one merged run
    o = np.lexsort((v, u))
    u, v, lab = u[o], v[o], lab[o]
    close = np.zeros(u.size, bool)
    pair = (u[1:] == u[:-1]) & (np.abs(v[1:] - v[:-1]) < 6.0)
    close[1:] |= pair
    close[:-1] |= pair
    return u[~close], v[~close], lab[~close]


def _tilted(rng: np.random.Generator, X: np.ndarray, max_deg: float) -> np.ndarray:
    """A surface normal turned up to ``max_deg`` from facing the camera at X."""
    face = -X / np.linalg.norm(X)
    axis = np.cross(face, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    a = np.radians(rng.uniform(0, max_deg))
    return face * np.cos(a) + np.cross(axis, face) * np.sin(a)


@pytest.mark.parametrize("seed", range(12))
def test_order_labels_planar_surfaces_right(seed):
    rng = np.random.default_rng(seed)
    cam, planes, X = _rig(rng)
    co = CrossOrder.from_calibration(cam, planes)
    right = wrong = total = 0
    for _ in range(10):
        n_s = _tilted(rng, X, 25.0)
        p_s = X + rng.uniform(-20, 20) * n_s  # the surface nearer or farther along its normal
        u, v, truth = _stripes(cam, planes, n_s, p_s)
        keep = np.ones(u.size, bool)
        lab, _ = co.labels(u, v, keep)
        total += u.size
        right += int((lab == truth).sum())
        wrong += int(((lab > 0) & (lab != truth)).sum())
    assert wrong == 0
    assert right >= 0.9 * total


def test_order_fails_loudly_where_it_cannot_tell():
    """Parallel planes (no crossing line), and a crossing line across the viewing ray: on a
    surface facing the camera both stripes then run along its image."""
    cam = Camera(np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]]), np.zeros(5), (W, H))
    n = np.array([0.0, 0.6, -0.8])
    with pytest.raises(ValueError, match="parallel"):
        CrossOrder.from_calibration(cam, LaserPlanes(LaserPlane(n, 100.0), LaserPlane(n, 120.0)))
    X = np.array([0.0, 0.0, 200.0])
    planes = []
    for a in (np.radians(20.0), np.radians(-35.0)):  # both planes hold the line X + t (1, 0, 0)
        m = np.array([0.0, np.cos(a), np.sin(a)])
        planes.append(LaserPlane(m, -float(m @ X)))
    with pytest.raises(ValueError, match="the same way"):
        CrossOrder.from_calibration(cam, LaserPlanes(*planes))


def test_all_ab_scan_is_labelled_and_followed():
    """Every frame AB: the first is labelled by the order, the next follow it as the surface turns."""
    rng = np.random.default_rng(3)
    cam, planes, X = _rig(rng)
    dis = Disambiguator(order=CrossOrder.from_calibration(cam, planes), max_frame_gap=2)
    face = -X / np.linalg.norm(X)
    axis = np.cross(face, [1.0, 0.0, 0.0])
    axis /= np.linalg.norm(axis)
    right = wrong = total = 0
    for f in range(20):
        a = np.radians(2.0 * f)  # the surface turns 2 deg per frame, up to 38 deg
        n_s = face * np.cos(a) + np.cross(axis, face) * np.sin(a)
        u, v, truth = _stripes(cam, planes, n_s, X + 0.5 * f * face)
        label, _ = dis.process(f, "AB", u, v, np.zeros(u.size, np.uint8))
        code = np.where(label == "A", 1, np.where(label == "B", 2, 0))
        right += int((code == truth).sum())
        wrong += int(((code > 0) & (code != truth)).sum())
        total += u.size
    c = dis.counts
    assert wrong == 0
    assert right >= 0.9 * total
    assert c["labelled_by_order"]["frames"] == 20
    assert c["labelled_by_order"]["by_previous_frames"] > c["labelled_by_order"]["by_order"]
    dropped = sum(c["dropped"].values())
    assert c["labelled"]["A"] + c["labelled"]["B"] + dropped == c["centres_in"]


def test_crossing_out_of_the_window_is_labelled():
    """No crossing in view: the stripes extended to l meet there, or each goes by its direction."""
    hits = alone = 0
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        cam, planes, X = _rig(rng)
        co = CrossOrder.from_calibration(cam, planes)
        p, d = planes.intersection_line()
        face = -X / np.linalg.norm(X)
        for shift in np.linspace(-150.0, 150.0, 31):  # the surface nearer or farther
            P = p + ((X + shift * face - p) @ face) / (d @ face) * d  # L meets the surface here
            x = cam.project(P[None])[0]
            if (0 <= x[0] < W and 0 <= x[1] < H) or P[2] <= 20:
                continue
            u, v, truth = _stripes(cam, planes, face, X + shift * face)
            if min((truth == 1).sum(), (truth == 2).sum()) < 50:
                continue
            lab, _ = co.labels(u, v, np.ones(u.size, bool))
            assert not np.any((lab > 0) & (lab != truth)), (seed, shift)
            hits += int((lab == truth).mean() > 0.9)
            # one stripe alone (the other off the part): nothing meets it, its direction decides
            for k in (1, 2):
                one = truth == k
                lab, _ = co.labels(u[one], v[one], np.ones(int(one.sum()), bool))
                assert not np.any((lab > 0) & (lab != k)), (seed, shift, k)
                alone += int((lab == k).mean() > 0.9)
            break
    assert hits >= 6 and alone >= 12


def test_one_stripe_followed_before_the_other_is_seen():
    """The first frames see stripe A only (B off the part): A is followed from the first frame
    on, not told from its direction anew in each frame; B joins when it comes into view."""
    rng = np.random.default_rng(5)
    cam, planes, X = _rig(rng)
    dis = Disambiguator(order=CrossOrder.from_calibration(cam, planes), max_frame_gap=2)
    face = -X / np.linalg.norm(X)
    wrong = 0
    for f in range(12):
        u, v, truth = _stripes(cam, planes, face, X + 0.5 * f * face)
        if f < 6:
            u, v, truth = u[truth == 1], v[truth == 1], truth[truth == 1]
        label, _ = dis.process(f, "AB", u, v, np.zeros(u.size, np.uint8))
        code = np.where(label == "A", 1, np.where(label == "B", 2, 0))
        wrong += int(((code > 0) & (code != truth)).sum())
    c = dis.counts["labelled_by_order"]
    assert wrong == 0
    assert c["by_previous_frames"] > 3 * c["by_order"], c


def _stripes_by_axis(cam: Camera, planes: LaserPlanes, n_s: np.ndarray, p_s: np.ndarray):
    """Like :func:`_stripes`, but a stripe steeper than 45 deg is sampled per image row, as the
    extractor profiles it (axis 1); returns u, v, axis, truth."""
    out = []
    d_s = -float(n_s @ p_s)
    for code, k in ((1, "A"), (2, "B")):
        p, d = plane_line_intersection(planes[k].normal, planes[k].d, n_s, d_s)
        pts = p + np.linspace(-400, 400, 20001)[:, None] * d
        uv = cam.project(pts[pts[:, 2] > 10])
        uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)]
        if len(uv) < 2:
            continue
        ax = int(np.ptp(uv[:, 1]) > np.ptp(uv[:, 0]))  # steep: along the rows
        out.append((*_sampled(uv, ax), ax, code))
    return _without_crossing(out)


def _sampled(q: np.ndarray, ax: int) -> tuple[np.ndarray, np.ndarray]:
    """A curve's points (N, 2) at the integer image columns (``ax`` 0) or rows (1) it spans: u, v."""
    o = np.argsort(q[:, ax])
    grid = np.arange(np.ceil(q[:, ax].min()), np.floor(q[:, ax].max()) + 1)
    other = np.interp(grid, q[o, ax], q[o, 1 - ax])
    return (grid, other) if ax == 0 else (other, grid)


def _without_crossing(pieces: list) -> tuple[np.ndarray, ...]:
    """u, v, axis, truth of sampled pieces ``(u, v, axis, code)``, less the crossing, where the
    extractor finds one merged run (within 6 px of the other laser's stripe)."""
    u = np.concatenate([p[0] for p in pieces])
    v = np.concatenate([p[1] for p in pieces])
    axis = np.concatenate([np.full(p[0].size, p[2], np.uint8) for p in pieces])
    lab = np.concatenate([np.full(p[0].size, p[3]) for p in pieces])
    near = np.zeros(u.size, bool)
    a, b = lab == 1, lab == 2
    if a.any() and b.any():
        dist = np.hypot(u[a, None] - u[None, b], v[a, None] - v[None, b])
        near[np.flatnonzero(a)] = dist.min(1) < 6.0
        near[np.flatnonzero(b)] = dist.min(0) < 6.0
    return u[~near], v[~near], axis[~near], lab[~near]


@pytest.mark.parametrize("seed", range(4))
def test_near_vertical_stripe_labelled_by_the_order(seed):
    """Every frame AB, laser A's stripe within 4 deg of the image's columns: its centres are
    profiled along the rows; followed down the rows (trace space), its pieces are lines and
    the cross's order labels them. Linked by image column instead, a near-vertical stripe
    falls apart into pieces of a column or two, which no line fits."""
    from crossline.scan.centreline import trace_space

    rng = np.random.default_rng(200 + seed)
    cam, planes, X = _rig(rng, theta=np.radians(90.0 + rng.uniform(-4, 4)))
    co = CrossOrder.from_calibration(cam, planes)
    n_s = _tilted(rng, X, 15.0)
    u, v, axis, truth = _stripes_by_axis(cam, planes, n_s, X)
    assert (axis[truth == 1] == 1).all() and (truth == 1).sum() > 300
    keep = np.ones(u.size, bool)
    lab, _ = co.labels(u, v, keep, link=trace_space(u, v, axis))
    assert not np.any((lab > 0) & (lab != truth))
    assert (lab == truth)[truth == 1].mean() > 0.9 and (lab == truth)[truth == 2].mean() > 0.9
    old, _ = co.labels(u, v, keep)  # linked by image column
    assert (old == truth)[truth == 1].mean() < 0.5
    dis = Disambiguator(order=co, max_frame_gap=2)
    tu, tv = trace_space(u, v, axis)
    label, _ = dis.process(0, "AB", tu, tv, np.zeros(u.size, np.uint8), image=(u, v))
    code = np.where(label == "A", 1, np.where(label == "B", 2, 0))
    assert not np.any((code > 0) & (code != truth)) and (code == truth).mean() > 0.9


def _on_ball(cam: Camera, planes: LaserPlanes, centre: np.ndarray, radius: float):
    """Each laser's stripe on a ball (the side facing the camera), sampled as the extractor
    profiles it: per image column where the curve runs shallower than 45 deg, per image row
    where steeper (axis 1), switching along the curve; returns u, v, axis, truth."""
    out = []
    for code, k in ((1, "A"), (2, "B")):
        n, d = planes[k].normal, planes[k].d
        dist = float(n @ centre + d)
        if abs(dist) >= radius:
            continue
        e1 = np.cross(n, [0.0, 0.0, 1.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        t = np.linspace(0, 2 * np.pi, 200001)[:, None]
        P = centre - dist * n + np.sqrt(radius**2 - dist**2) * (np.cos(t) * e1 + np.sin(t) * e2)
        uv = cam.project(P)
        seen = (np.einsum("ij,ij->i", P - centre, P) < 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) \
            & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        idx = np.flatnonzero(seen)
        for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            q = uv[run]
            dq = np.gradient(q, axis=0)
            steep = np.abs(dq[:, 1]) > np.abs(dq[:, 0])
            for seg in np.split(np.arange(run.size), np.flatnonzero(np.diff(steep.astype(int))) + 1):
                ax = int(steep[seg[0]])
                out.append((*_sampled(q[seg], ax), ax, code))
    return _without_crossing(out)


@pytest.mark.parametrize("seed", [32, 33, 36, 37])
def test_a_stripe_turning_past_the_row_switch_on_a_ball_keeps_one_label(seed):
    """Every frame AB, a small ball at the cross: a stripe that turns from shallow to steep is
    profiled along the columns, then along the rows, and is two traces end to end. Labelled
    apart, the piece far from the crossing line took the other laser (its line drawn a long
    way to l, or its direction turned towards the other stripe's): 13-66 wrong labels on these
    balls (random rig 14's ball: 10 % of its AB centres). Joined, it takes the label of its
    piece nearest l."""
    from crossline.scan.centreline import trace_space

    rng = np.random.default_rng(300 + seed)
    cam, planes, X = _rig(rng)
    co = CrossOrder.from_calibration(cam, planes)
    radius = rng.uniform(8, 15)
    centre = X + 0.7 * radius * X / np.linalg.norm(X) + rng.uniform(-4, 4, 3) * [1, 1, 0]
    u, v, axis, truth = _on_ball(cam, planes, centre, radius)
    lab, piece = co.labels(u, v, np.ones(u.size, bool), link=trace_space(u, v, axis))
    # the case: a labelled piece holds centres of both profile directions
    both = [p for p in np.unique(piece[lab > 0]) if np.ptp(axis[piece == p]) == 1]
    assert both
    assert not np.any((lab > 0) & (lab != truth))
    assert (lab == truth).mean() > 0.7

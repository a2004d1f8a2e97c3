"""Which laser made each stripe of an AB frame without single-laser frames: the order of the cross.

The paper tells the two stripes of an AB frame apart by the A and B frames before it. A
scanner that lights both lasers in every frame (pattern ``AB`` only), or a scan whose A or
B frames are missing, has no such frames. Geometry then decides, from the calibration alone.

The two laser planes meet in a line ``L``; its image ``l`` (a straight line in undistorted
coordinates) passes through the crossing of the two stripes on any surface. On each side of
``l`` there is one branch of each stripe, and the two branches leave the crossing in an
order around it that does not depend on the surface, as long as the surface's tangent plane
does not pass through ``L`` (where the two stripes would lie on one another): the pencil of
planes through ``L`` meets the tangent plane in the pencil of lines through the crossing,
and a projective map of pencils keeps their cyclic order. On a plane facing the camera the
order is computed once from the calibration: the stripe at the smaller angle from ``l`` is A
where ``sigma`` > 0, B where it is < 0.

Per AB frame, the centres are linked into traces and each trace split by the side of ``l``
it lies on; a piece long and straight enough over the part nearest ``l`` is a line there.
Two pieces whose lines meet ``l`` at one point are branches of one crossing, seen or out of
the window; at clearly different angles they are the two lasers, in the order ``sigma``
gives. Across ``l`` a stripe runs on through the crossing, bent where the surface is curved,
so two pieces on opposite sides count as two lasers only if their angle is more than half
the angle between the stripes on a surface facing the camera. Where no two pieces meet in a
frame (the crossing hidden), each piece takes the laser whose stripe on such a surface runs
nearer its direction, if clearly nearer.

The order flips for a surface turned so far that its tangent plane passes through ``L``
(both stripes then lie along ``l``): the true surface is then the less plausible reading of
the image. A surface turned towards ``L`` gets there first, after a turn from facing the
camera of 90 deg less the angle between ``L`` and the viewing ray. So a piece's votes must
agree, and :class:`~crossline.scan.labels.Disambiguator` follows the stripes from frame to
frame once they are told apart: a piece the frames before label keeps that label.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crossline.camera import Camera
from crossline.laser import LaserPlanes
from crossline.scan.centreline import join_traces, link_traces, trace_position

__all__ = ["CrossOrder"]

MIN_ANGLE_DEG = 5.0  # the stripes' image directions on a surface facing the camera must differ


def _angle_from_l(t: np.ndarray, x: np.ndarray, along: np.ndarray, across: np.ndarray) -> float:
    """Angle in [0, pi) from ``l`` to the image of 3-D direction ``t`` at point ``x``."""
    d = t[:2] - x[:2] / x[2] * t[2]
    return float(np.arctan2(across @ d, along @ d) % np.pi)


def _circ(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Angle between two image directions (angles modulo pi), in [0, pi / 2]."""
    d = np.abs(np.asarray(a) - np.asarray(b)) % np.pi
    return np.minimum(d, np.pi - d)


@dataclass(frozen=True)
class CrossOrder:
    """The image of the planes' crossing line and the order of the stripes about it."""

    cam: Camera
    origin: np.ndarray  # a point of l, undistorted normalised coordinates
    along: np.ndarray  # unit direction of l
    across: np.ndarray  # unit normal of l (h > 0 on its side)
    sigma: float  # +1: stripe A at the smaller angle from l on a surface facing the camera, -1: B
    angles: tuple[float, float]  # image angle of stripes A and B from l on that surface, rad

    @classmethod
    def from_calibration(cls, cam: Camera, planes: LaserPlanes) -> CrossOrder:
        """The order for a camera and two laser planes; ValueError if the planes give no crossing."""
        p, d = planes.intersection_line()
        if abs(d[2]) > 1e-9:  # two points of L in front of the camera: at depths 1 and 1 + d_z mm
            d = d if d[2] > 0 else -d
            p = p + (1.0 - p[2]) / d[2] * d
        if p[2] <= 0:
            raise ValueError("the lasers' crossing line is not in front of the camera")
        q0, q1 = p, p + d
        a, b = q0[:2] / q0[2], q1[:2] / q1[2]
        if np.linalg.norm(b - a) < 1e-12:
            raise ValueError("the lasers' crossing line passes through the camera: its image is a point")
        along = (b - a) / np.linalg.norm(b - a)
        across = np.array([-along[1], along[0]])
        # the image point of l nearest the principal point, where a scanner's cross is meant to
        # be seen, and the point X of L on its ray (the two lines meet: both lie in L's plane
        # through the camera centre)
        foot = a - (a @ along) * along
        ray = np.array([foot[0], foot[1], 1.0])
        (lam, _), *_ = np.linalg.lstsq(np.stack([ray, -d], axis=1), p, rcond=None)
        X = lam * ray
        if X[2] <= 0:
            raise ValueError("the lasers' crossing line is seen only behind the camera")
        n_face = -X / np.linalg.norm(X)  # a surface facing the camera at X
        angles = tuple(_angle_from_l(np.cross(planes[k].normal, n_face), X, along, across)
                       for k in ("A", "B"))
        if _circ(*angles) < np.radians(MIN_ANGLE_DEG):
            raise ValueError("the two stripes run the same way in the image: no order to tell them apart")
        # the angle from l falls as its cotangent rises: A first along l where it is smaller
        sigma = 1.0 if angles[0] < angles[1] else -1.0
        return cls(cam, foot, along, across, sigma, angles)

    def coordinates(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position along ``l`` and signed distance from it, in pixels (focal length units)."""
        q = self.cam.undistort(np.stack([u, v], axis=1)) - self.origin
        f = float(self.cam.K[0, 0])
        return f * (q @ self.along), f * (q @ self.across)

    def labels(
        self,
        u: np.ndarray,
        v: np.ndarray,
        usable: np.ndarray,
        *,
        near_px: float = 3.0,
        fit_px: float = 60.0,
        min_points: int = 10,
        elongation: float = 4.0,
        meet_px: float = 4.0,
        meet_frac: float = 0.05,
        same_deg: float = 8.0,
        agreement: float = 0.8,
        direction_margin: float = 0.25,
        link: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Label the ``usable`` centres of one AB frame: 1 = A, 2 = B, 0 = not decided; and pieces.

        Also returns each centre's stripe piece (-1: not usable, or within ``near_px`` of ``l``).

        Centres are linked into traces and each trace split by the side of ``l`` into
        pieces; a piece of ``min_points`` centres or more, ``elongation`` times longer than
        wide over its ``fit_px`` nearest ``l``, is a line there: its angle to ``l`` and the
        point where it meets ``l``. Two pieces that meet ``l`` at one point (within ``meet_px`` plus
        ``meet_frac`` of the longer extrapolation) are branches of one crossing: at angles
        ``same_deg`` or more apart they are the two lasers, in the order ``sigma`` gives, and
        each gets a vote; a piece whose votes agree to ``agreement`` or more takes that label.
        Across ``l`` a stripe runs on through the crossing, bent on a curved surface: two
        pieces there are two lasers only if their angle is over half that between the stripes
        on a surface facing the camera. In a frame where no two pieces meet (the crossing
        hidden, or out of the window), a piece takes the laser whose stripe on such a surface
        runs nearer its direction, if nearer by ``direction_margin`` of the angle between the
        two or more; where some pieces meet, the others stay undecided (a short piece on a ball
        can run either way). Traces that continue one another in the image (a stripe turning
        past the switch between column and row profiles, :func:`~crossline.scan.centreline.join_traces`)
        are one piece on each side of ``l``, labelled as their part nearest ``l``; the pieces
        returned are these. Centres within ``near_px`` of ``l`` stay undecided. ``link``: the
        coordinates the centres are linked into traces by, where not ``(u, v)`` (the trace
        space of :func:`crossline.scan.centreline.trace_space`, which follows a steep stripe
        down the rows).
        """
        out = np.zeros(u.size, np.int8)
        piece_of = np.full(u.size, -1, np.int64)
        idx = np.flatnonzero(usable)
        if idx.size < min_points:
            return out, piece_of
        uu, vv = u[idx], v[idx]
        s, h = self.coordinates(uu, vv)
        lu, lv = (uu, vv) if link is None else (link[0][idx], link[1][idx])
        prev = link_traces(np.zeros(idx.size, np.int64), np.zeros(idx.size, "<U1"), lu, lv)
        trace, _, _ = trace_position(prev, lu)
        _, piece = np.unique(2 * trace.astype(np.int64) + (h > 0), return_inverse=True)
        piece = piece.reshape(-1)
        n_pieces = int(piece.max()) + 1
        side = np.zeros(n_pieces, bool)
        side[piece] = h > 0
        # each piece's line over its part nearest l
        h_min = np.full(n_pieces, np.inf)
        np.minimum.at(h_min, piece, np.abs(h))
        near_end = np.abs(h) <= h_min[piece] + fit_px
        pc, sn, hn = piece[near_end], s[near_end], h[near_end]
        n = np.bincount(pc, minlength=n_pieces).astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            ms = np.bincount(pc, sn, n_pieces) / n
            mh = np.bincount(pc, hn, n_pieces) / n
            ds, dh = sn - ms[pc], hn - mh[pc]
            css = np.bincount(pc, ds * ds, n_pieces) / n
            chh = np.bincount(pc, dh * dh, n_pieces) / n
            csh = np.bincount(pc, ds * dh, n_pieces) / n
        angle = 0.5 * np.arctan2(2.0 * csh, css - chh) % np.pi
        spread = np.sqrt(np.maximum((css - chh) ** 2 + 4.0 * csh**2, 0.0))
        major, minor = 0.5 * (css + chh + spread), 0.5 * (css + chh - spread)
        line = (n >= min_points) & (major > elongation**2 * np.maximum(minor, 1e-12))
        crosses_l = np.abs(np.sin(angle)) > np.sin(np.radians(5.0))  # not running along l
        with np.errstate(invalid="ignore", divide="ignore"):
            s0 = ms - mh * np.cos(angle) / np.sin(angle)  # where the piece's line meets l
        reach = np.abs(mh) / np.maximum(np.abs(np.sin(angle)), 1e-9)  # extrapolated length
        ok = np.flatnonzero(line & crosses_l & np.isfinite(s0))
        votes = np.zeros((n_pieces, 2))
        if ok.size >= 2:
            i, j = np.triu_indices(ok.size, 1)
            p, q = ok[i], ok[j]
            meet = np.abs(s0[p] - s0[q]) <= meet_px + meet_frac * np.maximum(reach[p], reach[q])
            # two branches on one side of l are two lasers; across l, a stripe goes on through
            # the crossing, bent where the surface is curved: two lasers there only if nearer
            # the angle between the lasers' stripes than one
            same_side = side[p] == side[q]
            apart = _circ(angle[p], angle[q]) >= np.where(same_side, np.radians(same_deg),
                                                          0.5 * _circ(*self.angles))
            pair = meet & apart
            p, q = p[pair], q[pair]
            # the smaller angle from l is A where sigma > 0
            p_is_a = (angle[p] < angle[q]) == (self.sigma > 0)
            np.add.at(votes, (p, np.where(p_is_a, 0, 1)), 1.0)
            np.add.at(votes, (q, np.where(p_is_a, 1, 0)), 1.0)
        total = votes.sum(axis=1)
        code = np.where((total > 0) & (votes[:, 0] >= agreement * total), 1,
                        np.where((total > 0) & (votes[:, 1] >= agreement * total), 2, 0))
        # no two pieces meet (the crossing hidden or out of view): each piece's direction, if
        # clearly nearer one laser's than the other's on a surface facing the camera
        to_a, to_b = _circ(angle, self.angles[0]), _circ(angle, self.angles[1])
        margin = direction_margin * _circ(*self.angles)
        by_dir = np.where(to_b - to_a >= margin, 1, np.where(to_a - to_b >= margin, 2, 0))
        if not (total > 0).any():  # no crossing seen in this frame: the directions alone
            code = np.where(line, by_dir, code)
        # a stripe turning past the switch between column and row profiles (a curve on a
        # ball) is several traces end to end: they are one laser, the one its piece nearest l
        # was given (the order holds at the crossing; a piece far from it is told by a line
        # drawn a long way to l, or by a direction the curve has turned from)
        group = join_traces(trace, lu, uu, vv)
        _, gpiece = np.unique(2 * group.astype(np.int64) + (h > 0), return_inverse=True)
        gpiece = gpiece.reshape(-1)
        group_of = np.zeros(n_pieces, np.int64)
        group_of[piece] = gpiece
        decided = np.flatnonzero(code > 0)
        nearest = decided[np.lexsort((h_min[decided], group_of[decided]))]
        first = np.ones(nearest.size, bool)  # each group's piece nearest l, of those decided
        first[1:] = group_of[nearest][1:] != group_of[nearest][:-1]
        group_code = np.zeros(int(gpiece.max()) + 1, code.dtype)
        group_code[group_of[nearest[first]]] = code[nearest[first]]
        code, piece = group_code, gpiece
        off_l = np.abs(h) > near_px
        out[idx[off_l]] = code[piece[off_l]]
        piece_of[idx[off_l]] = piece[off_l]
        return out, piece_of

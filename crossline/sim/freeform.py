"""The freeform part: a leaning superellipsoid of degree 4 cut by the table, with an optional dent.

``FreeformPart`` (the earbud-case-like part: rays by a monotone Newton iteration on its convex
gauge function, ``_gauge_root``), ``Dent`` (a Gaussian defect pressed into its surface).
Split from ``crossline.sim.scene`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crossline.sim.primitive import Curve, Primitive
from crossline.sim.vec3 import INF, _basis, mat3, norm3, rowdot, take_rows

__all__ = ["Dent", "FreeformPart"]


# ----------------------------------------------------------------------------- freeform


def _gauge_root(X0: np.ndarray, D: np.ndarray, s_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First s in [0, s_max] with ||X0 + s D||_4 = 1, from points X0 outside; and misses.

    Along the line, ``||X0 + s D||_4^4`` is a quartic in s; Newton's method on its fourth root
    (the 4-norm, convex in s) from outside is monotone and never passes the first root.
    A ray misses when the norm stops decreasing before reaching 1. Converged to a step of
    1e-15 (relative), i.e. ~1e-14 mm.
    """
    n = len(X0)
    out = np.zeros(n)
    missed = np.zeros(n, bool)
    ai = np.arange(n)
    X02, D2 = X0 * X0, D * D
    c4 = D2[:, 0] ** 2 + D2[:, 1] ** 2 + D2[:, 2] ** 2
    c3 = 4.0 * rowdot(X0, D * D2)
    c2 = 6.0 * rowdot(X02, D2)
    c1 = 4.0 * rowdot(X0 * X02, D)
    c0 = X02[:, 0] ** 2 + X02[:, 1] ** 2 + X02[:, 2] ** 2
    sa = np.zeros(n)
    ha = np.broadcast_to(s_max, (n,)).copy()
    for _ in range(100):
        if ai.size == 0:
            break
        P4 = (((c4 * sa + c3) * sa + c2) * sa + c1) * sa + c0
        dP = ((4.0 * c4 * sa + 3.0 * c3) * sa + 2.0 * c2) * sa + c1
        q = np.sqrt(np.sqrt(np.maximum(P4, 0.0)))
        gp = dP / (4.0 * q * q * q)
        miss = (gp >= 0) | (sa > ha)
        step = np.where(miss, 0.0, (1.0 - q) / np.where(miss, -1.0, gp))
        sa = sa + step
        done = miss | (np.abs(step) <= 1e-15 * (1.0 + np.abs(sa)))
        if done.any():
            out[ai[done]] = sa[done]
            missed[ai[miss]] = True
            k = ~done
            ai, sa, ha = ai[k], sa[k], ha[k]
            c0, c1, c2, c3, c4 = c0[k], c1[k], c2[k], c3[k], c4[k]
    out[ai] = sa
    return out, missed


@dataclass(frozen=True)
class Dent:
    """A local defect pressed into a surface: the surface moves inward along its normal by
    ``depth_mm * exp(-|p - centre|^2 / (2 sigma_mm^2))`` (``centre`` on the undented surface,
    parent frame, mm). Beyond ``REACH`` sigmas the surface is left exactly as designed."""

    centre: np.ndarray
    depth_mm: float
    sigma_mm: float

    REACH = 5.0

    def transformed(self, T: np.ndarray) -> Dent:
        """The same dent in another frame."""
        return Dent(T[:3, :3] @ self.centre + T[:3, 3], self.depth_mm, self.sigma_mm)

    def near(self, P: np.ndarray) -> np.ndarray:
        """Points (N, 3) where the dent moves the surface."""
        return norm3(P - self.centre) < self.REACH * self.sigma_mm

    def depth(self, P: np.ndarray) -> np.ndarray:
        """Inward displacement (mm) at points (N, 3)."""
        r = P - self.centre
        return self.depth_mm * np.exp(-rowdot(r, r) / (2.0 * self.sigma_mm**2))

    def gradient(self, P: np.ndarray) -> np.ndarray:
        """Gradient (N, 3) of :meth:`depth`."""
        return -(P - self.centre) * (self.depth(P) / self.sigma_mm**2)[:, None]


@dataclass
class FreeformPart(Primitive):
    """A convex freeform: ``||X||_4 <= 1, X_z >= 0`` with ``X = M (p - c)``.

    ``M = diag(1/a, 1/b, 1/c) @ S @ R^T`` maps the part frame (origin at the middle of its
    footprint on the table, z up) to the unit superellipsoid of degree 4; ``S`` shears x by
    z (the part leans). The surface is the level set ``N(X) = 1`` of the convex gauge function
    ``N(X) = (X^4 + Y^4 + Z^4)^(1/4)``: rays meet it by Newton's method on ``N - 1``, which
    converges monotonically from outside (convexity) to machine precision. Its bottom
    (X_z = 0) rests on the table (face 1, hidden).

    With a :class:`Dent`, the surface is the zero set of ``F(p) = s(p) + dent.depth(p)``, where
    ``s = (N - 1) / |grad_p N|`` is the design surface's signed distance to first order (its
    error at 0.1 mm from the surface is ~0.1 mm^2 / radius of curvature, below 1 um here):
    hits, normals, sections and the inside test near the dent follow F by Newton's method from
    the design surface's (a few iterations, to 1e-12 mm).
    """

    c: np.ndarray
    M: np.ndarray
    albedo_value: float = 0.75
    name: str = "part"
    dent: Dent | None = None

    def __post_init__(self):
        self.Minv = np.linalg.inv(self.M)

    def transformed(self, T):
        """The same part in another frame."""
        R, t = T[:3, :3], T[:3, 3]
        dent = None if self.dent is None else self.dent.transformed(T)
        return FreeformPart(R @ self.c + t, self.M @ R.T, self.albedo_value, self.name, dent)

    def design_gradient(self, P):
        """grad_p N (N, 3) of the design surface's gauge at points."""
        X = self.to_unit(P)
        return mat3(X**3 / np.maximum(self.gauge(X), 1e-300)[:, None] ** 3, self.M)

    def dent_function(self, P):
        """F(p): positive outside the dented surface, zero on it, in mm near the surface."""
        return (self.gauge(self.to_unit(P)) - 1.0) / norm3(self.design_gradient(P)) + self.dent.depth(P)

    def dent_step(self, P, D, iterations: int = 12):
        """Steps s (N,) with F(P + s D) = 0 near the design-surface points P, by Newton's method."""
        s = np.zeros(len(P))
        for _ in range(iterations):
            Q = P + s[:, None] * D
            g = self.design_gradient(Q)
            dF = rowdot(g / norm3(g)[:, None] + self.dent.gradient(Q), D)
            step = -self.dent_function(Q) / np.where(np.abs(dF) > 1e-12, dF, 1e-12)
            s += step
            if np.abs(step).max(initial=0.0) < 1e-12:
                break
        return s

    @staticmethod
    def gauge(X):
        """N(X) = ||X||_4 of points (..., 3)."""
        X2 = X * X
        return np.sqrt(np.sqrt(X2[..., 0] ** 2 + X2[..., 1] ** 2 + X2[..., 2] ** 2))

    def to_unit(self, P):
        """Unit-superellipsoid coordinates X of parent points."""
        return mat3(P - self.c, self.M.T)

    def intersect(self, o, d, tmin):
        """First hit t and face (0 surface, 1 bottom) of rays o + t d."""
        t, face = self._intersect_design(o, d, tmin)
        if self.dent is None:
            return t, face
        hit = np.flatnonzero(np.isfinite(t) & (face == 0))
        if hit.size:
            oh = o[hit] if o.ndim == 2 else np.broadcast_to(o, (hit.size, 3))
            P = oh + t[hit, None] * d[hit]
            near = self.dent.near(P)
            if near.any():
                k = hit[near]
                # the dent only removes material: the ray meets it beyond the design hit
                t[k] += self.dent_step(P[near], d[k])
        return t, face

    def _intersect_design(self, o, d, tmin):
        """First hit t and face of rays o + t d with the undented design surface."""
        n = len(d)
        oX = self.to_unit(o) if o.ndim == 2 else np.broadcast_to(self.to_unit(o[None])[0], (n, 3))
        dX = mat3(d, self.M.T)
        lo_b = np.array([-1.0, -1.0, 0.0])
        hi_b = np.array([1.0, 1.0, 1.0])
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dX
            t1 = (lo_b - oX) * inv
            t2 = (hi_b - oX) * inv
        bad = np.isnan(t1) | np.isnan(t2)
        lo3 = np.where(bad, -INF, np.minimum(t1, t2))
        hi3 = np.where(bad, INF, np.maximum(t1, t2))
        lo = np.maximum(np.maximum(lo3[:, 0], lo3[:, 1]), lo3[:, 2])
        hi = np.minimum(np.minimum(hi3[:, 0], hi3[:, 1]), hi3[:, 2])
        t = np.full(n, INF)
        face = np.zeros(n, np.int8)
        idx = np.nonzero((lo <= hi) & (hi > tmin))[0]
        if idx.size == 0:
            return t, face
        o_, d_ = take_rows(oX, idx), take_rows(dX, idx)
        # the body lies inside the ball ||X||_2 <= 3^(1/4) (since ||X||_2 <= 3^(1/4) ||X||_4):
        # start Newton where the ray enters that ball, if later than the box
        a2 = rowdot(d_, d_)
        b2 = rowdot(d_, o_)
        c2 = rowdot(o_, o_) - np.sqrt(3.0)
        disc = b2 * b2 - a2 * c2
        t_ball = np.where(disc > 0, (-b2 - np.sqrt(np.maximum(disc, 0.0))) / a2, INF)
        keep = disc > 0
        if not keep.all():
            idx, o_, d_, t_ball = idx[keep], o_[keep], d_[keep], t_ball[keep]
            if idx.size == 0:
                return t, face
        tt = np.maximum(np.maximum(lo[idx], t_ball), tmin)
        X0 = o_ + tt[:, None] * d_
        inside0 = (self.gauge(X0) < 1.0) & (X0[:, 2] >= 0)
        missed = np.zeros(idx.size, bool)
        ai = np.nonzero(~inside0)[0]
        s_, miss_ = _gauge_root(o_[ai] + tt[ai, None] * d_[ai], d_[ai], hi[idx[ai]] - tt[ai])
        tt[ai] += s_
        missed[ai] = miss_
        Xh = o_ + tt[:, None] * d_
        ok = ~missed & ~inside0 & (np.abs(self.gauge(Xh) - 1.0) < 1e-9) & (Xh[:, 2] >= 0)
        res = np.where(ok, tt, INF)
        # the bottom face X_z = 0 (only reachable from below the table)
        with np.errstate(divide="ignore", invalid="ignore"):
            tb = -o_[:, 2] / d_[:, 2]
        Xb = o_ + np.where(np.isfinite(tb), tb, 0.0)[:, None] * d_
        bottom = np.isfinite(tb) & (tb > tmin) & (self.gauge(Xb) <= 1.0) & (d_[:, 2] > 0)
        fres = (bottom & (tb < res)).astype(np.int8)
        res = np.where(fres == 1, tb, res)
        res = np.where(inside0, tmin, res)
        t[idx] = res
        face[idx] = fres
        return t, face

    def normal(self, P, face):
        """Outward unit normals."""
        X = self.to_unit(P)
        g = mat3(X**3, self.M)
        if self.dent is not None:
            near = (face == 0) & self.dent.near(P)
            if near.any():
                gn = self.design_gradient(P[near])
                g[near] = gn / norm3(gn)[:, None] + self.dent.gradient(P[near])
        g = np.where((face == 1)[:, None], -self.M[2], g)  # bottom: gradient of -X_z
        return g / norm3(g)[:, None]


    def inside(self, P, tol=1e-9):
        """Points in the closed solid (tol in mm, roughly)."""
        X = self.to_unit(P)
        tn = 1.5 * tol * np.linalg.norm(self.M, 2)
        out = (self.gauge(X) <= 1.0 + tn) & (X[:, 2] >= -tn)
        if self.dent is not None:
            near = out & self.dent.near(P)
            if near.any():
                out[near] = self.dent_function(P[near]) <= 1.5 * tol
        return out

    def sections(self, n, d):
        """The closed curve where the plane meets the surface, cut at the table."""
        n_unit = n / np.linalg.norm(n)
        m = self.Minv.T @ n
        h = n @ self.c + d
        mn = np.linalg.norm(m)
        m, h = m / mn, h / mn
        w = np.sign(m) * np.abs(m) ** (1.0 / 3.0)
        lam = -h / (m @ w)
        Xs = lam * w  # point of the plane with the smallest gauge
        if self.gauge(Xs) >= 1.0 - 1e-12:
            return []
        e1, e2 = _basis(m)

        # from Xs (inside) every in-plane direction leaves the body once, inside the ball
        # ||X||_2 <= 3^(1/4): come back from that ball's surface to the body's
        r_out = np.sqrt(np.sqrt(3.0)) * 1.0001

        def fn(t):
            dirs = np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2
            b2 = dirs @ Xs
            rho0 = -b2 + np.sqrt(b2 * b2 - (Xs @ Xs - r_out**2))
            s_, _ = _gauge_root(Xs + rho0[:, None] * dirs, -dirs, rho0)
            X = Xs + (rho0 - s_)[:, None] * dirs
            P = self.c + mat3(X, self.Minv.T)
            g = mat3(X**3, self.M)
            N = g / norm3(g)[:, None]
            if self.dent is not None:
                near = self.dent.near(P)
                if near.any():
                    # the dented curve: from the design curve inward, within the plane
                    u = N[near] - np.outer(N[near] @ n_unit, n_unit)
                    u /= norm3(u)[:, None]
                    P[near] -= self.dent_step(P[near], -u)[:, None] * u
                    N[near] = self.normal(P[near], np.zeros(int(near.sum()), np.int8))
            return P, N, X[:, 2] >= 0

        return [Curve(self.pid, fn, 0.0, 2 * np.pi, True)]

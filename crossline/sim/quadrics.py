"""Round solids of the ball artefact: the sphere and its stem, a finite cylinder's side.

Split from ``crossline.sim.scene`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crossline.sim.primitive import Curve, Primitive
from crossline.sim.vec3 import INF, _basis, dot3, norm3, outer3, rowdot, take_rows

__all__ = ["Cylinder", "Sphere"]


# ----------------------------------------------------------------------------- sphere


@dataclass
class Sphere(Primitive):
    """A sphere of centre c and radius r."""

    c: np.ndarray
    r: float
    albedo_value: float = 0.7
    name: str = "sphere"

    def transformed(self, T):
        """The same sphere in another frame."""
        return Sphere(T[:3, :3] @ self.c + T[:3, 3], self.r, self.albedo_value, self.name)

    def intersect(self, o, d, tmin):
        """First hit t of rays o + t d."""
        oc = o - self.c
        a = rowdot(d, d)
        b = rowdot(d, oc) if oc.ndim == 2 else dot3(d, oc)
        cc = (rowdot(oc, oc) if oc.ndim == 2 else oc @ oc) - self.r**2
        disc = b * b - a * cc
        ok = disc >= 0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        # numerically stable roots
        q = -(b + np.copysign(sq, b))
        with np.errstate(divide="ignore", invalid="ignore"):
            r1 = q / a
            r2 = cc / q
        t1 = np.minimum(r1, r2)
        t2 = np.maximum(r1, r2)
        t = np.where(t1 > tmin, t1, np.where(t2 > tmin, t2, INF))
        t = np.where(ok, t, INF)
        return t, np.zeros(len(d), np.int8)

    def normal(self, P, face):
        """Outward normals."""
        return (P - self.c) / self.r


    def inside(self, P, tol=1e-9):
        """Points in the closed ball."""
        return norm3(P - self.c) <= self.r + tol

    def sections(self, n, d):
        """The circle where the plane meets the sphere."""
        s = n @ self.c + d
        if abs(s) >= self.r:
            return []
        cc = self.c - s * n
        rho = np.sqrt(self.r**2 - s * s)
        e1, e2 = _basis(n)

        def fn(t):
            P = cc + rho * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
            return P, (P - self.c) / self.r, np.ones(len(t), bool)

        return [Curve(self.pid, fn, 0.0, 2 * np.pi, True)]


# ----------------------------------------------------------------------------- cylinder


@dataclass
class Cylinder(Primitive):
    """The side of a cylinder: base centre c0, unit axis a, radius r, length L (no caps).

    Its caps are always buried in other solids (the table, the ball), so rays never meet them.
    """

    c0: np.ndarray
    a: np.ndarray
    r: float
    L: float
    albedo_value: float = 0.4
    name: str = "stem"

    def transformed(self, T):
        """The same cylinder in another frame."""
        return Cylinder(T[:3, :3] @ self.c0 + T[:3, 3], T[:3, :3] @ self.a, self.r, self.L,
                        self.albedo_value, self.name)

    def intersect(self, o, d, tmin):
        """First hit t of rays o + t d on the side within [0, L]."""
        n = len(d)
        # most rays pass far from a thin stem: reject them with its bounding sphere first
        mid = self.c0 + 0.5 * self.L * self.a
        R2 = (0.5 * self.L) ** 2 + self.r**2
        om = mid - o
        bb = dot3(d, om) if om.ndim == 1 else rowdot(d, om)
        cc = (om @ om if om.ndim == 1 else rowdot(om, om)) - R2
        cand = np.nonzero(bb * bb - rowdot(d, d) * cc >= 0)[0]
        t_all = np.full(n, INF)
        if cand.size == 0:
            return t_all, np.zeros(n, np.int8)
        if cand.size < n:
            o = o if o.ndim == 1 else o[cand]
            d = take_rows(d, cand)
        oc = o - self.c0
        if oc.ndim == 1:
            oc = np.broadcast_to(oc, d.shape)
        da = dot3(d, self.a)
        oa = dot3(oc, self.a)
        dp = d - outer3(da, self.a)
        op = oc - outer3(oa, self.a)
        A = rowdot(dp, dp)
        B = rowdot(dp, op)
        C = rowdot(op, op) - self.r**2
        disc = B * B - A * C
        ok = (disc >= 0) & (A > 1e-300)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        q = -(B + np.copysign(sq, B))
        with np.errstate(divide="ignore", invalid="ignore"):
            r1 = q / A
            r2 = C / q
        t = np.full(len(d), INF)
        for root in (np.maximum(r1, r2), np.minimum(r1, r2)):
            h = oa + root * da
            good = ok & (root > tmin) & (h >= 0) & (h <= self.L)
            t = np.where(good & (root < t), root, t)
        t_all[cand] = t
        return t_all, np.zeros(n, np.int8)

    def normal(self, P, face):
        """Outward radial normals."""
        q = P - self.c0
        q = q - outer3(dot3(q, self.a), self.a)
        return q / norm3(q)[:, None]


    def inside(self, P, tol=1e-9):
        """Points in the closed cylinder."""
        q = P - self.c0
        h = dot3(q, self.a)
        rr = norm3(q - h[:, None] * self.a)
        return (rr <= self.r + tol) & (h >= -tol) & (h <= self.L + tol)

    def sections(self, n, d):
        """The ellipse arc(s) where the plane meets the side."""
        na = n @ self.a
        if abs(na) < 1e-6:
            return []  # plane parallel to the axis: never happens in our scenes
        e1, e2 = _basis(self.a)
        k0 = n @ self.c0 + d

        def fn(t):
            radial = np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2
            h = -(k0 + self.r * dot3(radial, n)) / na
            P = self.c0 + self.r * radial + h[:, None] * self.a
            return P, radial, (h >= 0) & (h <= self.L)

        return [Curve(self.pid, fn, 0.0, 2 * np.pi, True)]

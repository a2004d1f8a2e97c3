"""Flat-faced solids: the half-space (the table, a background) and the box (gauge block,
surface plate, the calibration board's plate, with the board's printed texture).

Split from ``crossline.sim.scene`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from crossline.sim.primitive import Curve, Primitive
from crossline.sim.vec3 import INF, dot3, mat3, take_rows

__all__ = ["Box", "HalfSpace"]


# ----------------------------------------------------------------------------- half-space


@dataclass
class HalfSpace(Primitive):
    """The solid ``n . (p - p0) <= 0`` (a table or a background); its face is the plane."""

    p0: np.ndarray
    n: np.ndarray
    albedo_value: float = 0.3
    name: str = "table"

    def transformed(self, T):
        """The same solid in another frame."""
        return HalfSpace(T[:3, :3] @ self.p0 + T[:3, 3], T[:3, :3] @ self.n, self.albedo_value,
                         self.name)

    def intersect(self, o, d, tmin):
        """First hit t (inf if none) and face (0) of rays o + t d."""
        nd = dot3(d, self.n)
        po = (self.p0 - o) @ self.n if o.ndim == 1 else dot3(self.p0 - o, self.n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = po / nd
        ok = (nd < 0) & (t > tmin)
        return np.where(ok, t, INF), np.zeros(len(d), np.int8)

    def normal(self, P, face):
        """Outward unit normals at points."""
        return np.broadcast_to(self.n, P.shape)


    def inside(self, P, tol=1e-9):
        """Points in the closed solid (within tol)."""
        return dot3(P - self.p0, self.n) <= tol

    def sections(self, n, d):
        """The line where the plane n . p + d = 0 meets the face."""
        u = np.cross(n, self.n)
        if np.linalg.norm(u) < 1e-9:
            return []
        u /= np.linalg.norm(u)
        A = np.stack([n, self.n, u])
        p = np.linalg.solve(A, np.array([-d, self.n @ self.p0, 0.0]))
        nn = self.n

        def fn(t):
            P = p + t[:, None] * u
            return P, np.broadcast_to(nn, P.shape), np.ones(len(t), bool)

        return [Curve(self.pid, fn, -2000.0, 2000.0, False)]


# ----------------------------------------------------------------------------- box


@dataclass
class Box(Primitive):
    """A box: centre c, axes R (columns, parent frame), half sizes h.

    Faces are numbered 2*axis + (0 for the -side, 1 for the +side). ``hidden`` faces rest on
    another solid and carry no stripe. ``texture`` maps (face, local points) to
    (albedo, distance to the nearest albedo edge in mm) for textured faces (the board).
    """

    c: np.ndarray
    R: np.ndarray
    h: np.ndarray
    albedo_value: float = 0.5
    name: str = "box"
    hidden: tuple[int, ...] = ()
    textures: dict = field(default_factory=dict)

    def transformed(self, T):
        """The same box in another frame."""
        return Box(T[:3, :3] @ self.c + T[:3, 3], T[:3, :3] @ self.R, self.h, self.albedo_value,
                   self.name, self.hidden, self.textures)

    def local(self, P):
        """Box-local coordinates of parent-frame points."""
        return mat3(P - self.c, self.R)

    def intersect(self, o, d, tmin):
        """First hit t and face of rays o + t d (slab method)."""
        n = len(d)
        ol = (o - self.c) @ self.R if o.ndim == 1 else mat3(o - self.c, self.R)
        dl = mat3(d, self.R)
        tnear = np.full(n, -INF)
        tfar = np.full(n, INF)
        face = np.zeros(n, np.int8)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                dk = dl[:, k]
                ok_ = ol[k] if ol.ndim == 1 else ol[:, k]
                inv = 1.0 / dk
                t1 = (-self.h[k] - ok_) * inv
                t2 = (self.h[k] - ok_) * inv
                lo = np.minimum(t1, t2)
                hi = np.maximum(t1, t2)
                # 0 * inf (a ray in a slab's plane): no bound from this slab
                nan = np.isnan(lo)
                if nan.any():
                    lo[nan] = -INF
                nan = np.isnan(hi)
                if nan.any():
                    hi[nan] = INF
                # entering through the -h face when the ray runs towards +k
                better = lo > tnear
                tnear = np.where(better, lo, tnear)
                fk = (dk < 0).view(np.int8)  # 0 / 1 as int8, no int64 temporaries
                fk += 2 * k
                face = np.where(better, fk, face)
                tfar = np.minimum(tfar, hi)
        hit = (tnear <= tfar) & (tnear > tmin)
        # a ray that starts inside (tnear <= tmin < tfar) is blocked at once (shadow rays)
        inside = (tnear <= tmin) & (tfar > tmin) & (tnear <= tfar)
        t = np.where(hit, tnear, np.where(inside, tmin, INF))
        return t, face

    def normal(self, P, face):
        """Outward unit normals of faces."""
        normals = np.concatenate([-self.R.T[:, None, :], self.R.T[:, None, :]], axis=1).reshape(6, 3)
        return take_rows(normals, face)

    def albedo(self, P, face):
        """Reflectance at points (textured faces through their texture)."""
        a = np.full(len(P), self.albedo_value)
        for f, tex in self.textures.items():
            m = face == f
            if m.any():
                a[m] = tex(self.local(P[m]), False)[0]
        return a

    def edge_distance(self, P, face):
        """Distance (mm) to the nearest edge: the face's border, or an albedo edge on it."""
        q = self.local(P)
        e = self._border_distance(q, face)
        for f, tex in self.textures.items():
            m = face == f
            if m.any():
                e[m] = np.minimum(e[m], tex(q[m])[1])
        return e

    def _border_distance(self, q, face):
        """Distance (mm) from local points on a face to that face's border."""
        slack = self.h - np.abs(q)
        slack[np.arange(len(q)), face // 2] = INF
        return np.minimum(np.minimum(slack[:, 0], slack[:, 1]), slack[:, 2])

    def shade(self, P, face, edges: bool):
        """Normals, albedos and (optionally) edge distances, evaluating textures once."""
        q = self.local(P)
        N = self.normal(P, face)
        a = np.full(len(P), self.albedo_value)
        e = None
        if edges:
            e = self._border_distance(q, face)
        for f, tex in self.textures.items():
            m = face == f
            if m.all():
                a, em = tex(q, edges)
                if edges:
                    e = np.minimum(e, em)
            elif m.any():
                am, em = tex(q[m], edges)
                a[m] = am
                if edges:
                    e[m] = np.minimum(e[m], em)
        return N, a, e

    def inside(self, P, tol=1e-9):
        """Points in the closed box."""
        q = np.abs(self.local(P))
        return (q[:, 0] <= self.h[0] + tol) & (q[:, 1] <= self.h[1] + tol) & (q[:, 2] <= self.h[2] + tol)

    def face_planes(self):
        """(face, point, outward normal) of every face."""
        out = []
        for axis in range(3):
            for s in (0, 1):
                sign = 1.0 if s else -1.0
                nrm = self.R[:, axis] * sign
                out.append((2 * axis + s, self.c + nrm * self.h[axis], nrm))
        return out

    def sections(self, n, d, faces: tuple[int, ...] | None = None):
        """Segments where the plane meets the visible faces (or the given ones)."""
        curves = []
        for f, p0, nf in self.face_planes():
            if f in self.hidden or (faces is not None and f not in faces):
                continue
            u = np.cross(n, nf)
            if np.linalg.norm(u) < 1e-9:
                continue
            u /= np.linalg.norm(u)
            A = np.stack([n, nf, u])
            p = np.linalg.solve(A, np.array([-d, nf @ p0, 0.0]))
            q0 = (p - self.c) @ self.R
            q1 = u @ self.R
            lo, hi = -INF, INF
            for j in range(3):
                if j == f // 2:
                    continue
                if abs(q1[j]) < 1e-12:
                    if abs(q0[j]) > self.h[j]:
                        lo, hi = INF, -INF
                    continue
                a = (-self.h[j] - q0[j]) / q1[j]
                b = (self.h[j] - q0[j]) / q1[j]
                lo, hi = max(lo, min(a, b)), min(hi, max(a, b))
            if not lo < hi:
                continue

            def fn(t, p=p, u=u, nf=nf):
                P = p + t[:, None] * u
                return P, np.broadcast_to(nf, P.shape), np.ones(len(t), bool)

            curves.append(Curve(self.pid, fn, lo, hi, False))
        return curves

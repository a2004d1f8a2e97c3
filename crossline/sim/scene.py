"""Analytic scenes: exact ray intersections, shadow tests and plane sections in float64.

Primitives: a half-space (the table, a background), a box (gauge block, surface plate, the
calibration board's plate), a sphere, a finite cylinder (the ball's stem) and a convex
freeform (a leaning superellipsoid of degree 4 cut by the table: the earbud-case-like part,
see ``FreeformPart``). Every primitive answers, for rays ``P = o + t d``:

* ``intersect(o, d, tmin)``: the first hit ``t`` (inf when none) and a face index;
* ``normal``, ``albedo``: surface normal (outward) and reflectance at hits;
* ``inside(P)``: whether points lie in the closed solid (a point of one surface inside
  another solid is not a surface point of the scene);
* ``sections(n, d)``: the exact curves where a plane ``n . p + d = 0`` meets its surface, as
  parametric curves that can be evaluated anywhere (used for the true stripe centreline and
  to find the image band that the laser can light).

A scene is built in the base frame and transformed to the camera frame for each image, so
camera rays start at the origin. Everything is float64 and analytic (the freeform by a
monotone Newton iteration on a convex gauge function), so hits are exact to ~1e-10 mm.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Box", "Curve", "Cylinder", "FreeformPart", "HalfSpace", "Scene", "Sphere"]

INF = np.inf


# Small (N, 3) x (3,) products written out by component: numpy hands ``a @ M`` to BLAS, whose
# threads spin and whose summation order may depend on the thread count; these are faster for
# three components, single-threaded and bit-reproducible.


def dot3(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise dot products (N,) of points (N, 3) with one vector (3,)."""
    return a[:, 0] * v[0] + a[:, 1] * v[1] + a[:, 2] * v[2]


def rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products (N,) of two (N, 3) arrays."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def empty3(n: int) -> np.ndarray:
    """An uninitialised (n, 3) array stored column by column.

    Point arrays are (N, 3) but their maths runs on columns: in column-major storage
    ``P[:, k]`` is contiguous, and ``P - c`` or ``t[:, None] * d`` are one vectorised loop
    over N instead of N loops over 3. The values do not depend on
    the storage order.
    """
    return np.empty((3, n)).T


def take_rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` for point arrays (N, 3), column-major (see ``empty3``)."""
    out = empty3(len(idx))
    for k in range(3):
        np.take(a[:, k], idx, out=out[:, k])
    return out


def put_rows(a: np.ndarray, idx: np.ndarray, v: np.ndarray) -> None:
    """``a[idx] = v`` for point arrays (N, 3), column by column."""
    for k in range(3):
        a[:, k][idx] = v[:, k]


def outer3(s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``s[:, None] * v`` for scalars (N,) and a vector (3,), column-major."""
    out = empty3(len(s))
    for k in range(3):
        np.multiply(s, v[k], out=out[:, k])
    return out


def mat3(a: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``a @ M`` for points (N, 3) and a 3 x 3 matrix, without BLAS (column-major result)."""
    out = empty3(len(a))
    for j in range(3):
        out[:, j] = a[:, 0] * M[0, j] + a[:, 1] * M[1, j] + a[:, 2] * M[2, j]
    return out


def norm3(a: np.ndarray) -> np.ndarray:
    """Row-wise Euclidean norms (N,) of (N, 3)."""
    return np.sqrt(rowdot(a, a))


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit vector n to a right-handed orthonormal basis."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


@dataclass
class Curve:
    """A parametric curve on a primitive's surface: ``fn(t) -> (points, normals, valid)``."""

    prim: int
    fn: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
    t0: float
    t1: float
    closed: bool = False


class Primitive:
    """Base of the scene's solids; ``pid`` is set by the scene."""

    name: str = ""
    pid: int = -1

    def transformed(self, T: np.ndarray) -> Primitive:  # pragma: no cover - interface
        raise NotImplementedError

    def albedo(self, P, face):
        """Reflectance at points: one value over the whole solid unless a solid says more."""
        return np.full(len(P), self.albedo_value)

    def edge_distance(self, P, face):
        """Distance (mm) to the nearest albedo edge: none on a plain solid."""
        return np.full(len(P), INF)


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


# ----------------------------------------------------------------------------- scene


class Scene:
    """A list of primitives with first-hit tracing, shadow tests and plane sections."""

    def __init__(self, prims: list[Primitive], up: np.ndarray | None = None):
        self.prims = prims
        for i, p in enumerate(prims):
            p.pid = i
        self.textured = any(getattr(p, "textures", None) for p in prims)
        self.up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)

    def transformed(self, T: np.ndarray) -> Scene:
        """The scene in another frame (p_new = T @ p)."""
        return Scene([p.transformed(T) for p in self.prims], T[:3, :3] @ self.up)

    def trace(self, o: np.ndarray, d: np.ndarray, tmin: float = 1e-9):
        """First hits of rays o + t d: t (inf = none), primitive index (-1), face."""
        n = len(d)
        t = np.full(n, INF)
        pid = np.full(n, -1, np.int16)
        face = np.zeros(n, np.int8)
        for p in self.prims:
            tp, fp = p.intersect(o, d, tmin)
            better = tp < t
            t = np.where(better, tp, t)
            pid = np.where(better, p.pid, pid)
            face = np.where(better, fp, face)
        return t, pid, face

    def blocked(self, P: np.ndarray, E: np.ndarray, tmin: float = 1e-7,
                on: np.ndarray | None = None) -> np.ndarray:
        """Whether the segment from each point P to E (a point or points) meets a solid.

        ``on`` (optional) names the primitive each point lies on, for points already known to
        face E: every primitive is convex, so a ray leaving its surface outwards cannot meet it
        again, and that test is skipped.
        """
        d = E - P
        out = np.zeros(len(P), bool)
        for p in self.prims:
            free = ~out if on is None else ~out & (on != p.pid)
            idx = np.nonzero(free)[0]
            if idx.size == 0:
                continue
            tp, _ = p.intersect(take_rows(P, idx), take_rows(d, idx), tmin)
            out[idx] = tp < 1.0 - 1e-9
        return out

    def shade(self, P, pid, face, edges: bool = False):
        """Normals, albedos (and distances to the nearest edge) at hits of known primitives."""
        n = len(P)
        N = np.empty_like(P)
        a = np.empty(n)
        e = np.full(n, INF) if edges else None
        for p in self.prims:
            m = pid == p.pid
            cnt = int(m.sum()) if n else 0
            if cnt == 0:
                continue
            if cnt == n:
                Pm, fm = P, face
            else:
                m = np.flatnonzero(m)  # row indices: much faster than a row mask
                Pm, fm = take_rows(P, m), face[m]
            if isinstance(p, Box) and p.textures:
                Nm, am, em = p.shade(Pm, fm, edges)
            else:
                Nm, am = p.normal(Pm, fm), p.albedo(Pm, fm)
                em = p.edge_distance(Pm, fm) if edges else None
            if cnt == n:
                N[:], a[:] = Nm, am
                if edges:
                    e[:] = em
            else:
                put_rows(N, m, Nm)
                a[m] = am
                if edges:
                    e[m] = em
        return N, a, e

    def surface(self, P, pid, face):
        """Normals and albedos at hit points of known primitives."""
        N, a, _ = self.shade(P, pid, face)
        return N, a

    def edge_distance(self, P, pid, face):
        """Distance to the nearest albedo or face edge, inf where none."""
        return self.shade(P, pid, face, edges=True)[2]

    def inside_other(self, P: np.ndarray, pid: int, tol: float = 1e-9) -> np.ndarray:
        """Points inside (or on) any solid other than primitive ``pid``."""
        out = np.zeros(len(P), bool)
        for p in self.prims:
            if p.pid != pid:
                out |= p.inside(P, tol)
        return out

    def sections(self, n: np.ndarray, d: float) -> list[Curve]:
        """All curves where the plane n . p + d = 0 meets the scene's surfaces."""
        out = []
        for p in self.prims:
            out.extend(p.sections(np.asarray(n, dtype=np.float64), float(d)))
        return out

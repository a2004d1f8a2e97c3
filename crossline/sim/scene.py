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

The code lives in modules beside this one (issue 21.3): ``vec3`` (point-array products and
storage), ``primitive`` (``Primitive``, ``Curve``), ``planar`` (``HalfSpace``, ``Box``),
``quadrics`` (``Sphere``, ``Cylinder``) and ``freeform`` (``FreeformPart``, ``Dent``). This one
holds the ``Scene`` (first hits, shadows, shading and sections over its primitives) and
re-exports the names its importers use, so ``from crossline.sim.scene import ...`` works as
before.
"""

from __future__ import annotations

import numpy as np

from crossline.sim.freeform import Dent as Dent
from crossline.sim.freeform import FreeformPart
from crossline.sim.planar import Box, HalfSpace
from crossline.sim.primitive import Curve, Primitive
from crossline.sim.quadrics import Cylinder, Sphere
from crossline.sim.vec3 import INF, put_rows, take_rows
from crossline.sim.vec3 import dot3 as dot3
from crossline.sim.vec3 import empty3 as empty3
from crossline.sim.vec3 import norm3 as norm3
from crossline.sim.vec3 import rowdot as rowdot

__all__ = ["Box", "Curve", "Cylinder", "FreeformPart", "HalfSpace", "Scene", "Sphere"]


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

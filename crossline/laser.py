"""Laser planes in the camera frame: ``n · p + d = 0`` with ``|n| = 1`` (the paper's [A B C D])."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from crossline.errors import CrosslineError
from crossline.geometry import angle_between, plane_line_intersection
from crossline.io.atomic import write_json
from crossline.io.values import finite_array

__all__ = ["LASERS", "LaserFileError", "LaserPlane", "LaserPlanes"]

LASERS = ("A", "B")
NORMAL_TOLERANCE = 1e-6  # | |n| - 1 | allowed in lasers.json (a stage writes unit normals)
# two planes closer than this are one: sin of their angle (rad), and their distance (mm) per mm
# of |d| (at least 1 mm): a plane copied, or written again with its numbers rounded
SAME_PLANE_TOLERANCE = 1e-6
PLANE_FORM = "{'normal': [nx, ny, nz], 'd': d}"


class LaserFileError(CrosslineError, ValueError):
    """lasers.json cannot be read or holds no usable laser plane (names the file)."""


@dataclass(frozen=True)
class LaserPlane:
    """One laser's light plane in the camera frame (mm)."""

    normal: np.ndarray
    d: float
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).reshape(3)
        norm = np.linalg.norm(n)
        if not np.isfinite(norm) or norm < 1e-9:
            raise ValueError(f"laser plane normal must be a finite non-zero vector, got {n}")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "d", float(self.d) / norm)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distances (N,) of camera-frame points (N, 3) to the plane."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.d

    def intersect_rays(self, rays: np.ndarray) -> np.ndarray:
        """Points (N, 3) where camera rays through the origin with directions (N, 3) meet the plane.

        This is the paper's eq. 8 written for any ray direction: ``Z = -D / (n · r)``.
        """
        rays = np.asarray(rays, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -self.d / (rays @ self.normal)
        return rays * t[..., None]

    def to_dict(self) -> dict[str, Any]:
        """JSON mapping with ``normal`` and ``d`` plus any extras (residuals, counts, ...)."""
        out = dict(self.extra)
        out.update(normal=self.normal.tolist(), d=self.d)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LaserPlane:
        """Plane from a mapping with keys ``normal`` (a unit vector, within
        ``NORMAL_TOLERANCE``) and ``d``, finite numbers; ValueError naming the key otherwise."""
        n = finite_array(data, "normal", (3,), "the plane's unit normal [nx, ny, nz]")
        d = finite_array(data, "d", (), "the plane's offset d in mm (n · p + d = 0), a number")
        length = float(np.linalg.norm(n))
        if abs(length - 1.0) > NORMAL_TOLERANCE:
            raise ValueError(f"'normal' = {n.tolist()} has length {length:.9g}: expected a unit normal "
                             f"(|n| = 1 within {NORMAL_TOLERANCE:g})")
        extra = {k: v for k, v in data.items() if k not in ("normal", "d")}
        return cls(n, float(d), extra)


def _same_plane(a: LaserPlane, b: LaserPlane) -> str | None:
    """Why plane ``b`` is plane ``a`` (the same normal, or its opposite, and the same offset,
    within :data:`SAME_PLANE_TOLERANCE`), or None where they are two planes."""
    s = 1.0 if float(a.normal @ b.normal) >= 0 else -1.0  # n, d and -n, -d are one plane
    sin = float(np.linalg.norm(np.cross(a.normal, b.normal)))
    apart = abs(a.d - s * b.d)
    if sin > SAME_PLANE_TOLERANCE or apart > SAME_PLANE_TOLERANCE * max(1.0, abs(a.d)):
        return None
    return (f"its plane is laser A's (normal {b.normal.tolist()}, d = {b.d:.9g}: "
            f"{np.degrees(np.arcsin(min(sin, 1.0))):.3g} deg and {apart:.3g} mm from A's)")


@dataclass(frozen=True)
class LaserPlanes:
    """The planes of a rig's lasers, as stored in ``lasers.json``: A, and B on a two-line rig.

    A one-line rig (``rig.yaml`` ``lasers: [A]``) has ``B = None``; the angle between the
    planes and their crossing line exist only where there are two.
    """

    A: LaserPlane
    B: LaserPlane | None = None
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def names(self) -> tuple[str, ...]:
        """The lasers held: ("A",) or ("A", "B")."""
        return ("A",) if self.B is None else LASERS

    def __getitem__(self, laser: str) -> LaserPlane:
        if laser not in self.names:
            raise KeyError(f"unknown laser {laser!r}; this calibration has {list(self.names)}")
        return getattr(self, laser)

    def __contains__(self, laser: object) -> bool:
        return laser in self.names

    def angle_deg(self) -> float:
        """Angle between the two planes in degrees (90 for a perfect cross)."""
        if self.B is None:
            raise ValueError("one laser plane: there is no angle between planes")
        return float(np.degrees(angle_between(self.A.normal, self.B.normal)))

    def intersection_line(self) -> tuple[np.ndarray, np.ndarray]:
        """The planes' line of intersection in the camera frame: a point and a unit direction.

        Raises ValueError with one plane, or with two parallel planes.
        """
        if self.B is None:
            raise ValueError("one laser plane: there is no crossing line")
        return plane_line_intersection(self.A.normal, self.A.d, self.B.normal, self.B.d)

    def to_dict(self) -> dict[str, Any]:
        """The ``lasers.json`` mapping (two lasers: with their angle and crossing line)."""
        out: dict[str, Any] = {k: self[k].to_dict() for k in self.names}
        out.update(self.extra)
        if self.B is not None:
            out.setdefault("angle_AB_deg", self.angle_deg())
            try:
                p, u = self.intersection_line()
            except ValueError:  # parallel planes: no line to write
                pass
            else:
                out.setdefault("intersection_line", {"point": p.tolist(), "direction": u.tolist()})
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LaserPlanes:
        """Planes from a ``lasers.json`` mapping (``A``, and ``B`` if the rig has two lasers);
        ValueError naming the laser, the key and what was expected where one is not a plane."""
        if not isinstance(data, dict):
            raise ValueError(f"expected a JSON object with the plane of laser A (and B), "
                             f"got {type(data).__name__}")
        planes: dict[str, LaserPlane] = {}
        for name in LASERS:
            if name == "A" and name not in data:
                raise ValueError(f"no laser A: expected the plane of laser A as {PLANE_FORM}")
            if name in data:
                try:
                    planes[name] = LaserPlane.from_dict(data[name])
                except ValueError as exc:
                    raise ValueError(f"laser {name}: {exc} (expected the plane of laser {name} "
                                     f"as {PLANE_FORM})") from None
        if "B" in planes:
            why = _same_plane(planes["A"], planes["B"])
            if why is not None:
                raise ValueError(f"laser B: {why}; two lasers in one plane make no cross: expected "
                                 "two planes that cross in a line")
        extra = {k: v for k, v in data.items() if k not in LASERS}
        return cls(planes["A"], planes.get("B"), extra)

    def save(self, path: str | Path) -> None:
        """Write ``lasers.json`` atomically."""
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> LaserPlanes:
        """Read ``lasers.json``; LaserFileError naming the file and what is wrong."""
        path = Path(path)
        try:
            return cls.from_dict(json.loads(path.read_text()))
        except (KeyError, ValueError, TypeError) as exc:
            raise LaserFileError(f"{path}: not a laser-plane file: {exc}") from exc

"""What every solid of the analytic scene answers: ``Primitive`` and its section ``Curve``.

A primitive intersects rays, gives normals, albedos and edge distances at its surface points,
tells points inside it, and cuts its surface with a plane into ``Curve`` objects (see
``crossline.sim.scene``). Split from ``crossline.sim.scene`` (issue 21.3), which re-exports
the names its importers use.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from crossline.sim.vec3 import INF

__all__ = ["Curve", "Primitive"]


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

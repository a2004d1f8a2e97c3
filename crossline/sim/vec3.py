"""Point arrays (N, 3) for the analytic scene: products by component, column-major storage.

Row-wise dot products, norms, ``a @ M`` and ``s[:, None] * v`` written out by component
(single-threaded and bit-reproducible, see below), ``empty3`` / ``take_rows`` / ``put_rows``
for points stored column by column, ``_basis`` completing a unit vector to an orthonormal
basis, and ``INF``, the "no hit" of every tracer. Split from ``crossline.sim.scene``
(issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

import numpy as np

__all__ = ["INF", "dot3", "empty3", "mat3", "norm3", "outer3", "put_rows", "rowdot", "take_rows"]

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

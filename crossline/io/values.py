"""The numbers of a stage's JSON artefact (camera.json, lasers.json, handeye.json), checked as
they are read: each fault a ValueError naming the key, the value and what was expected (the
artefact's reader adds the file). A disk or an interrupted copy can leave a text, a NaN, a
list of another length or a matrix that is no longer a rigid transform where a stage wrote
numbers; none of them may reach a computation that then fails far from the file, or worse,
does not fail.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crossline.io.contract import _short

__all__ = ["RIGID_TOLERANCE", "finite_array", "rigid_transform"]

# largest |RᵀR − I| of a stored rotation: a stage writes float64 (1e-15); a hand-typed one to
# 6 decimals (1e-6) passes
RIGID_TOLERANCE = 1e-5


def finite_array(data: Any, key: str, shape: tuple[int, ...], what: str) -> np.ndarray:
    """``data[key]`` as a float64 array of ``shape`` with finite values; ValueError naming the
    key and ``what`` was expected if ``data`` is no JSON object holding such numbers there
    (texts, booleans, nulls and ragged lists are not numbers)."""
    if not isinstance(data, dict):
        raise ValueError(f"expected a JSON object with the key '{key}', got {type(data).__name__}")
    if key not in data:
        raise ValueError(f"no key '{key}': expected {what}")
    value = data[key]
    try:
        a = np.asarray(value)
    except (ValueError, TypeError):  # a ragged list
        a = None
    if a is None or a.dtype.kind not in "iuf" or a.shape != shape:
        raise ValueError(f"'{key}' = {_short(value)}: expected {what}")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"'{key}' = {_short(value)} holds non-finite values: expected {what}")
    return a


def rigid_transform(data: Any, key: str) -> np.ndarray:
    """``data[key]`` as a 4x4 rigid transform (rotation part orthonormal within
    :data:`RIGID_TOLERANCE`, determinant +1, last row [0, 0, 0, 1]); ValueError naming the key
    and what is wrong otherwise."""
    T = finite_array(data, key, (4, 4), f"'{key}', a finite 4x4 matrix (a rigid transform, mm)")
    R = T[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if off > RIGID_TOLERANCE or np.linalg.det(R) <= 0 or np.any(T[3] != (0.0, 0.0, 0.0, 1.0)):
        raise ValueError(
            f"'{key}' is not a rigid transform: its rotation part deviates from orthonormal by "
            f"{off:.3g} (at most {RIGID_TOLERANCE:g}), has determinant {np.linalg.det(R):.6g} "
            f"(expected +1) and last row {T[3].tolist()} (expected [0, 0, 0, 1])")
    return T

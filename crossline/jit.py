"""Compiled hot loops: numba (nogil, cached) when it is installed, plain Python otherwise.

numba is a dependency; the fallback only keeps the package importable where it is missing
(the loops then run as Python, slowly but with the same results).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

try:
    import numba as _numba
except ImportError:  # pragma: no cover - depends on the environment
    _numba = None

__all__ = ["HAVE_NUMBA", "jit"]

HAVE_NUMBA = _numba is not None


def jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` compiled by numba (nogil so threads run it in parallel, cached on disk, no bounds
    checks), or ``fn`` unchanged without numba."""
    if _numba is None:  # pragma: no cover - numba is a dependency
        return fn
    return _numba.njit(cache=True, nogil=True, boundscheck=False)(fn)

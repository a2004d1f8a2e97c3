"""A small Levenberg–Marquardt solver on the normal equations, for the calibration problems.

``scipy.optimize.least_squares(method="lm")`` (MINPACK) factorises the full Jacobian by QR at
every step, which dominates the camera bundle adjustment (thousands of residuals, a hundred
or more parameters). Here the step solves ``(JᵀJ + λ diag(JᵀJ)) δ = −Jᵀf`` (BLAS matrix
products and a Cholesky factorisation of a matrix the size of the parameter vector).
Marquardt's diagonal scaling makes the step independent of the parameters' units. The cost
is evaluated exactly, so the minimum found is exact even though the normal equations square
the Jacobian's condition number.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

__all__ = ["LMResult", "dense_normal", "levenberg_marquardt"]


@dataclass(frozen=True)
class LMResult:
    """Solution, residuals and ``JᵀJ`` at the solution, and the iteration count."""

    x: np.ndarray
    fun: np.ndarray
    normal: np.ndarray  # JᵀJ at x: its inverse is the covariance of whitened residuals
    iterations: int
    converged: bool

    @property
    def cost(self) -> float:
        """Half the sum of squared residuals, as scipy reports it."""
        return 0.5 * float(self.fun @ self.fun)


def levenberg_marquardt(
    fun: Callable[[np.ndarray], np.ndarray],
    normal: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0: np.ndarray,
    *,
    max_iter: int = 100,
    ftol: float = 1e-14,
    xtol: float = 1e-13,
) -> LMResult:
    """Minimise ``|fun(x)|²`` from ``x0``; ``normal(x, f)`` returns ``(JᵀJ, Jᵀf)`` at ``x``.

    Stops when a step lowers the cost by less than ``ftol`` relative, or moves the residuals
    by less than ``xtol`` of their norm, or when no step lowers the cost any more, or after
    ``max_iter`` Jacobians.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    f = fun(x)
    cost = float(f @ f)
    lam = 1e-3
    iterations = 0
    converged = False
    A, g = normal(x, f)
    for iterations in range(1, max_iter + 1):  # noqa: B007 - reported after the loop
        d = np.maximum(np.diag(A), 1e-300)
        scale = np.sqrt(d)
        accepted = False
        while lam < 1e16:
            try:
                c = cho_factor(A + lam * np.diag(d))
                step = -cho_solve(c, g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            x_new = x + step
            f_new = fun(x_new)
            cost_new = float(f_new @ f_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                # the step's effect on the residuals, relative to their size
                small_x = np.linalg.norm(step * scale) <= xtol * np.sqrt(cost)
                small_f = cost - cost_new <= ftol * cost
                x, f, cost = x_new, f_new, cost_new
                lam = max(lam / 10.0, 1e-12)
                accepted = True
                if small_x or small_f or cost == 0.0:
                    converged = True
                break
            lam *= 10.0
        if not accepted:
            converged = True  # no step lowers the cost: at the minimum to machine precision
            break
        A, g = normal(x, f)
        if converged:
            break
    return LMResult(x, f, A, iterations, converged)


def dense_normal(jac: Callable[[np.ndarray], np.ndarray]):
    """``normal`` for :func:`levenberg_marquardt` from a function giving the dense Jacobian."""

    def normal(x: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        J = jac(x)
        return J.T @ J, J.T @ f

    return normal

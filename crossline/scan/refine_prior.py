"""The arm's error model as the pose refinement's prior: sigmas, drift, its covariance.

``ArmPrior`` holds the per-axis sigmas of the reported poses' error, the share of it that is
a smooth Gauss-Markov drift and that drift's correlation time; ``prior_covariance`` is the
prior's correlation between frames (dense) and ``_prior_sparse`` its banded square-root
information, with the drift as unknowns of its own. Split from ``crossline.scan.refine``
(issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ArmPrior", "prior_covariance", "prior_draws"]

LEVER_MM = 300.0  # rotation prior from the position figure: the error spread over one arm link


@dataclass(frozen=True)
class ArmPrior:
    """The arm's reported-pose error model: per-axis sigmas, their smooth share and correlation time."""

    sigma_mm: float  # per axis, 1 sigma, flange position (base frame)
    sigma_rad: float  # per axis, 1 sigma, flange orientation
    smooth_fraction: float = 0.9  # the Gauss-Markov part's sigma over the whole (variances add)
    corr_time_s: float = 0.3  # correlation time of the smooth part

    def __post_init__(self) -> None:
        if not (self.sigma_mm > 0 and self.sigma_rad > 0 and 0 <= self.smooth_fraction <= 1
                and self.corr_time_s > 0):
            raise ValueError(
                f"arm prior out of range: sigma_mm={self.sigma_mm} (> 0), sigma_rad={self.sigma_rad} "
                f"(> 0), smooth_fraction={self.smooth_fraction} (0..1), "
                f"corr_time_s={self.corr_time_s} (> 0)")

    @classmethod
    def from_precision(
        cls, precision_mm: float, precision_rad: float | None = None, *,
        smooth_fraction: float = 0.9, corr_time_s: float = 0.3,
    ) -> ArmPrior:
        """Prior from datasheet figures read as 2 sigma of the 3-D error (so sigma = p / (2 sqrt 3)).

        Without a rotation figure, the rotation sigma is the position sigma over ``LEVER_MM``
        (300 mm, about one link of a portable arm): the wrist's position error spread over
        the last link is what tilts the flange.
        """
        s = float(precision_mm) / (2.0 * np.sqrt(3.0))
        r = s / LEVER_MM if precision_rad is None else float(precision_rad) / (2.0 * np.sqrt(3.0))
        return cls(s, r, float(smooth_fraction), float(corr_time_s))

    @classmethod
    def from_estimate(
        cls, sigma_mm: float, sigma_rad: float, *, smooth_fraction: float = 0.9,
        corr_time_s: float = 0.3,
    ) -> ArmPrior:
        """Prior from per-axis sigmas measured on the arm (the hand-eye views' noise estimate).

        The rotation sigma is kept at least the position sigma over ``LEVER_MM``: a handful of
        views determines it poorly (8 views of one random rig gave 0), and a prior tighter than
        the arm keeps the refinement from correcting what the arm did, where a looser one
        costs only some noise.
        """
        s = float(sigma_mm)
        return cls(s, max(float(sigma_rad), s / LEVER_MM), float(smooth_fraction), float(corr_time_s))

    def sigmas(self) -> np.ndarray:
        """Per-dof 1-sigma (6,): rotation x, y, z (rad), then translation x, y, z (mm)."""
        return np.array([self.sigma_rad] * 3 + [self.sigma_mm] * 3)


def prior_covariance(times: np.ndarray | None, prior: ArmPrior, F: int) -> np.ndarray:
    """Prior correlation (F, F) of each scaled error component between frames.

    Per axis the error is a Gauss-Markov process of sigma ``smooth_fraction`` times the whole
    (correlation exp(-|t_k - t_l| / corr_time_s)) plus an independent part carrying the rest
    of the variance (sigma ``sqrt(1 - smooth_fraction^2)`` times the whole); without times
    the frames are independent.
    """
    rho = prior.smooth_fraction
    if times is None or rho == 0.0:
        return np.eye(F)
    t = np.asarray(times, dtype=np.float64)
    phi = np.exp(-np.abs(t[:, None] - t[None, :]) / prior.corr_time_s)
    return rho * rho * phi + (1.0 - rho * rho) * np.eye(F)


def _prior_sparse(times: np.ndarray | None, prior: ArmPrior, F: int):
    """Square-root information of the same prior, sparse, on [e, s] (s: the smooth part).

    The Gauss-Markov part is Markov, so with it as extra unknowns the information is banded:
    what lets long scans be solved without a dense F x F matrix.
    """
    import scipy.sparse as sp

    rho = prior.smooth_fraction
    eye = sp.identity(6 * F, format="csr")
    if times is None or rho == 0.0:
        return eye, 6 * F
    t = np.asarray(times, dtype=np.float64)
    phi = np.exp(-np.diff(t) / prior.corr_time_s)
    # AR(1) rows on s: s_0 / rho, (s_k - phi s_{k-1}) / (rho sqrt(1 - phi^2))
    q = rho * np.sqrt(np.maximum(1.0 - phi * phi, 1e-12))
    main = sp.diags(np.repeat(np.concatenate([[1.0 / rho], 1.0 / q]), 6), 0, shape=(6 * F, 6 * F))
    lower = sp.diags(np.repeat(-phi / q, 6), -6, shape=(6 * F, 6 * F))
    Ls = (main + lower).tocsr()
    if rho == 1.0:
        return Ls, 6 * F  # e = s
    w = 1.0 / np.sqrt(1.0 - rho * rho)
    # white rows (e - s) / sqrt(1 - rho^2); unknowns ordered [e, s]
    return sp.vstack([sp.hstack([eye * w, -eye * w]),
                      sp.hstack([sp.csr_matrix((6 * F, 6 * F)), Ls])]).tocsr(), 12 * F


def prior_draws(times: np.ndarray | None, prior: ArmPrior, F: int, draws: int,
                rng: np.random.Generator) -> np.ndarray:
    """Draws (draws, F, 6) of the scaled pose errors from the prior itself (unit sigma per axis).

    The prior's process simulated directly, O(draws F): per axis an AR(1) (Gauss-Markov) part
    of sigma ``smooth_fraction`` over the frames' times plus a white part carrying the rest of
    the variance, the same model as :func:`prior_covariance` without an F x F matrix.
    """
    rho = prior.smooth_fraction
    white = rng.standard_normal((draws, F, 6))
    if times is None or rho == 0.0 or F == 0:
        return white
    t = np.asarray(times, dtype=np.float64)
    phi = np.exp(-np.diff(t) / prior.corr_time_s)
    q = np.sqrt(np.maximum(1.0 - phi * phi, 0.0))
    xi = rng.standard_normal((draws, F, 6))
    s = np.empty_like(xi)
    s[:, 0] = xi[:, 0]
    for k in range(1, F):  # a recursion over frames, vectorised over draws and axes
        s[:, k] = phi[k - 1] * s[:, k - 1] + q[k - 1] * xi[:, k]
    return rho * s + np.sqrt(1.0 - rho * rho) * white

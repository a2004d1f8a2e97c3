"""The MAP solve of every frame's pose error from the crossings' gaps.

``solve_errors``: one scalar per crossing against 6 unknowns per frame and the A-minus-B
offset, the prior of :mod:`crossline.scan.refine_prior`, robust (Huber) weights re-estimated
a few times; dense Cholesky on the seen frames up to ``DENSE_MAX_FRAMES`` frames, sparse LDL^T
(QDLDL) on the banded augmented form beyond. Split from ``crossline.scan.refine`` (issue 21.3),
which re-exports these names.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np

from crossline.robust import robust_sigma
from crossline.scan.refine_crossings import Crossings
from crossline.scan.refine_prior import ArmPrior, _prior_sparse, prior_covariance, prior_draws

__all__ = ["solve_errors"]

DENSE_MAX_FRAMES = 800  # up to here the normal equations are solved dense (6F unknowns)
MIN_GAP_SIGMA_MM = 1e-4  # the best a crossing's gap is ever taken to be known (0.1 µm)
MIN_DOF_SHARE = 0.1  # the noise scale's degrees of freedom: at least this share of the crossings
EXACT_TRACE_MAX = 1200  # up to this many unknowns the hat matrix's trace is exact
TRACE_PROBES = 16  # beyond, Hutchinson's estimate from this many probe vectors


def solve_errors(
    cr: Crossings,
    origins: np.ndarray,
    prior: ArmPrior,
    times: np.ndarray | None = None,
    *,
    huber: float = 2.0,
    reject: float = 5.0,
    max_iter: int = 6,
    dense: bool | None = None,
    draws: int = 0,
    seed: int = 0,
) -> tuple[np.ndarray, float, dict[str, Any]]:
    """MAP pose errors (F, 6) = (ω, t) per frame from the crossings, and the A-minus-B offset β.

    Unknowns are scaled by the prior sigmas. The noise of each crossing is its curve-fit
    prediction variance times one global scale, estimated robustly (MAD) from the residuals
    at each iteration, corrected for the unknowns the fit spends on them (the hat matrix's
    trace, :func:`_effective_parameters`); residuals beyond ``huber`` scaled sigmas get Huber weights, beyond
    ``reject`` none. ``dense`` (default: up to ``DENSE_MAX_FRAMES`` frames) solves the
    normal equations by dense Cholesky, otherwise sparse LDL^T on the banded augmented form.

    ``draws`` > 0 also gives ``info["posterior"]`` (draws, F, 6): the errors left after the
    solve, drawn from its posterior (perturb-and-MAP: the prior and the crossings' noise drawn,
    each draw one more solve with the factorised normal equations), in mm and rad like the
    estimate; a frame that no crossing sees is drawn from the prior given the seen ones.
    """
    import scipy.linalg as sla
    import scipy.sparse as sp

    F = len(origins)
    K = len(cr.gap)
    sig = prior.sigmas()
    info: dict[str, Any] = {"crossings": K}
    if K == 0:
        out = {**info, "iterations": 0, "used": 0, "rejected": 0}
        if draws > 0:  # nothing seen: the posterior is the prior
            out["posterior"] = (prior_draws(times, prior, F, draws, np.random.default_rng(seed))
                                * sig).astype(np.float32)
        return np.zeros((F, 6)), 0.0, out
    dense = F <= DENSE_MAX_FRAMES if dense is None else dense
    if dense:
        # only frames that some crossing sees are unknowns: the prior of the others is
        # marginalised out (a Gaussian's marginal is the sub-block of its covariance) and
        # their errors are predicted afterwards from the solved ones
        seen = np.zeros(F, bool)
        seen[cr.frame_a] = True
        seen[cr.frame_b] = True
        cov = prior_covariance(times, prior, F)
        obs = np.flatnonzero(seen)
        lam = sla.cho_solve(sla.cho_factor(cov[np.ix_(obs, obs)]), np.eye(len(obs)))
        col = np.full(F, -1)
        col[obs] = np.arange(len(obs))
        nu = 6 * len(obs)
        P = np.zeros((nu + 1, nu + 1))
        P[:nu, :nu] = np.kron(lam, np.eye(6))  # frame-major: unknown f * 6 + axis
        L = None
    else:
        col = np.arange(F)
        L, nu = _prior_sparse(times, prior, F)
        P = sp.block_diag([(L.T @ L), sp.csr_matrix((1, 1))]).tocsc()
        lam = cov = obs = seen = None
    beta_info = 1e-6  # the A-minus-B offset is nearly free (a 1000-sigma prior)
    # Jacobian of the gap: n·(ω_f × (x − o_f) + t_f) − n·(ω_g × (x − o_g) + t_g); on
    # same-frame crossings the two cancel and only beta is seen
    ja = np.hstack([np.cross(cr.x - origins[cr.frame_a], cr.n), cr.n]) * sig
    jb = np.hstack([np.cross(cr.x - origins[cr.frame_b], cr.n), cr.n]) * sig
    rows = np.repeat(np.arange(K), 6)
    J = sp.csr_matrix(
        (np.concatenate([ja.ravel(), -jb.ravel(), np.ones(K)]),
         (np.concatenate([rows, rows, np.arange(K)]),
          np.concatenate([(col[cr.frame_a][:, None] * 6 + np.arange(6)).ravel(),
                          (col[cr.frame_b][:, None] * 6 + np.arange(6)).ravel(), np.full(K, nu)]))),
        shape=(K, nu + 1),
    )
    s0 = np.maximum(cr.sigma, np.median(cr.sigma) * 0.5)
    # no crossing is known better than MIN_GAP_SIGMA_MM: on perfect data the scale would go to
    # zero and the data outweigh the prior by so much that the normal equations lose the
    # unobservable directions to rounding
    floor = MIN_GAP_SIGMA_MM / float(np.median(s0))
    w = np.ones(K)
    scale = max(robust_sigma(cr.gap) / float(np.median(s0)), floor)
    z = np.zeros(nu + 1)
    iterations = 0
    for iterations in range(1, max_iter + 1):  # noqa: B007 (the count is reported)
        wi = w / (scale * s0) ** 2
        solve = _normal_equations(J, wi, P, nu, beta_info, dense)
        z_new = solve(J.T @ (wi * cr.gap))
        res = (cr.gap - J @ z_new) / s0
        # the residuals of a fit with p_eff effective parameters are smaller than the noise by
        # sqrt((n - p_eff) / n): with few crossings a frame and a loose prior p_eff nears n,
        # and a scale taken from them as they are shrinks, weighs the data up and overfits
        # (random rig 9's quick ball with the hand-eye's prior: size -37.8 um, -22.5 with this)
        p_eff = _effective_parameters(J, wi, solve)
        n_in = float(np.count_nonzero(w > 0))
        dof = max(n_in - p_eff, MIN_DOF_SHARE * n_in, 1.0)
        new_scale = max(robust_sigma(res[w > 0], about=0.0) * np.sqrt(n_in / dof), floor)
        u = np.abs(res) / new_scale
        w_new = np.where(u <= huber, 1.0, np.where(u <= reject, huber / np.maximum(u, 1e-300), 0.0))
        # converged: the unknowns moved by less than a twentieth of their prior sigma
        done = float(np.max(np.abs(z_new - z))) < 0.05 and np.array_equal(w_new > 0, w > 0)
        z, w, scale = z_new, w_new, new_scale
        if done:
            break
    if dense:
        a = np.zeros((F, 6))
        a[obs] = z[:nu].reshape(-1, 6)
        # the unseen frames: their conditional mean given the seen ones, C_uo C_oo^-1 a_o
        a[~seen] = cov[np.ix_(~seen, obs)] @ (lam @ a[obs])
    else:
        a = z[: 6 * F].reshape(F, 6)
    e = a * sig
    if draws > 0:
        wi = w / (scale * s0) ** 2
        solve = _normal_equations(J, wi, P, nu, beta_info, dense)
        post = _posterior(J, wi, solve, dense, lam, cov, obs, seen, L, nu, beta_info, F, draws,
                          np.random.default_rng(seed))
        info["posterior"] = post * sig.astype(np.float32)
    res_mm = cr.gap - J @ z
    used = w > 0
    info.update(
        iterations=iterations, used=int(used.sum()), rejected=int((~used).sum()),
        solver="dense" if dense else "sparse",
        noise_scale=scale, effective_parameters=p_eff,
        gap_rms_before_mm=float(np.sqrt(np.mean((cr.gap[used] - z[nu]) ** 2))),
        gap_rms_after_mm=float(np.sqrt(np.mean(res_mm[used] ** 2))),
    )
    return e, float(z[nu]), info


def _effective_parameters(J, wi: np.ndarray, solve) -> float:
    """tr(H^-1 J^T W J), the trace of the fit's hat matrix: how many of the unknowns the
    crossings determine (the rest is the prior's), with ``solve`` the factorised H.

    Exact up to ``EXACT_TRACE_MAX`` unknowns; beyond, Hutchinson's estimate from
    ``TRACE_PROBES`` Rademacher vectors (fixed seed: the same run gives the same figure), whose
    relative error is about sqrt(2 / (probes p_eff)) for a matrix with eigenvalues in [0, 1].
    """
    n = J.shape[1]
    if n <= EXACT_TRACE_MAX:
        JtWJ = (J.T.multiply(wi[None, :]).tocsr() @ J).toarray()
        return float(np.trace(np.asarray(solve(JtWJ))))
    Z = np.random.default_rng(0).choice([-1.0, 1.0], size=(n, TRACE_PROBES))
    AZ = np.asarray(J.T @ (wi[:, None] * (J @ Z)))
    return float(np.mean(np.sum(np.asarray(solve(Z)) * AZ, axis=0)))


def _normal_equations(J, wi, P, nu: int, beta_info: float, dense: bool):
    """The solve of the weighted normal equations H = J^T W J + P (+ the offset's prior),
    factorised once: dense Cholesky, or sparse LDL^T (QDLDL, AMD ordering) of the banded
    augmented form.

    H is symmetric positive definite, so a symmetric factor is the right one. SuperLU (scipy's
    ``splu``, used before) treats it as a general matrix: on a 50 000-frame scan whose arm
    path crosses itself (587 353 unknowns, 15 383 crossings) its L + U held 82 M entries, took
    21 s a factorisation and lifted the fuse stage's peak memory by 3.4 GB; QDLDL's L takes
    0.6 s and 0.25 GB, the solutions agreeing to 1e-12 of their size.
    """
    import scipy.linalg as sla
    import scipy.sparse as sp

    JtWJ = J.T.multiply(wi[None, :]).tocsr() @ J
    if dense:
        H = JtWJ.toarray() + P
        H[nu, nu] += beta_info
        return partial(sla.cho_solve, sla.cho_factor(H, check_finite=False), check_finite=False)
    import qdldl

    n = JtWJ.shape[0]
    H = JtWJ + P + sp.csc_matrix(([beta_info], ([nu], [nu])), shape=(n, n))
    factor = qdldl.Solver(sp.triu(H, format="csc"), upper=True)

    def solve(b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, dtype=np.float64)
        if b.ndim == 1:
            return factor.solve(b)
        return np.column_stack([factor.solve(np.ascontiguousarray(b[:, i])) for i in range(b.shape[1])])

    return solve


POSTERIOR_CHUNK = 16  # draws solved at once at most
POSTERIOR_CHUNK_VALUES = 2_000_000  # and no more random numbers per chunk than this (16 MB)


def _posterior(J, wi, solve, dense, lam, cov, obs, seen, L, nu, beta_info, F, draws, rng
               ) -> np.ndarray:
    """Scaled posterior draws (draws, F, 6), float32, of the errors about the MAP estimate.

    Perturb-and-MAP: z = H^-1 (J^T W^1/2 xi + P^1/2 eta) has covariance H^-1 (J^T W J + P) H^-1
    = H^-1, the posterior's, for H = J^T W J + P the normal equations of the solve.
    """
    K = J.shape[0]
    JT, sw = J.T, np.sqrt(wi)[:, None]  # J^T W^1/2 xi as J^T (W^1/2 xi): no copy of J
    out = np.zeros((draws, F, 6), np.float32)
    Lc = np.linalg.cholesky(cov[np.ix_(obs, obs)]) if dense else None
    # a long scan has millions of crossings: its right-hand sides are drawn a few at a time
    chunk = max(1, min(POSTERIOR_CHUNK, POSTERIOR_CHUNK_VALUES // max(K, nu + 1, 1)))
    for d0 in range(0, draws, chunk):
        n = min(chunk, draws - d0)
        G = np.asarray(JT @ (sw * rng.standard_normal((K, n))))
        if dense:
            n_o = len(obs)
            # a prior draw a ~ N(0, C_oo) per axis gives the information's square root as P a
            A = lam @ (Lc @ rng.standard_normal((n_o, 6 * n)))
            G[:nu] += A.reshape(n_o, n, 6).transpose(0, 2, 1).reshape(nu, n)
        else:
            G[:nu] += np.asarray(L.T @ rng.standard_normal((L.shape[0], n)))
        G[nu] += np.sqrt(beta_info) * rng.standard_normal(n)
        Z = np.asarray(solve(G))[:nu]
        if dense:
            out[d0:d0 + n, obs] = Z.reshape(len(obs), 6, n).transpose(2, 0, 1)
        else:
            out[d0:d0 + n] = Z[: 6 * F].reshape(F, 6, n).transpose(2, 0, 1)
    un = np.flatnonzero(~seen) if dense else ()
    if len(un):
        # the unseen frames given the seen ones: mean C_uo C_oo^-1 a_o, covariance its Schur
        # complement C_uu - C_uo C_oo^-1 C_ou (per axis: the axes share the correlation)
        C_uo = cov[np.ix_(un, obs)]
        S = cov[np.ix_(un, un)] - C_uo @ lam @ C_uo.T
        w_s, V = np.linalg.eigh(0.5 * (S + S.T))
        root = V * np.sqrt(np.maximum(w_s, 0.0))
        mean = np.einsum("uo,doa->dua", C_uo @ lam, out[:, obs])
        out[:, un] = mean + np.einsum("uk,dka->dua", root, rng.standard_normal((draws, len(un), 6)))
    return out

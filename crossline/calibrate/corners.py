"""Sub-pixel chessboard corners: a blurred X-junction fitted to the pixels around each corner.

OpenCV's corner refiners (``findChessboardCornersSB``, ``cornerSubPix``) leave rendered
chessboard corners several times further from the true projected corners than the circle
grid's refined centres are from theirs; this fit removes most of that error
(``python benchmarks/bench_corners.py`` prints each refiner's RMS error in px, full-sensor
pixel coordinates, against the simulator's true corners on both presets).
Here each corner is refined by fitting, by weighted least squares over the
pixels of a window around it, the image of an ideal X-junction: two straight edges through
the corner, the squares' two grey levels, a Gaussian blur, and shading that varies linearly
across the window::

    I(x) = m0 + m·(x - p) + (c0 + c·(x - p)) · erf(d1 / (√2 σ)) · erf(d2 / (√2 σ))

with ``d1``, ``d2`` the signed distances of pixel ``x`` to the two edges through ``p``.

Why the centre is unbiased although the model is not exact: an X-junction looks the same turned
by 180° about its corner, blur and pixel integration keep that symmetry, and so does the
window weight, centred on the estimate. What the model misses (edges not at right angles,
unequal blur across and along the sensor, a trace of lens curvature) is point-symmetric about
the corner and leaves the corner a stationary point of the fit; the one effect that is not,
shading across the window, is part of the model. Perspective keeps edges straight, and a
corner, unlike a circle's centroid, has no perspective bias.

The window is a parallelogram spanned by the local grid directions, ``WINDOW_FRACTION`` of
the way to the neighbouring corners (so it holds this corner's two edges and nothing else),
at most ``MAX_HALF_PX`` across half, with a raised-cosine taper over its outer half.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

from crossline.board import Board

__all__ = ["MAX_HALF_PX", "WINDOW_FRACTION", "refine_chessboard_corners"]

WINDOW_FRACTION = 0.35  # window half-size, as a fraction of the spacing of neighbouring corners
MAX_HALF_PX = 20.0  # ... and at most this many pixels (the edges' first pixels hold the information)
MIN_HALF_PX = 4.0  # fewer pixels than this cannot hold a blurred edge
_NPAR = 11  # px, py, alpha1, alpha2, log sigma, m0, mx, my, c0, cx, cy


def _local_axes(points: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Image vectors (N, 2) from each corner to its next along the board's x and y axes."""
    g = points.reshape(board.rows, board.cols, 2)
    e1 = np.gradient(g, axis=1)  # central differences inside, one-sided on the border
    e2 = np.gradient(g, axis=0)
    return e1.reshape(-1, 2), e2.reshape(-1, 2)


def _taper(t: np.ndarray) -> np.ndarray:
    """1 for |t| <= 1/2, a raised cosine down to 0 at |t| = 1, 0 beyond."""
    a = np.abs(t)
    w = 0.5 * (1.0 + np.cos(np.pi * np.clip(2.0 * a - 1.0, 0.0, 1.0)))
    return np.where(a < 1.0, w, 0.0)


def _window(image: np.ndarray, p: np.ndarray, e1: np.ndarray, e2: np.ndarray, h: np.ndarray):
    """Pixels (N, P) around each corner: x, y, intensity and taper weight (0 for padding).

    Only pixels of non-zero weight are kept, packed to the front of each corner's row.
    """
    H, W = image.shape
    ext = h[:, None] * (np.abs(e1) + np.abs(e2))  # (N, 2) half-extent of the parallelogram
    R = int(np.ceil(ext.max())) + 1
    oy, ox = np.mgrid[-R : R + 1, -R : R + 1]
    c = np.rint(p).astype(np.int64)
    xs = c[:, 0, None] + ox.ravel()[None, :]
    ys = c[:, 1, None] + oy.ravel()[None, :]
    inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
    # local grid coordinates (a, b): x - p = a e1 + b e2
    Minv = np.linalg.inv(np.stack([e1, e2], axis=-1))  # columns e1, e2
    dx, dy = xs - p[:, 0, None], ys - p[:, 1, None]
    a = Minv[:, 0, 0, None] * dx + Minv[:, 0, 1, None] * dy
    b = Minv[:, 1, 0, None] * dx + Minv[:, 1, 1, None] * dy
    w = _taper(a / h[:, None]) * _taper(b / h[:, None]) * inside
    # pack the pixels of non-zero weight (a parallelogram: about half its bounding box)
    keep = w > 0
    n = keep.sum(axis=1)
    order = np.argsort(~keep, axis=1, kind="stable")[:, : max(int(n.max()), 1)]
    take = lambda arr: np.take_along_axis(arr, order, axis=1)  # noqa: E731
    wk = take(w) * (np.arange(order.shape[1])[None, :] < n[:, None])
    xk, yk = take(xs), take(ys)
    val = image[np.clip(yk, 0, H - 1), np.clip(xk, 0, W - 1)].astype(np.float64)
    return xk.astype(np.float64), yk.astype(np.float64), val, wk


def _model(q: np.ndarray, x: np.ndarray, y: np.ndarray, L: np.ndarray, jac: bool):
    """The X-junction model (N, P) at pixels x, y for parameters q (N, 11), and its Jacobian."""
    px, py, a1, a2, ls, m0, mx, my, c0, cx, cy = (q[:, k, None] for k in range(_NPAR))
    s = np.exp(ls)
    dx, dy = x - px, y - py
    ux, uy = dx / L[:, None], dy / L[:, None]
    n1x, n1y, n2x, n2y = np.cos(a1), np.sin(a1), np.cos(a2), np.sin(a2)
    d1 = n1x * dx + n1y * dy
    d2 = n2x * dx + n2y * dy
    k = 1.0 / (np.sqrt(2.0) * s)
    E1, E2 = erf(d1 * k), erf(d2 * k)
    C = c0 + cx * ux + cy * uy
    EE = E1 * E2
    f = m0 + mx * ux + my * uy + C * EE
    if not jac:
        return f, None
    g = np.sqrt(2.0 / np.pi) / s
    # a fit that fails (a corner under a laser stripe) may run its blur to ~0: exp(-inf) = 0
    # is right there, and the corner is flagged by the checks on the result
    with np.errstate(over="ignore"):
        g1 = g * np.exp(-0.5 * (d1 / s) ** 2)  # dE1/dd1
        g2 = g * np.exp(-0.5 * (d2 / s) ** 2)
    J = np.empty((*f.shape, _NPAR))
    cg1, cg2 = C * g1 * E2, C * E1 * g2
    J[..., 0] = -(mx + cx * EE) / L[:, None] - cg1 * n1x - cg2 * n2x
    J[..., 1] = -(my + cy * EE) / L[:, None] - cg1 * n1y - cg2 * n2y
    J[..., 2] = cg1 * (-n1y * dx + n1x * dy)
    J[..., 3] = cg2 * (-n2y * dx + n2x * dy)
    J[..., 4] = -(cg1 * d1 + cg2 * d2)  # d/d(log sigma) of erf(d / (sqrt 2 sigma)) is -g d
    J[..., 5] = 1.0
    J[..., 6] = ux
    J[..., 7] = uy
    J[..., 8] = EE
    J[..., 9] = ux * EE
    J[..., 10] = uy * EE
    return f, J


def _fit(q: np.ndarray, x, y, val, w, L, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on every corner at once; returns parameters and weighted RSS (N,)."""
    f, J = _model(q, x, y, L, True)
    r = f - val
    cost = np.sum(w * r * r, axis=1)
    lam = np.full(len(q), 1e-3)
    eye = np.eye(_NPAR)
    active = np.ones(len(q), bool)
    for _ in range(iterations):
        Jw = J * w[..., None]
        A = np.matmul(Jw.transpose(0, 2, 1), J)
        gvec = np.einsum("npi,np->ni", Jw, r)
        D = np.einsum("nii->ni", A)[:, :, None] * eye
        try:
            step = -np.linalg.solve(A + lam[:, None, None] * D + 1e-12 * eye, gvec[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        qn = q + step
        fn, Jn = _model(qn, x, y, L, True)
        rn = fn - val
        cn = np.sum(w * rn * rn, axis=1)
        ok = active & np.isfinite(cn) & (cn <= cost)
        q = np.where(ok[:, None], qn, q)
        J = np.where(ok[:, None, None], Jn, J)
        r = np.where(ok[:, None], rn, r)
        cost = np.where(ok, cn, cost)
        lam = np.where(ok, lam / 3.0, lam * 4.0)
        # a corner is done once an accepted step moves it by < 1e-5 px, or LM gives up on it
        active &= ~(ok & (np.abs(step[:, :2]).max(axis=1) < 1e-5)) & (lam < 1e8)
        if not active.any():
            break
    return q, cost


def refine_chessboard_corners(
    image: np.ndarray, board: Board, points: np.ndarray, *, passes: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Refine chessboard corners (N, 2) in board order on a grey image of any bit depth.

    Returns the refined corners (N, 2) and a flag per corner (N,) that is False where the fit
    did not hold (no X-junction of the board's contrast in the window, a corner that ran off
    its window, a blur outside 0.2 px to half the window): there the input corner is
    returned unchanged.
    """
    if board.pattern != "chessboard":
        raise ValueError(f"refine_chessboard_corners needs a chessboard, got a {board.pattern} grid")
    img = np.asarray(image)
    p0 = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    e1, e2 = _local_axes(p0, board)
    spacing = np.minimum(np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1))
    h = np.minimum(WINDOW_FRACTION, MAX_HALF_PX / np.maximum(np.linalg.norm(e1, axis=1),
                                                             np.linalg.norm(e2, axis=1)))
    L = h * spacing  # the window's half-size in px along its shorter axis
    usable = L >= MIN_HALF_PX
    # edges through the corner along e1 and e2: their normals
    a1 = np.arctan2(e1[:, 0], -e1[:, 1])
    a2 = np.arctan2(e2[:, 0], -e2[:, 1])
    x, y, val, w = _window(img, p0, e1, e2, h)
    sw = np.maximum(w.sum(axis=1), 1e-12)
    m0 = np.sum(w * val, axis=1) / sw
    d1 = np.cos(a1)[:, None] * (x - p0[:, :1]) + np.sin(a1)[:, None] * (y - p0[:, 1:])
    d2 = np.cos(a2)[:, None] * (x - p0[:, :1]) + np.sin(a2)[:, None] * (y - p0[:, 1:])
    c0 = np.sum(w * (val - m0[:, None]) * np.sign(d1) * np.sign(d2), axis=1) / sw
    zeros = np.zeros(len(p0))
    q = np.column_stack([p0, a1, a2, zeros, m0, zeros, zeros, c0, zeros, zeros])
    for k in range(passes):  # fit, then re-centre the window on the estimate and fit again
        if k:
            x, y, val, w = _window(img, q[:, :2], e1, e2, h)
        q, cost = _fit(q, x, y, val, w, L)
    sigma = np.exp(q[:, 4])
    resid = np.sqrt(cost / np.maximum(w.sum(axis=1), 1e-12))
    ok = (
        usable
        & np.all(np.isfinite(q), axis=1)
        & (np.linalg.norm(q[:, :2] - p0, axis=1) < 0.5 * L)
        & (sigma > 0.2)
        & (sigma < 0.5 * L)
        # an X-junction of the board's contrast, well above the noise: a corner painted over
        # or shadowed fits too, with no contrast
        & (np.abs(q[:, 8]) > np.maximum(5.0 * resid, 0.2 * np.median(np.abs(q[:, 8]))))
    )
    out = np.where(ok[:, None], q[:, :2], p0)
    return out, ok

"""The stripe-centre bias of a sheet of finite thickness on a curved surface, and its correction.

A laser sheet is not a plane but a Gaussian slab: its irradiance falls as
``exp(-f^2 / 2 sigma_f^2)`` with ``f`` the distance from its centre plane (``sigma_f`` is half
the 1/e^2 half-thickness). A pixel sees the surface point its ray meets, so the image profile
across the stripe is that Gaussian of ``f`` read along the image. On a flat surface ``f`` is
linear in the image coordinate ``tau`` across the stripe: the profile is symmetric and every
extractor finds the pixel whose ray meets the centre plane, where triangulation puts the point.
On a curved surface ``f(tau) = f1 tau + f2 tau^2``: the profile is skewed and an extractor's
centre moves off ``f = 0`` by ``K (f2 / f1)`` px, ``K`` about ``k sigma_u^2`` with ``sigma_u =
sigma_f / f1`` the profile's width; ``k`` is the extractor's response to skew (about -3 for an
intensity centroid, -5.5 for the speckle-weighted Gaussian fit, whose weights favour the
tails; a mode would not move). The centre, triangulated with the centre plane, lands off the
surface: a sphere of radius R is measured small by about ``sigma_f^2 / R`` times the
extractor's factor (docs/method.md, "Stripe centres corrected for the sheet's thickness", gives
a case measured on a random rig).

The correction, at the cause: :func:`surface_shape` (or :class:`CellSums` for a long scan)
fits the local shape of the scanned surface (normal and second fundamental form, from the
scan's own points over a few mm); :func:`sheet_sigma` finds each laser's sheet sigma and the
camera's blur from the widths the extractor reports; :func:`skew_response` measures ``k``
against the sheet's sigma by running the scan's own extractor (same parameters) on synthetic
skewed, blurred profiles at the scan's levels and noise; :func:`centre_shift` computes each
centre's ``f(tau)`` along the profile the extractor took by intersecting the rays of the
neighbouring pixels with that shape, and adds Lambert's term (the cosine of incidence changes
across the band on a curved surface: a Gaussian times ``1 + s tau`` peaks ``s sigma^2``
further on), which needs the laser's emitter: no calibration here measures it, and the caller
takes the foot of the perpendicular from the camera centre to the plane. Nothing here knows
the renderer: the sheet's thickness enters through the measured widths, the shape through the
measured points.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from crossline.robust import robust_sigma

__all__ = [
    "CellSums",
    "SurfaceShape",
    "cell_keys",
    "centre_shift",
    "sheet_sigma",
    "skew_response",
    "stripe_gradient",
    "surface_shape",
]

SKEW_BETA = 0.02  # skew of the synthetic profiles: f = t + beta t^2 / sigma (linear response)
SYNTH_COLUMNS = 384  # columns per synthetic frame
BLOCK = 8192  # centres (or points) handled at a time: bounded memory on long scans
CELL_MM = 0.5  # the grid of the surface's shape: a sheet's band is 0.1-1 mm wide
MAX_SIGMA_PX = 15.0  # the widest sheet profile the response is measured for (px, sigma)
FWHM = 2.0 * np.sqrt(2.0 * np.log(2.0))
X_SPREAD = 25.0  # sheet_sigma: a centre whose 1/|grad f|^2 is this many times its laser's median is left out


def _synthetic_frame(sigma: float, beta: float, peak: float, background: float, relative_noise: float,
                     noise_dn: float, data_max: float, dtype: np.dtype, rng: np.random.Generator,
                     blur: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A frame (height, width) with one near-horizontal stripe, a sheet of ``sigma`` px skewed
    by ``beta`` and blurred by ``blur`` px, and the true centre row (f = 0) of each column."""
    from scipy.ndimage import gaussian_filter1d

    sub = 8  # samples per pixel: the blur, then the pixel's integration
    H = int(np.ceil(12.0 * np.hypot(sigma, blur))) + 24
    col = np.arange(SYNTH_COLUMNS)
    centre = H / 2.0 + 0.37 * col / SYNTH_COLUMNS  # a slow slope: every subpixel phase
    t = (np.arange(H * sub)[:, None] + 0.5) / sub - 0.5 - centre[None, :]
    f = t + beta * t * t / sigma
    E = np.where(np.abs(t) < 6.0 * sigma, np.exp(-0.5 * (f / sigma) ** 2), 0.0)
    if blur > 0:
        E = gaussian_filter1d(E, blur * sub, axis=0, mode="constant")
    E = E.reshape(H, sub, SYNTH_COLUMNS).mean(1)
    img = background + peak * E * (1.0 + relative_noise * rng.standard_normal(E.shape))
    img += noise_dn * rng.standard_normal(E.shape)
    return np.clip(np.round(img), 0, data_max).astype(dtype), centre


def skew_response(
    extract: Callable[[np.ndarray], dict[str, np.ndarray]],
    sigmas: np.ndarray,
    *,
    blur: float,
    peak: float,
    background: float,
    relative_noise: float,
    noise_dn: float,
    data_max: float,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """The extractor's centre shift per unit skew of the sheet, against the sheet's sigma.

    ``extract`` takes a frame transposed, (width, height), and returns its centres (``u``:
    column, ``v``: row); ``sigmas`` are the sheet sigmas (px, across the stripe) of the scan's
    centres, to cover; ``blur`` the camera's (px). Profiles are made as the scan's are: a
    Gaussian sheet skewed as ``f(tau) = tau + beta tau^2 / sigma``, blurred, integrated over
    pixels, at the scan's peak, background and noise. Returns (sigma, k) sorted by sigma: a
    sheet of sigma ``s`` with ``f(tau) = f1 tau + f2 tau^2`` puts the centre at ``k s^2 f2 /
    f1`` px along ``tau`` (-3 for a centroid, whatever the blur).
    """
    w = np.asarray(sigmas, dtype=np.float64)
    # a centre whose stripe runs nearly along its own sheet (|grad f| ~ 0) has no profile to
    # skew: the table covers the widths a stripe can have
    w = w[np.isfinite(w) & (w > 0) & (w <= MAX_SIGMA_PX)]
    if w.size == 0:
        return np.empty(0), np.empty(0)
    sig = np.unique(np.round(np.quantile(w, [0.005, 0.1, 0.3, 0.5, 0.7, 0.9, 0.995]), 2))
    sig = sig[sig >= 0.3]
    dtype = np.dtype(np.uint8 if data_max <= 255 else np.uint16)
    rng = np.random.default_rng(seed)
    out_s, out_k = [], []
    blur = float(blur) if np.isfinite(blur) else 0.0
    for sg in sig:
        shift = []
        for beta in (SKEW_BETA, -SKEW_BETA):
            img, centre = _synthetic_frame(float(sg), beta, peak, background, relative_noise, noise_dn,
                                           data_max, dtype, rng, blur)
            c = extract(np.ascontiguousarray(img.T))
            u = np.round(np.asarray(c["u"])).astype(np.int64)
            ok = (u >= 0) & (u < SYNTH_COLUMNS)
            if ok.sum() < SYNTH_COLUMNS // 4:
                break
            shift.append(float(np.median(np.asarray(c["v"])[ok] - centre[u[ok]])))
        if len(shift) == 2:
            # f2 / f1 = beta / sigma: k = shift / (sigma^2 f2 / f1) = shift / (beta sigma)
            out_k.append((shift[0] - shift[1]) / (2.0 * SKEW_BETA * sg))
            out_s.append(float(sg))
    return np.asarray(out_s), np.asarray(out_k)


_BITS = 21  # per axis of a cell key: +-2^20 cells of 0.25 mm is +-262 m around the base
_HALF = 1 << (_BITS - 1)


def cell_keys(points: np.ndarray, cell_mm: float) -> np.ndarray:
    """One int64 key per point: its cell of a grid of ``cell_mm`` fixed in the base frame."""
    k = np.floor(np.asarray(points, dtype=np.float64) / cell_mm).astype(np.int64) + _HALF
    np.clip(k, 0, (1 << _BITS) - 1, out=k)
    return (k[:, 0] << (2 * _BITS)) | (k[:, 1] << _BITS) | k[:, 2]


class CellSums:
    """Points summed per cell, a batch at a time: the scan's shape without holding its points."""

    def __init__(self, cell_mm: float = CELL_MM, batch: int = 4_000_000):
        self.cell_mm = cell_mm
        self.keys = np.empty(0, np.int64)
        self.sums = np.empty((0, 3))
        self.counts = np.empty(0, np.int64)
        self._pending: list[np.ndarray] = []
        self._n = 0
        self._batch = batch

    def add(self, points: np.ndarray) -> None:
        """Add points (N, 3) in the base frame."""
        self._pending.append(np.asarray(points, dtype=np.float64))
        self._n += len(points)
        if self._n >= self._batch:
            self._merge()

    def _merge(self) -> None:
        if not self._pending:
            return
        p = np.concatenate(self._pending)
        self._pending, self._n = [], 0
        k = np.concatenate([self.keys, cell_keys(p, self.cell_mm)])
        keys, inv = np.unique(k, return_inverse=True)
        sums = np.stack([np.bincount(inv, weights=np.concatenate([self.sums[:, i], p[:, i]]),
                                     minlength=len(keys)) for i in range(3)], 1)
        w = np.concatenate([self.counts, np.ones(len(p), np.int64)])
        counts = np.bincount(inv, weights=w, minlength=len(keys)).astype(np.int64)
        self.keys, self.sums, self.counts = keys, sums, counts

    def shape(self, **kw: Any) -> SurfaceShape:
        """The shape of the points added (:func:`surface_shape`), each cell fitted when asked."""
        self._merge()
        return SurfaceShape(self.cell_mm, self.keys, self.sums / np.maximum(self.counts, 1)[:, None],
                            self.counts, **kw)


class SurfaceShape:
    """The local shape of a scanned surface, per cell of a grid over it (base frame).

    A cell's shape is fitted when first asked for (:meth:`ensure`): a long scan's stage needs
    it only where the sheet is thick enough for the correction to matter.
    """

    def __init__(self, cell_mm: float, keys: np.ndarray, centroids: np.ndarray, counts: np.ndarray,
                 radius_mm: float = 2.5, neighbours: int = 48, min_cells: int = 12):
        self.cell_mm = cell_mm
        self.keys = keys  # (M,) sorted cell keys (:func:`cell_keys`)
        self._cen = centroids
        self._cnt = counts
        self._radius, self._k, self._min = radius_mm, neighbours, min_cells
        M = len(keys)
        self._tree = cKDTree(centroids) if M else None
        self.normal = np.zeros((M, 3))  # unit normals
        self.e1 = np.zeros((M, 3))  # tangent basis
        self.e2 = np.zeros((M, 3))
        self.second = np.zeros((M, 3))  # second fundamental form (s11, s12, s22), 1/mm, along normal
        self.ok = np.zeros(M, dtype=bool)  # enough neighbours to tell the shape
        self._done = np.zeros(M, dtype=bool)

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """Index into the cells of each point (-1 where its cell holds no shape)."""
        key = cell_keys(points, self.cell_mm)
        if len(self.keys) == 0:
            return np.full(len(key), -1)
        i = np.clip(np.searchsorted(self.keys, key), 0, len(self.keys) - 1)
        return np.where(self.keys[i] == key, i, -1)

    @property
    def fitted(self) -> int:
        """Cells whose shape has been fitted so far."""
        return int(self._done.sum())

    def curvature(self, cells: np.ndarray | None = None) -> np.ndarray:
        """The larger principal curvature (absolute, 1/mm) of each cell, or of ``cells``
        (indices); 0 where not fitted."""
        s = self.second if cells is None else self.second[cells]
        return np.abs(0.5 * (s[:, 0] + s[:, 2])) + np.sqrt(0.25 * (s[:, 0] - s[:, 2]) ** 2 + s[:, 1] ** 2)

    def ensure(self, cells: np.ndarray | None = None) -> None:
        """Fit the shape of ``cells`` (indices; None: all) where not yet fitted."""
        todo = np.arange(len(self.keys)) if cells is None else np.unique(np.asarray(cells, np.int64))
        todo = todo[(todo >= 0) & ~self._done[todo]] if todo.size else todo
        for a in range(0, todo.size, BLOCK):
            self._fit(todo[a:a + BLOCK])

    def _fit(self, idx: np.ndarray) -> None:
        cen, cnt, M = self._cen, self._cnt, len(self.keys)
        radius_mm = self._radius
        K = min(self._k, M)
        a, b = 0, idx.size
        normal, e1, e2, second, ok = (np.zeros((b, 3)), np.zeros((b, 3)), np.zeros((b, 3)),
                                      np.zeros((b, 3)), np.zeros(b, dtype=bool))
        tree = self._tree
        q = cen[idx]
        d, j = tree.query(q, k=K, distance_upper_bound=radius_mm)
        d, j = np.atleast_2d(d), np.atleast_2d(j)
        valid = j < M
        jj = np.where(valid, j, 0)
        Q = cen[jj]  # (B, K, 3)
        wt = np.where(valid, cnt[jj] * np.exp(-0.5 * (d / (0.5 * radius_mm)) ** 2), 0.0)
        sw = wt.sum(1)
        mean = np.einsum("bk,bki->bi", wt, Q) / np.maximum(sw, 1e-300)[:, None]
        D = Q - mean[:, None, :]
        # batched matrix products (BLAS), not a three-operand einsum
        C = np.matmul((D * wt[:, :, None]).transpose(0, 2, 1), D) / np.maximum(sw, 1e-300)[:, None, None]
        ev, V = np.linalg.eigh(C)  # ascending: normal = smallest
        n0, t2, t1 = V[:, :, 0], V[:, :, 1], V[:, :, 2]
        R = Q - q[:, None, :]
        x = np.einsum("bki,bi->bk", R, t1)
        y = np.einsum("bki,bi->bk", R, t2)
        h = np.einsum("bki,bi->bk", R, n0)
        one = np.ones_like(x)
        full = np.stack([x * x, x * y, y * y, x, y, one], -1)
        umb = np.stack([x * x + y * y, x, y, one], -1)
        coef_f = _weighted_lstsq(full, h, wt)
        coef_u = _weighted_lstsq(umb, h, wt)
        # the minor tangent spread over the major: below 0.15 the neighbours are one line
        two_d = ev[:, 1] > (0.15**2) * ev[:, 2]
        s11 = np.where(two_d, 2 * coef_f[:, 0], 2 * coef_u[:, 0])
        s12 = np.where(two_d, coef_f[:, 1], 0.0)
        s22 = np.where(two_d, 2 * coef_f[:, 2], 2 * coef_u[:, 0])
        gx = np.where(two_d, coef_f[:, 3], coef_u[:, 1])
        gy = np.where(two_d, coef_f[:, 4], coef_u[:, 2])
        nn = n0 - gx[:, None] * t1 - gy[:, None] * t2  # the fit's tilt of the tangent plane
        nn /= np.linalg.norm(nn, axis=1, keepdims=True)
        normal[a:b] = nn
        # re-orthogonalise the tangent basis on the tilted normal (second order: kept as is)
        u1 = t1 - np.einsum("bi,bi->b", t1, nn)[:, None] * nn
        u1 /= np.linalg.norm(u1, axis=1, keepdims=True)
        e1[a:b] = u1
        e2[a:b] = np.cross(nn, u1)
        second[a:b] = np.stack([s11, s12, s22], 1)
        ok[a:b] = (valid.sum(1) >= self._min) & np.isfinite(second[a:b]).all(1)
        self.normal[idx], self.e1[idx], self.e2[idx], self.second[idx] = normal, e1, e2, second
        self.ok[idx] = ok
        self._done[idx] = True


def surface_shape(points: np.ndarray, *, cell_mm: float = CELL_MM, radius_mm: float = 2.5,
                  neighbours: int = 48, min_cells: int = 12) -> SurfaceShape:
    """Normal and second fundamental form of the surface through ``points`` (N, 3), per cell.

    The points are averaged per cell of ``cell_mm``; around each cell a weighted quadric
    ``h = a x^2 + b x y + c y^2 + d x + e y + g`` (``x, y`` along the cell's principal
    directions, ``h`` along its normal) is fitted to the ``neighbours`` nearest cell means
    within ``radius_mm``. Where they lie nearly on one line (a lone stripe), the umbilic
    quadric ``a (x^2 + y^2) + ...`` is fitted instead: its one curvature is the line's.
    Every cell is fitted here; :class:`CellSums` gives the same shape for a scan too long to
    hold, fitted where asked.
    """
    acc = CellSums(cell_mm)
    acc.add(points)
    sh = acc.shape(radius_mm=radius_mm, neighbours=neighbours, min_cells=min_cells)
    sh.ensure()
    return sh


def _weighted_lstsq(A: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per row b: argmin_c sum_k w (A c - y)^2, for A (B, K, P); NaN where singular."""
    Aw = (A * w[:, :, None]).transpose(0, 2, 1)
    N = np.matmul(Aw, A)
    r = np.matmul(Aw, y[:, :, None])[..., 0]
    P = A.shape[-1]
    scale = np.sqrt(np.abs(np.einsum("bpp->bp", N))) + 1e-300
    Ns = N / scale[:, :, None] / scale[:, None, :]
    out = np.full((len(A), P), np.nan)
    ev = np.abs(np.linalg.eigvalsh(Ns))  # Ns is symmetric: its condition from its eigenvalues
    with np.errstate(divide="ignore", invalid="ignore"):
        good = ev.max(1) < 1e10 * ev.min(1)
    if good.any():
        out[good] = np.linalg.solve(Ns[good], (r / scale)[good][..., None])[..., 0] / scale[good]
    return out


def _hit(camera: Any, uv: np.ndarray, P0: np.ndarray, N: np.ndarray, e1: np.ndarray,
         e2: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the quadric through P0 (normal N, tangents e1, e2, second
    form s = (s11, s12, s22)), and the quadric's unit normal there."""
    r = camera.rays(uv)
    rn = np.einsum("ij,ij->i", r, N)
    t = np.einsum("ij,ij->i", P0, N) / rn  # the tangent plane's hit, then Newton on the quadric
    r1 = np.einsum("ij,ij->i", r, e1)
    r2 = np.einsum("ij,ij->i", r, e2)
    for _ in range(4):
        w = t[:, None] * r - P0
        x = np.einsum("ij,ij->i", w, e1)
        y = np.einsum("ij,ij->i", w, e2)
        h = np.einsum("ij,ij->i", w, N)
        F = h - 0.5 * (s[:, 0] * x * x + 2 * s[:, 1] * x * y + s[:, 2] * y * y)
        dF = rn - (s[:, 0] * x + s[:, 1] * y) * r1 - (s[:, 1] * x + s[:, 2] * y) * r2
        t = t - F / dF
    w = t[:, None] * r - P0
    x = np.einsum("ij,ij->i", w, e1)
    y = np.einsum("ij,ij->i", w, e2)
    Nh = N - (s[:, 0] * x + s[:, 1] * y)[:, None] * e1 - (s[:, 1] * x + s[:, 2] * y)[:, None] * e2
    return t[:, None] * r, Nh / np.linalg.norm(Nh, axis=1, keepdims=True)


def stripe_gradient(camera: Any, normal: np.ndarray, d: float, uv: np.ndarray, p_cam: np.ndarray,
                    N: np.ndarray, e1: np.ndarray, e2: np.ndarray, second: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """|grad f| (mm of sheet offset per px) at each centre and the stripe's unit image normal
    (N, 2), towards +f: the profile's sigma across the stripe is ``sigma_f / |grad f|``."""
    uv = np.asarray(uv, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    g = np.full(len(uv), np.nan)
    ph = np.zeros_like(uv)
    h = 1.0
    du, dv = np.array([h, 0.0]), np.array([0.0, h])
    for a in range(0, len(uv), BLOCK):
        b = min(a + BLOCK, len(uv))
        shape = (p_cam[a:b], N[a:b], e1[a:b], e2[a:b], second[a:b])
        q = uv[a:b]
        with np.errstate(invalid="ignore", divide="ignore"):
            fu = (_offset(camera, q + du, shape, n, d) - _offset(camera, q - du, shape, n, d)) / (2 * h)
            fv = (_offset(camera, q + dv, shape, n, d) - _offset(camera, q - dv, shape, n, d)) / (2 * h)
            g[a:b] = np.hypot(fu, fv)
            ph[a:b] = np.stack([fu, fv], 1) / g[a:b, None]
    return g, ph


def _offset(camera: Any, uv: np.ndarray, shape: tuple, n: np.ndarray, d: float) -> np.ndarray:
    X, _ = _hit(camera, uv, *shape)
    return X @ n + d


def centre_shift(camera: Any, normal: np.ndarray, d: float, uv: np.ndarray, p_cam: np.ndarray,
                 N: np.ndarray, e1: np.ndarray, e2: np.ndarray, second: np.ndarray, *,
                 sigma_f: float, k: np.ndarray, along: np.ndarray | None = None,
                 emitter: np.ndarray | None = None,
                 gradient: tuple[np.ndarray, np.ndarray] | None = None,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bias of each stripe centre ``uv`` (N, 2) px of the sheet (``normal``, ``d``, sigma
    ``sigma_f`` mm across its thickness; camera frame) on the surface shape ``N, e1, e2,
    second`` (camera frame) through ``p_cam``.

    ``k`` (per centre) is the extractor's shift per unit skew over the sheet's variance
    (:func:`skew_response` at the centre's sheet sigma); ``along`` (N, 2) the image
    direction each profile was taken along (a column: (0, 1)), where NaN or None: across the
    stripe. Along a column ``f`` also bends with the stripe's own curve in the image, which
    this sees too; the profile there is ``1 / |cos|`` as long. With the laser's ``emitter``
    (camera frame), Lambert's cosine across the band adds its slope: a Gaussian times
    ``1 + s tau`` peaks ``s sigma^2`` further on. Returns (bias px along the direction, the
    direction (N, 2), the stripe's image normal (N, 2)): the centre the extractor would have
    found on a flat surface is ``uv - bias * direction``. NaN bias where the shape gives no
    profile. ``gradient``: :func:`stripe_gradient`'s result for these centres, if at hand.
    """
    uv = np.asarray(uv, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    e = None if emitter is None else np.asarray(emitter, dtype=np.float64)
    g, ph = gradient if gradient is not None else stripe_gradient(camera, n, d, uv, p_cam, N, e1, e2, second)
    bias = np.full(len(uv), np.nan)
    direction = np.zeros_like(uv)
    h = 1.0  # px: f is quadratic over the profile, the step only has to resolve it
    for a in range(0, len(uv), BLOCK):
        b = min(a + BLOCK, len(uv))
        shape = (p_cam[a:b], N[a:b], e1[a:b], e2[a:b], second[a:b])
        q = uv[a:b]
        with np.errstate(invalid="ignore", divide="ignore"):
            p = ph[a:b] if along is None else np.where(np.isfinite(along[a:b]), along[a:b], ph[a:b])
            cos = np.einsum("ij,ij->i", p, ph[a:b])
            var = (sigma_f / (g[a:b] * cos)) ** 2  # the sheet's profile along p, px^2
            X0, _ = _hit(camera, q, *shape)
            Xp, Np = _hit(camera, q + h * p, *shape)
            Xm, Nm = _hit(camera, q - h * p, *shape)
            f0, fp, fm = X0 @ n + d, Xp @ n + d, Xm @ n + d
            out = k[a:b] * var * (fp + fm - 2 * f0) / (2 * h * h) / ((fp - fm) / (2 * h))
            if e is not None:
                out = out + var * (_log_cos(Xp, Np, e) - _log_cos(Xm, Nm, e)) / (2 * h)
            bias[a:b] = out
        direction[a:b] = np.where(np.isfinite(p), p, 0.0)
    return bias, direction, ph


def _log_cos(X: np.ndarray, Nh: np.ndarray, emitter: np.ndarray) -> np.ndarray:
    ell = X - emitter
    return np.log(np.abs(np.einsum("ij,ij->i", ell, Nh)) / np.linalg.norm(ell, axis=1))


def sheet_sigma(samples: dict[str, tuple[np.ndarray, np.ndarray]]) -> tuple[dict[str, float], float]:
    """Each laser's sheet sigma across its thickness (mm) and the camera's blur (px), from
    centres on any surface: a profile's variance is ``(sigma_f / g)^2 + sigma_0^2`` with ``g =
    |grad f|`` (:func:`stripe_gradient`); ``samples[laser] = (g, reported width / FWHM)``.

    One blur for all lasers (the camera's), one sheet per laser, fitted by least squares and
    again without the centres far off the fit (merged or clipped stripes). A sheet that the
    widths do not resolve from the blur gets 0 (its centres are left as found).
    """
    names = [k for k, (g, w) in samples.items() if len(g)]
    with np.errstate(divide="ignore"):
        xs = [1.0 / np.asarray(samples[k][0], dtype=np.float64) ** 2 for k in names]
    ys = [np.asarray(samples[k][1], dtype=np.float64) ** 2 for k in names]
    ok = [np.isfinite(x) & np.isfinite(y) for x, y in zip(xs, ys, strict=True)]
    # where the sheet meets the surface almost along the ray (|grad f| near 0) the model's
    # profile is unbounded and no extractor reports it; left in, one such x dwarfs the other
    # columns below the solve's cutoff (relative to its largest) and every sheet comes out 0
    ok = [o & (x <= X_SPREAD * np.median(x[o])) if o.any() else o
          for x, o in zip(xs, ok, strict=True)]
    xs = [x[o] for x, o in zip(xs, ok, strict=True)]
    ys = [y[o] for y, o in zip(ys, ok, strict=True)]
    if sum(x.size for x in xs) < 50:
        return {k: 0.0 for k in samples}, float("nan")
    x = np.concatenate(xs)
    y = np.concatenate(ys)
    which = np.concatenate([np.full(v.size, i) for i, v in enumerate(xs)])
    A = np.zeros((x.size, len(names) + 1))
    A[np.arange(x.size), which] = x
    A[:, -1] = 1.0
    keep = np.ones(x.size, dtype=bool)
    coef = np.zeros(len(names) + 1)
    scale = np.maximum(np.abs(A).max(axis=0), 1e-300)  # columns alike: no cutoff by units
    for _ in range(4):
        coef = np.linalg.lstsq(A[keep] / scale, y[keep], rcond=None)[0] / scale
        r = y - A @ coef
        mad = robust_sigma(r[keep])
        keep = np.abs(r) <= 3.0 * max(mad, 1e-9)
    blur2 = max(float(coef[-1]), 0.0)
    out = {k: 0.0 for k in samples}
    for i, k in enumerate(names):
        m = keep & (which == i)
        # with the blur fixed, each sheet from its own centres (robust to a narrow spread of g)
        slope = float(np.median((y[m] - blur2) / x[m])) if m.any() else 0.0
        out[k] = float(np.sqrt(slope)) if slope > 0 else 0.0
    return out, float(np.sqrt(blur2))

"""Find the calibration board in an image: circle grids (symmetric, asymmetric; dark or light
circles) and chessboards, with sub-pixel centres.

Circle grids are found by ``cv2.findCirclesGrid`` with a blob detector sized from the board
geometry and the image size (OpenCV's default detector drops blobs over 5000 px², and the
paper's circles image at ~70 px across). The crude centres are then refined in a local window
around each blob: the weight of a pixel is its contrast relative to a background plane fitted
in an annulus around the blob (``1 - I / bg`` for dark circles), which makes the estimate the
area centroid of the imaged circle, independent of blur, of the illumination level and of a
linear illumination gradient across the blob. That area centroid is *not* the projection of
the circle's centre (perspective bias); :mod:`crossline.calibrate.bias` predicts the offset.
Chessboards are found by ``cv2.findChessboardCornersSB`` (or the classic finder), and every
corner is refined by fitting a blurred X-junction to its pixels
(:mod:`crossline.calibrate.corners`), which has no perspective bias to correct.

Labelling. Points are returned in :meth:`Board.object_points` order (row by row). OpenCV may
label a grid in any of the orders that map the board onto itself (the symmetric grid and the
chessboard look the same turned by 180°, square grids also by 90°); it may also return a
mirrored order. Here every labelling is made right-handed (board x, y, z = x × y with z
pointing away from the camera, as the board frame of DESIGN.md needs) and, among the
labellings the board's symmetry allows, the one whose first point lies nearest the image's
top-left corner is chosen. For intrinsics and laser planes any right-handed labelling is
equally good; the hand-eye stage re-labels views so that all of them agree on one board frame
(:func:`board_symmetries` lists the alternatives).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.corners import refine_chessboard_corners

__all__ = [
    "Detection",
    "blob_detector",
    "board_symmetries",
    "canonical_labelling",
    "detect_board",
    "refine_circle_centres",
    "subpix_corners",
    "to_uint8",
]

log = logging.getLogger(__name__)

# Detection runs on an image reduced so that its long side is about this many pixels: blob
# detection and grid finding are faster and as reliable there; centres are refined at full size.
DETECT_LONG_SIDE = 1600
MAX_LABELLING_ERROR = 0.25  # spacings: see labelling_error
EDGE_BINS = np.arange(-2.0, 8.01, 0.25)  # px beyond a blob's rim, for the edge profile


@dataclass(frozen=True)
class Detection:
    """The board found (or not) in one image.

    ``points`` (N, 2) are refined centres (circle grids: area centroids of the imaged circles)
    in :meth:`Board.object_points` order, or None with ``reason`` saying why not.
    ``shapes`` (N, 2, 2) are the blobs' second-moment matrices (px²) for circle grids.
    """

    points: np.ndarray | None
    reason: str = ""
    shapes: np.ndarray | None = None
    # (N,) chessboard corners not refined, with ``partial``: their rows of ``points`` are NaN
    missing: np.ndarray | None = None

    @property
    def found(self) -> bool:
        """True when the whole board was found."""
        return self.points is not None


def to_uint8(image: np.ndarray) -> np.ndarray:
    """An 8-bit copy of a grey image stretched between its 0.5th and 99.5th percentiles."""
    img = np.asarray(image)
    lo, hi = np.percentile(img[::4, ::4], [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1.0
    return np.clip((img.astype(np.float32) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def _grid_extent(board: Board) -> tuple[float, float]:
    ex, ey = board.extent()
    return max(ex, board.spacing), max(ey, board.spacing)


def _nearest_neighbour_distance(board: Board) -> float:
    """Smallest centre-to-centre distance on the board (mm)."""
    if board.pattern == "asymmetric":
        return float(min(np.sqrt(2.0), 2.0) * board.spacing)
    return float(board.spacing)


def blob_detector(board: Board, image_size: tuple[int, int], scale: float = 1.0):
    """A ``cv2.SimpleBlobDetector`` for the board's circles in an image of ``image_size``.

    The area limits follow from the geometry: the board must fit in the image (largest
    circle: the grid spans the image's long side, with 2× for perspective) and be at least
    an eighth of the image's short side (smallest circle). ``scale`` is the detection image's
    size relative to ``image_size``. The image is expected stretched to 0..255 (:func:`to_uint8`).
    """
    w, h = image_size
    ex, ey = _grid_extent(board)
    d_max = board.diameter / min(ex, ey) * max(w, h) * 2.0 * scale
    d_min = board.diameter / max(ex, ey) * min(w, h) / 8.0 * scale
    p = cv2.SimpleBlobDetector_Params()
    p.blobColor = 0 if board.circles == "dark" else 255
    p.filterByColor = True
    p.minThreshold = 30
    p.maxThreshold = 225
    p.thresholdStep = 15
    p.minRepeatability = 2
    p.filterByArea = True
    p.minArea = max(4.0, 0.5 * np.pi / 4 * d_min**2)
    p.maxArea = np.pi / 4 * d_max**2
    p.filterByCircularity = False
    p.filterByConvexity = True
    p.minConvexity = 0.85
    p.filterByInertia = True
    p.minInertiaRatio = 0.1  # circles seen at up to ~84° of tilt
    p.minDistBetweenBlobs = max(2.0, 0.5 * d_min)
    return cv2.SimpleBlobDetector_create(p)


def board_symmetries(board: Board) -> list[np.ndarray]:
    """Index permutations that map the board's point set onto itself by a rotation in its plane.

    ``perm[k]`` is the index of the point that lands where point ``k`` was. The identity is
    always first; a symmetric grid or a chessboard adds the 180° turn (and a square one the
    90° turns). These are the labellings a detector may return for the same physical view.
    """
    P = board.object_points()[:, :2]
    c = 0.5 * (P.min(0) + P.max(0))
    perms = []
    for k in range(4):
        a = k * np.pi / 2
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        Q = (P - c) @ R.T + c
        d = np.linalg.norm(Q[:, None, :] - P[None, :, :], axis=-1)
        j = d.argmin(1)
        if np.all(d[np.arange(len(P)), j] < 1e-6 * board.spacing) and len(set(j)) == len(P):
            perms.append(j)
    return perms


def _orientation(points: np.ndarray, board: Board) -> float:
    """Signed area (px²) spanned by the board's x and y axes as seen in the image."""
    H, _ = cv2.findHomography(board.object_points()[:, :2], points, 0)
    if H is None:
        return 0.0
    c = board.object_points()[:, :2].mean(0)
    e = np.array([c, c + np.array([board.spacing, 0.0]), c + np.array([0.0, board.spacing])])
    q = cv2.perspectiveTransform(e[None], H)[0]
    ax, ay = q[1] - q[0], q[2] - q[0]
    return float(ax[0] * ay[1] - ax[1] * ay[0])


def _mirror_permutations(board: Board) -> list[np.ndarray]:
    """Permutations of the point list that mirror the board (right- to left-handed)."""
    P = board.object_points()[:, :2]
    c = 0.5 * (P.min(0) + P.max(0))
    out = []
    for M in (np.diag([-1.0, 1.0]), np.diag([1.0, -1.0]), np.array([[0.0, 1.0], [1.0, 0.0]])):
        Q = (P - c) @ M.T + c
        d = np.linalg.norm(Q[:, None, :] - P[None, :, :], axis=-1)
        j = d.argmin(1)
        if np.all(d[np.arange(len(P)), j] < 1e-6 * board.spacing) and len(set(j)) == len(P):
            out.append(j)
    return out


def canonical_labelling(points: np.ndarray, board: Board) -> np.ndarray | None:
    """Right-handed relabelling of detected points, first point nearest the image's top-left.

    Returns the reordered points, or None if a mirrored detection cannot be relabelled.
    """
    pts = np.asarray(points, dtype=np.float64)
    if _orientation(pts, board) < 0:
        for perm in _mirror_permutations(board):
            cand = pts[perm]
            if _orientation(cand, board) > 0:
                pts = cand
                break
        else:
            return None
    best = min(board_symmetries(board), key=lambda perm: float(pts[perm][0].sum()))
    return pts[best]


def labelling_error(points: np.ndarray, board: Board) -> float:
    """RMS (px) of the detected points about the board seen through a homography, in spacings.

    A right labelling leaves the lens's distortion and the centres' noise: a few hundredths
    of a spacing. A wrong one (rows taken in the wrong order) leaves about one spacing.
    """
    P = board.object_points()[:, :2]
    H, _ = cv2.findHomography(P, points, 0)
    if H is None:
        return np.inf
    r = cv2.perspectiveTransform(P[None], H)[0] - points
    step = np.median(np.linalg.norm(np.diff(points.reshape(board.rows, board.cols, 2), axis=1), axis=-1))
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))) / max(step, 1e-9))


def _find_grid(img8: np.ndarray, board: Board, image_size, scale: float) -> np.ndarray | None:
    flags = cv2.CALIB_CB_SYMMETRIC_GRID if board.pattern == "symmetric" else cv2.CALIB_CB_ASYMMETRIC_GRID
    det = blob_detector(board, image_size, scale)
    h = img8.shape[0]
    # OpenCV's grid finder can return every circle of an asymmetric grid, its rows taken in an
    # order no view of the board gives (seen on a 5 x 8 grid); the same finder on the image
    # turned a quarter labels it right. A labelling is kept only if a homography carries the
    # board onto it.
    for turned in (False, True):
        img = cv2.rotate(img8, cv2.ROTATE_90_CLOCKWISE) if turned else img8
        for extra in (0, cv2.CALIB_CB_CLUSTERING):
            ok, centres = cv2.findCirclesGrid(img, board.pattern_size, flags=flags | extra, blobDetector=det)
            if not (ok and centres is not None and len(centres) == board.n_points):
                continue
            c = centres.reshape(-1, 2).astype(np.float64)
            if turned:  # (x', y') of the turned image is (h - 1 - y, x) of the image
                c = np.column_stack([c[:, 1], h - 1 - c[:, 0]])
            if labelling_error(c, board) <= MAX_LABELLING_ERROR:
                return c
    return None


def _find_chessboard(img8: np.ndarray, board: Board) -> np.ndarray | None:
    ok, corners = cv2.findChessboardCornersSB(
        img8, board.pattern_size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    )
    if ok and corners is not None:
        return corners.reshape(-1, 2).astype(np.float64)
    ok, corners = cv2.findChessboardCorners(
        img8, board.pattern_size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    )
    if not ok or corners is None:
        return None
    spacing = np.median(np.linalg.norm(np.diff(corners.reshape(-1, 2), axis=0), axis=1))
    win = int(np.clip(0.4 * spacing, 3, 25))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    corners = cv2.cornerSubPix(img8, corners.astype(np.float32), (win, win), (-1, -1), crit)
    return corners.reshape(-1, 2).astype(np.float64)


def subpix_corners(img8: np.ndarray, points: np.ndarray, board: Board) -> np.ndarray:
    """Chessboard corners (N, 2) refined by ``cv2.cornerSubPix`` in a window of 0.4 spacings."""
    grid = points.reshape(board.rows, board.cols, 2)
    spacing = np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1))
    win = int(np.clip(0.4 * spacing, 3, 25))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    # (N, 1, 2) by reshape, not [:, None]: a new axis has stride 0, which cv2 rejects
    q = cv2.cornerSubPix(img8, points.astype(np.float32).reshape(-1, 1, 2), (win, win), (-1, -1), crit)
    return q.reshape(-1, 2).astype(np.float64)


def detect_board(image: np.ndarray, board: Board, *, refine: bool = True,
                 partial: bool = False) -> Detection:
    """Find ``board`` in a grey image; return refined points in board order or the reason why not.

    ``partial``: a chessboard whose every corner was found but some could not be refined (a
    laser stripe drawn across them) is returned with those rows NaN and flagged in
    ``missing``, and ``reason`` saying which; the caller decides whether the rest will do.
    """
    img = np.asarray(image)
    h, w = img.shape
    img8 = to_uint8(img)
    f = max(1, round(max(w, h) / DETECT_LONG_SIDE))
    small = cv2.resize(img8, (w // f, h // f), interpolation=cv2.INTER_AREA) if f > 1 else img8
    attempts = [(small, f)] + ([(img8, 1)] if f > 1 else [])
    crude = None
    for im, fac in attempts:
        if board.pattern == "chessboard":
            crude = _find_chessboard(im, board)
        else:
            crude = _find_grid(im, board, (w, h), 1.0 / fac)
        if crude is not None:
            # pixel centres of an f-times reduced image: full = f * small + (f - 1) / 2
            crude = crude * fac + 0.5 * (fac - 1)
            break
    if crude is None:
        what = (
            "chessboard" if board.pattern == "chessboard"
            else f"{board.pattern} grid of {board.circles} circles"
        )
        return Detection(None, f"board not found: no {board.cols}x{board.rows} {what} detected")
    pts = canonical_labelling(crude, board)
    if pts is None:
        return Detection(None, "board found mirrored and cannot be relabelled")
    if board.pattern == "chessboard":
        if not refine:
            return Detection(pts)
        if f > 1:  # corners found on the reduced image: OpenCV's refinement first, at full size
            pts = subpix_corners(img8, pts, board)
        pts, ok = refine_chessboard_corners(img, board, pts)
        if not ok.all():
            bad = np.flatnonzero(~ok)
            where = ", ".join(f"(row {k // board.cols}, col {k % board.cols})" for k in bad[:5])
            reason = (f"chessboard corners could not be refined: {bad.size} of {ok.size} "
                      f"corners show no sharp X-junction, e.g. at {where}")
            if not partial:
                return Detection(None, reason)
            pts = np.where(ok[:, None], pts, np.nan)
            return Detection(pts, reason, missing=~ok)
        return Detection(pts)
    if not refine:
        return Detection(pts)
    try:
        centres, shapes = refine_circle_centres(img, board, pts)
    except ValueError as exc:
        return Detection(None, f"circle centres could not be refined: {exc}")
    return Detection(centres, shapes=shapes)


# ----------------------------------------------------------------------------- refinement


def _local_ellipses(board: Board, points: np.ndarray) -> np.ndarray:
    """Second-moment matrices (N, 2, 2) of the circles' images, from the board's homography."""
    B = board.object_points()[:, :2]
    H, _ = cv2.findHomography(B, points, 0)
    if H is None:
        raise ValueError("no homography from board to image")
    x = np.column_stack([B, np.ones(len(B))]) @ H.T
    # Jacobian of the homography at each board point
    J = (H[None, :2, :2] * x[:, 2, None, None] - x[:, :2, None] * H[None, 2:3, :2]) / x[:, 2, None, None] ** 2
    R = 0.5 * board.diameter
    return (R * R / 4.0) * J @ np.swapaxes(J, 1, 2)


def refine_circle_centres(
    image: np.ndarray,
    board: Board,
    points: np.ndarray,
    *,
    margin_px: float | None = None,
    iterations: int = 4,
    chunk: int = 32,
) -> tuple[np.ndarray, np.ndarray]:
    """Area centroids (N, 2) and second-moment matrices (N, 2, 2) of the circles near ``points``.

    For each blob: a background plane ``bg`` is fitted (robustly) in an annulus around it and a
    plane ``fg`` to the circle's inner part, and the centroid of the weights
    ``(I - bg) / (fg - bg)`` is taken over the blob's ellipse grown by a margin. The weights are
    the area fraction of circle each pixel sees, so blur, pixel integration, the sensor's
    black level and a smooth illumination (level and gradient) leave the centroid unbiased.
    Repeated ``iterations`` (>= 3) times, each window centred and shaped on the previous
    estimate: the first two with generous windows, the later ones with the
    ellipse from the blob's own moments grown by ``margin_px``, by default measured from the
    image: the distance beyond the rim where the blurred edge has faded to 0.5 % of the
    contrast (averaged over all blobs), plus half a pixel. In those later rounds the pixels
    deeper inside than that margin are given their exact weight, 1, instead of a measured
    one: only the band around the rim is measured. Every measured pixel adds its noise with
    the lever of its distance from the centre, so a tight band matters (for light circles,
    whose bright interior is the noisiest part, it halves the centres' noise).
    """
    img = np.asarray(image, dtype=np.float32)
    h, w = img.shape
    c = np.asarray(points, dtype=np.float64).copy()
    n_pts = len(c)
    S = _local_ellipses(board, c)
    # room between this circle and its neighbours, in units of the circle's radius
    free = _nearest_neighbour_distance(board) / (0.5 * board.diameter)
    sign = -1.0 if board.circles == "dark" else 1.0  # sign of the circles' contrast
    margin = 3.0 if margin_px is None else float(margin_px)
    planes = np.zeros((n_pts, 3))  # background a + b u + c v in image coordinates
    cores = np.zeros((n_pts, 3))  # the circle's own level, likewise
    for it in range(max(iterations, 3)):
        ev = np.linalg.eigvalsh(S)
        if np.any(ev[:, 0] <= 0):
            raise ValueError("a blob's second moments are not positive")
        Sinv = np.linalg.inv(4.0 * S)  # rho^2 = d^T (4 S)^-1 d for a uniform ellipse
        r_minor, r_major = np.sqrt(4.0 * ev[:, 0]), np.sqrt(4.0 * ev[:, 1])
        # the first window's shape comes from the homography and needs slack; later ones come
        # from the blob's own moments (slightly widened by the blur)
        if it == 0:
            # where circles are small in the image and close together, the slack must still
            # leave a background ring of 0.2 radii between this window and the neighbours'
            rho_in = np.minimum(1.25 + 3.0 / r_minor, np.maximum(0.5 * (free - 0.2), 1.05))
        elif it == 1:
            rho_in = 1.0 + 5.0 / r_minor
        else:
            rho_in = 1.0 + margin / r_minor
        fit_bg = it == 0  # the planes are fitted once, on the generous first window
        rho_ring = np.minimum(free - rho_in, rho_in + 0.5)  # outer edge of the background ring
        if fit_bg and np.any(rho_ring < rho_in + 0.2):
            raise ValueError("circles too close together or too small for a background annulus")
        reach = rho_ring if fit_bg else rho_in
        half = int(np.ceil(np.max(reach * r_major))) + 1
        off = np.arange(-half, half + 1, dtype=np.float32)
        r_geo = np.sqrt(r_minor * r_major)
        prof_w = np.zeros(len(EDGE_BINS) + 1)
        prof_n = np.zeros(len(EDGE_BINS) + 1)
        new_c = np.empty_like(c)
        new_S = np.empty_like(S)
        for s in range(0, n_pts, chunk):
            sl = slice(s, min(s + chunk, n_pts))
            cc = c[sl]
            base = np.round(cc).astype(int)
            xs = base[:, 0, None] + off.astype(int)[None, :]  # (n, W) columns
            ys = base[:, 1, None] + off.astype(int)[None, :]  # (n, H) rows
            inside = ((xs >= 0) & (xs < w))[:, None, :] & ((ys >= 0) & (ys < h))[:, :, None]
            patch = img[np.clip(ys, 0, h - 1)[:, :, None], np.clip(xs, 0, w - 1)[:, None, :]]
            dx = (xs - cc[:, 0, None]).astype(np.float32)[:, None, :]  # (n, 1, W)
            dy = (ys - cc[:, 1, None]).astype(np.float32)[:, :, None]  # (n, H, 1)
            Si = Sinv[sl].astype(np.float32)
            rho = np.sqrt(Si[:, 0, 0, None, None] * dx * dx + 2 * Si[:, 0, 1, None, None] * dx * dy
                          + Si[:, 1, 1, None, None] * dy * dy)
            rin = rho_in[sl, None, None].astype(np.float32)
            inner = rho <= rin
            if np.any(np.any(inner & ~inside, axis=(1, 2))):
                raise ValueError("a circle lies too close to the image border")
            if fit_bg:
                ring = (rho >= rin + 0.1) & (rho <= rho_ring[sl, None, None]) & inside
                # store in image coordinates so later windows can reuse the planes
                for store, mask in ((planes, ring), (cores, (rho <= 0.7) & inside)):
                    coef = _background_planes(patch, dx, dy, mask)
                    store[sl, 0] = coef[:, 0] - coef[:, 1] * cc[:, 0] - coef[:, 2] * cc[:, 1]
                    store[sl, 1:] = coef[:, 1:]
            pl, co = planes[sl] , cores[sl]
            bg = (pl[:, 0, None, None] + pl[:, 1, None, None] * xs[:, None, :]
                  + pl[:, 2, None, None] * ys[:, :, None]).astype(np.float32)
            fg = (co[:, 0, None, None] + co[:, 1, None, None] * xs[:, None, :]
                  + co[:, 2, None, None] * ys[:, :, None]).astype(np.float32)
            # (I - bg) / (fg - bg) is the area fraction of circle a pixel sees, whatever the
            # illumination's level, gradient or the sensor's black level
            contrast = fg - bg
            if np.any(sign * contrast[:, half, half] <= 0):
                raise ValueError("a circle has no contrast against its background")
            wraw = (patch - bg) / contrast
            wgt = np.where(inner, wraw, np.float32(0.0))
            if it >= 2:
                # well inside the rim a pixel sees circle only: its weight is exactly 1, and
                # measuring it would add only noise (most of it for light circles)
                core = rho <= (1.0 - (margin + 0.5) / r_minor[sl])[:, None, None].astype(np.float32)
                wgt = np.where(core, np.float32(1.0), wgt)
            sw = wgt.sum(axis=(1, 2), dtype=np.float64)
            if np.any(sw <= 0):
                raise ValueError("a circle has no contrast against its background")
            wx = (wgt * dx).sum(axis=(1, 2), dtype=np.float64)
            wy = (wgt * dy).sum(axis=(1, 2), dtype=np.float64)
            wxx = (wgt * dx * dx).sum(axis=(1, 2), dtype=np.float64)
            wxy = (wgt * dx * dy).sum(axis=(1, 2), dtype=np.float64)
            wyy = (wgt * dy * dy).sum(axis=(1, 2), dtype=np.float64)
            mx, my = wx / sw, wy / sw
            sxx, sxy, syy = wxx / sw - mx * mx, wxy / sw - mx * my, wyy / sw - my * my
            new_c[sl] = cc + np.column_stack([mx, my])
            new_S[sl] = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
            if it == 1 and margin_px is None:
                # edge profile: weight against distance beyond the rim (px), normalised by
                # each blob's interior level
                core = rho < 0.7
                level = (np.where(core, wraw, 0).sum(axis=(1, 2)) / np.maximum(core.sum(axis=(1, 2)), 1))
                delta = (rho - 1.0) * r_geo[sl, None, None]
                sel = inside & (rho <= rho_ring[sl, None, None])
                b = np.digitize(delta[sel], EDGE_BINS)
                prof_w += np.bincount(b, (wraw / level[:, None, None])[sel], minlength=len(prof_w))
                prof_n += np.bincount(b, minlength=len(prof_n))
        c, S = new_c, new_S
        if it == 1 and margin_px is None:
            margin = _edge_margin(prof_w, prof_n)
    return c, S


def _edge_margin(prof_w: np.ndarray, prof_n: np.ndarray) -> float:
    """Distance (px) beyond the rim where the mean edge profile stays under 0.5 %, plus 0.5 px."""
    with np.errstate(invalid="ignore", divide="ignore"):
        prof = prof_w[1:-1] / prof_n[1:-1]  # bin k spans EDGE_BINS[k] .. EDGE_BINS[k + 1]
    upper = EDGE_BINS[1:]
    above = np.nonzero((prof > 0.005) & (upper > 0))[0]
    last = float(upper[above[-1]]) if len(above) else 0.0
    return float(np.clip(last + 0.5, 1.5, 6.0))


def _background_planes(patch: np.ndarray, dx: np.ndarray, dy: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Per-patch coefficients (n, 3) of background planes ``a + b dx + c dy`` fitted to the ring.

    Two passes, the second without the ring pixels beyond 3 RMS of the first fit (the board's
    edge or a neighbour reaching into the ring).
    """
    m = ring
    f64 = np.float64
    coef = np.zeros((len(patch), 3))
    for k in range(2):
        mf = m.astype(np.float32)
        mx, my, mi = mf * dx, mf * dy, mf * patch
        s = lambda a: a.sum(axis=(1, 2), dtype=f64)  # noqa: E731
        n, sx, sy = s(mf), s(mx), s(my)
        AtA = np.stack([
            np.stack([n, sx, sy], -1),
            np.stack([sx, s(mx * dx), s(mx * dy)], -1),
            np.stack([sy, s(my * dx), s(my * dy)], -1),
        ], -2)
        Atb = np.stack([s(mi), s(mi * dx), s(mi * dy)], -1)
        coef = np.linalg.solve(AtA, Atb[..., None])[..., 0]
        if k == 1:
            break
        fit = (coef[:, 0, None, None] + coef[:, 1, None, None] * dx + coef[:, 2, None, None] * dy)
        res2 = np.where(ring, (patch - fit) ** 2, 0.0)
        rms = np.sqrt(res2.sum(axis=(1, 2), dtype=f64) / np.maximum(ring.sum(axis=(1, 2)), 1))
        new = ring & (res2 <= (3.0 * rms[:, None, None]) ** 2)
        # keep the plain ring where clipping would leave too little of it
        few = new.sum(axis=(1, 2)) < 0.5 * ring.sum(axis=(1, 2))
        m = np.where(few[:, None, None], ring, new)
    return coef

"""Laser-plane calibration (the paper's §2.5, generalised to any number of board poses).

For each pose of each laser:

1. the board pose ``T_cam_board`` by PnP on the lasers-off image (bias-corrected centres);
2. the stripe: laser-on minus lasers-off image (ambient light and the board's print cancel),
   grey-centre per column (:func:`crossline.scan.stripes.grey_centre`; per row when the stripe is
   steeper than 45°, so that profiles cut the stripe at the smaller angle), with the
   threshold as a fraction of the stripe's peak level on the board's plate (its light area,
   or its dark one for light circles; within the board's outline, ``margin_px`` clear of the
   circles), whatever the stripe does on the table or on the circles;
3. the board's albedo is taken out of the difference (:func:`albedo_gain`): the stripe is laser
   irradiance times albedo, so across a circle rim or a square edge its profile steps by the
   albedo ratio (~10x), which would pull its centre towards the light side. The gain comes
   from the lasers-off image, less the sensor's black level, which the stripe's own levels on
   the two albedo classes give. With the gain, a centre must lie ``margin_px`` clear of the
   albedo edges (the blur of the edge is not quite undone there) and its whole window on the
   board; without it (a class too rare to measure the ratio on), its whole window must clear
   every albedo edge by ``margin_px``;
4. each centre's ray (undistorted) is intersected with the board plane.

One plane per laser is then fitted to the points of all its poses: a least-median start
from random triples, then trimmed least squares (points beyond ``trim`` robust sigmas are
dropped) until the inliers no longer change.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.detect import detect_board, to_uint8
from crossline.calibrate.pose import board_pose
from crossline.camera import CAMERA_PARAMETERS, Camera
from crossline.errors import CalibrationError, CrosslineError
from crossline.geometry import fit_plane, plane_covariance, plane_distance, plane_tilt_basis
from crossline.laser import LASERS, LaserPlane, LaserPlanes

__all__ = [
    "PoseStripe",
    "albedo_gain",
    "board_plane_points",
    "camera_jacobian",
    "edge_clearance",
    "group_sigma",
    "robust_plane",
    "run_calibrate_lasers",
    "stripe_points",
]

log = logging.getLogger(__name__)

MIN_CENTRES = 20  # fewer stripe centres on the board than this: no stripe
PAD_PX = 3  # how far the grey-centre window reaches beyond the run above threshold
MIN_POSES = 2  # usable poses per laser: one pose's stripe is a line, two span the plane
# the plane's inlier scatter, in pixels at the points' depth, beyond which its centres are
# not the stripe's (good stripes scatter by a tenth of a pixel or so)
MAX_PLANE_RMS_PX = 3.0
NOISE_K = 8.0  # the stripe stands this many noise sigmas above the laser-minus-board difference
MIN_PIECE_ELONGATION = 2.2  # a stripe piece is longer than wide by this; corner residues 1.3-1.8
STRIPE_OPEN_FRACTION = 0.012  # laser always on: the opening that removes the stripe, x sensor size


@dataclass(frozen=True)
class PoseStripe:
    """Stripe points of one board pose: camera-frame points and their pixels."""

    points: np.ndarray  # (M, 3) mm, camera frame
    uv: np.ndarray  # (M, 2) px
    T_cam_board: np.ndarray
    board_rms_px: float
    axis: str  # "column" or "row": the direction of the profiles
    n_centres: int  # centres found before the board-area filter
    albedo: dict | None = None  # the albedo gain's ratio and black level, None if not applied
    on_other: np.ndarray | None = None  # (M,) bool: the centre lies on the other albedo class
    board_points: np.ndarray | None = None  # (K, 2) px: the board's detected points (its pose)
    bias_correction: bool = True  # whether the pose corrected the circle-centre bias


def board_plane_points(camera: Camera, T_cam_board: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) where the rays through pixels (N, 2) meet the board plane."""
    r = camera.rays(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    n = T_cam_board[:3, 2]
    lam = (n @ T_cam_board[:3, 3]) / (r @ n)
    return r * lam[:, None]


def edge_clearance(board: Board, xy: np.ndarray, board_margin: float | None = None,
                   pattern: bool = True) -> np.ndarray:
    """Distance (mm) from board points (N, 2) to the nearest albedo edge; < 0 off the board.

    Albedo edges are circle rims (circle grids) or square edges (chessboards); with
    ``pattern`` False only the edge of the board's usable area counts. That area is the grid's
    bounding box grown by ``board_margin`` (default: one circle diameter beyond the outer
    centres; the chessboard's outer squares).
    """
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    s = board.spacing
    ex, ey = board.extent()
    m = _margin(board) if board_margin is None else board_margin
    inside = np.minimum.reduce([x + m, y + m, ex + m - x, ey + m - y])
    if not pattern:
        return inside
    if board.pattern == "chessboard":
        kx = np.clip(np.round(x / s), -1, board.cols)
        ky = np.clip(np.round(y / s), -1, board.rows)
        dx = np.where((y > -s) & (y < board.rows * s), np.abs(x - kx * s), np.inf)
        dy = np.where((x > -s) & (x < board.cols * s), np.abs(y - ky * s), np.inf)
        clear = np.minimum(dx, dy)
    else:
        R = 0.5 * board.diameter
        clear = np.full(x.shape, np.inf)
        r0 = np.floor(y / s)
        for dr in (-1, 0, 1, 2):
            r = np.clip(r0 + dr, 0, board.rows - 1)
            if board.pattern == "asymmetric":
                c0 = np.round((x - (r % 2) * s) / (2 * s))
                cands = [np.clip(c0 + dc, 0, board.cols - 1) for dc in (-1, 0, 1)]
                cx = [(2 * c + r % 2) * s for c in cands]
            else:
                c0 = np.round(x / s)
                cx = [np.clip(c0 + dc, 0, board.cols - 1) * s for dc in (-1, 0, 1)]
            for cxx in cx:
                clear = np.minimum(clear, np.abs(np.hypot(x - cxx, y - r * s) - R))
    return np.where(inside < 0, inside, np.minimum(clear, inside))


def _margin(board: Board) -> float:
    """How far the board's usable area reaches beyond the outer points (mm)."""
    return board.spacing if board.pattern == "chessboard" else float(board.diameter)


def _board_area(camera: Camera, T_cam_board: np.ndarray, board: Board, shape: tuple[int, int]) -> np.ndarray:
    """The pixels (bool mask) that see the board's usable area (``edge_clearance`` >= 0)."""
    ex, ey = board.extent()
    m = _margin(board)
    t = np.linspace(0.0, 1.0, 64, endpoint=False)
    x0, x1, y0, y1 = -m, ex + m, -m, ey + m
    xs = np.concatenate([x0 + (x1 - x0) * t, np.full_like(t, x1), x1 - (x1 - x0) * t, np.full_like(t, x0)])
    ys = np.concatenate([np.full_like(t, y0), y0 + (y1 - y0) * t, np.full_like(t, y1), y1 - (y1 - y0) * t])
    P = np.column_stack([xs, ys, np.zeros_like(xs)]) @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    uv = camera.project(P)  # the outline through the lens: 256 points, distortion included
    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.round(uv * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def _light_mask(board_image: np.ndarray) -> np.ndarray:
    """The board image's light albedo class (Otsu's threshold on the lasers-off image, stretched
    between its own percentiles: the data's range, not the container's)."""
    _, mask = cv2.threshold(to_uint8(board_image), 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return mask.astype(bool)


def _robust_noise(x: np.ndarray) -> float:
    """Robust sigma of a sample: 1.4826 MAD, or the RMS within 5 of it where the data are
    quantised to a fraction of a count (MAD 0); at least sqrt(1/12)."""
    x = np.asarray(x, dtype=np.float64).ravel()
    d = x - np.median(x)
    mad = 1.4826 * float(np.median(np.abs(d)))
    near = d[np.abs(d) <= 5.0 * max(mad, 1.0)]
    rms = float(np.sqrt(np.mean(near**2))) if near.size else 0.0
    return max(mad, rms, float(np.sqrt(1.0 / 12.0)))


def remove_stripe(laser_image: np.ndarray, kernel_px: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The laser image without its stripe, for a pose with the laser always on, and the mask.

    A grey opening with a disc wider than the stripe (``kernel_px``, default
    ``STRIPE_OPEN_FRACTION`` of the sensor's long side) removes every bright structure narrower
    than the disc: the stripe, not the board's squares or circles. The stripe is where the
    image stands above its opening by ``NOISE_K`` noise sigmas and a tenth of the stripe's own
    level, on components that are long (a tenth of the image's short side); only those pixels
    (grown by the stripe's width, for its tails) are replaced by the opening. The result
    stands in for the lasers-off image: the board is found in it, and laser minus it is the
    stripe.
    """
    img = np.asarray(laser_image)
    h, w = img.shape
    k = kernel_px or max(15, round(STRIPE_OPEN_FRACTION * max(h, w)) | 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    opened = cv2.morphologyEx(img, cv2.MORPH_OPEN, disc)
    top = img.astype(np.float32) - opened.astype(np.float32)
    sub = top[::5, ::5]
    noise = _robust_noise(sub)
    level = float(np.quantile(top, 0.999)) if top.size else 0.0
    thr = max(NOISE_K * noise, 0.1 * level)
    cand = (top > thr).astype(np.uint8)
    _n, lab, stats, _ = cv2.connectedComponentsWithStats(cand, connectivity=8)
    length = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    long_ = length >= 0.1 * min(h, w)
    long_[0] = False
    long_ |= _on_long_line(cand, lab, length, 0.1 * min(h, w))
    mask = long_[lab].astype(np.uint8)
    if long_.any():
        # the stripe's tails reach beyond the pixels above a tenth of its level: grow the mask
        # by the stripe's own width (its area over its length), 2 px at least
        width = float(np.max(stats[long_, cv2.CC_STAT_AREA] / length[long_]))
        g = 2 * max(2, round(width)) + 1
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (g, g)))
    mask = mask.astype(bool)
    return np.where(mask, opened, img).astype(img.dtype), mask


def _on_long_line(cand: np.ndarray, lab: np.ndarray, length: np.ndarray, min_len: float) -> np.ndarray:
    """Components that lie on one long straight line with others: a stripe cut into pieces.

    A stripe that crosses dark circles (or dark squares) is dim there and falls apart into
    pieces each shorter than a stripe must be; a probabilistic Hough transform that bridges
    gaps up to the same length joins them. Pieces shorter than 10 px (noise) are not taken.
    """
    keep = np.zeros(len(length), bool)
    if len(length) < 3:
        return keep
    lines = cv2.HoughLinesP(cand * np.uint8(255), 1, np.pi / 720, threshold=max(20, int(min_len / 4)),
                            minLineLength=min_len, maxLineGap=min_len)
    if lines is None:
        return keep
    on = np.zeros_like(cand)
    for x0, y0, x1, y1 in lines[:, 0]:
        cv2.line(on, (int(x0), int(y0)), (int(x1), int(y1)), 1, 3)
    hit = np.unique(lab[(on > 0) & (cand > 0)])
    keep[hit] = True
    keep[0] = False
    keep &= length >= 10
    # a piece of stripe is a segment, long for its width; the residues that the opening leaves
    # at a chessboard's corners are X-shaped blobs, which also line up (along the board's
    # rows) but are about as wide as long: elongation from each component's second moments
    ys, xs = np.nonzero(lab)
    ids = lab[ys, xs]
    n = np.bincount(ids, minlength=len(length)).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = np.bincount(ids, xs, len(length)) / n
        my = np.bincount(ids, ys, len(length)) / n
        dx, dy = xs - mx[ids], ys - my[ids]
        cxx = np.bincount(ids, dx * dx, len(length)) / n
        cyy = np.bincount(ids, dy * dy, len(length)) / n
        cxy = np.bincount(ids, dx * dy, len(length)) / n
        root = np.sqrt(np.maximum((cxx - cyy) ** 2 / 4 + cxy**2, 0.0))
        big, small = (cxx + cyy) / 2 + root, (cxx + cyy) / 2 - root
        elongation = np.sqrt(big / np.maximum(small, 1.0 / 12.0))  # a 1-px-wide line: L / 1
    keep &= np.nan_to_num(elongation) >= MIN_PIECE_ELONGATION
    return keep


def _peak(diff: np.ndarray, k: int = 400) -> float:
    """The stripe's level: the median of the ``k`` highest values of the difference image."""
    flat = diff.reshape(-1)
    top = np.partition(flat, flat.size - k)[flat.size - k :] if flat.size > k else flat
    return float(np.median(top))


def _stripe_axis(diff: np.ndarray, thr: float, keep) -> str:
    """'column' if the stripe is flatter than 45° in the image, else 'row'."""
    v, u = np.nonzero(diff > thr)
    if len(u) > 200_000:
        step = len(u) // 200_000 + 1
        u, v = u[::step], v[::step]
    ok = keep(np.column_stack([u, v]).astype(np.float64))
    u, v = u[ok], v[ok]
    if len(u) < 3:
        return "column"
    c = np.cov(np.vstack([u, v]).astype(np.float64))
    _, V = np.linalg.eigh(c)
    d = V[:, 1]
    return "column" if abs(d[0]) >= abs(d[1]) else "row"


def stripe_points(
    camera: Camera,
    board: Board,
    board_image: np.ndarray | None,
    laser_image: np.ndarray,
    *,
    threshold: float = 0.2,
    margin_px: float = 4.0,
    bias_correction: bool = True,
    name: str = "laser image",
    board_name: str | None = None,
    detect_image: np.ndarray | None = None,
    normalise_albedo: bool = True,
) -> PoseStripe:
    """Stripe points on the board plane (camera frame) of one pose; see the module docstring.

    ``threshold`` is a fraction of the stripe's peak level in laser-on minus lasers-off.
    ``board_image`` None: the laser was always on; the board is found in the laser image with
    its stripe removed (:func:`remove_stripe`), which stands in for the lasers-off image.
    ``detect_image`` (default: the lasers-off image) is the image the board is found in, e.g.
    a colour channel that shows the board better than the laser's. ``normalise_albedo`` False
    keeps the board's albedo in the stripe (the whole window must then clear every edge). Raises
    :class:`CalibrationError` naming ``name`` when the stripe is not found, and ``board_name``
    (the lasers-off image's file; default ``name``) when the board is not.
    """
    from crossline.scan.stripes import full_scale, grey_centre

    full_scale(laser_image.dtype)  # unsigned integers only
    where, name_board = "lasers-off image", board_name or name
    if board_image is None:
        board_image, _ = remove_stripe(laser_image)
        where, name_board = "laser image (laser always on; stripe removed)", name
        if detect_image is not None:
            detect_image, _ = remove_stripe(detect_image)
    det = detect_board(board_image if detect_image is None else detect_image, board)
    if not det.found:
        raise CalibrationError(f"{name_board}: {det.reason} in the {where} of this pose")
    pose = board_pose(camera, board, det.points, bias_correction=bias_correction)
    T = pose.T_cam_board
    n = T[:3, 2]
    # laser-on minus the lasers-off image scaled to the laser image's exposure (calibration
    # laser images may be taken with a shorter exposure than the board views)
    a, b = ambient_model(board_image, laser_image)
    diff_f = laser_image.astype(np.float32) - (a * board_image.astype(np.float32) + b)
    # grey_centre wants unsigned integers: keep 1/16 of a count of resolution where the data
    # leave room for it (up to 12 bits), less for wider data
    scale = float(min(16.0, 65535.0 / max(float(diff_f.max()), 1.0)))
    diff = np.clip(np.round(diff_f * scale), 0, 65535).astype(np.uint16)

    def clearance_px(uv: np.ndarray, pattern: bool = True) -> np.ndarray:
        r = camera.rays(uv)
        cosi = np.abs(r @ n)
        lam = (n @ T[:3, 3]) / (r @ n)
        p = r * lam[:, None]
        xy = p @ T[:3, :3] - T[:3, :3].T @ T[:3, 3]  # board frame (x, y, ~0)
        # mm per pixel on the board: depth / f, stretched by the obliquity
        mm_px = np.abs(lam) / camera.fx / np.maximum(cosi, 0.2)
        return edge_clearance(board, xy[:, :2], pattern=pattern) / mm_px

    # the difference's own noise sets the floor: the stripe stands NOISE_K sigmas above it
    noise = scale * _robust_noise(diff_f[::7, ::7])
    floor = NOISE_K * noise
    # The stripe's level differs by the albedo ratio (~10x) between the board's light and
    # dark areas: a threshold set by the brightest part would lose the stripe on the plate
    # of a light-circles board. Centres are taken on the plate (the circles' interiors add
    # little but noise on a dark-circles board), at the plate's own level, and on the board
    # only: the table around a dark board can be lit brighter than the board's plate.
    # The plate's pixels within margin_px of a circle are dropped before anything is measured:
    # the difference image rings there (an edge seen at two exposures), and on a board of light
    # circles those rings outnumber the faint stripe; no centre near an edge is used anyway.
    light = _light_mask(board_image)
    plate = (~light if board.circles == "light" else light).astype(np.uint8)
    k = 2 * int(np.ceil(margin_px)) + 1
    plate = cv2.erode(plate, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(bool)
    area = _board_area(camera, T, board, diff.shape)
    dm = np.where(plate & area, diff, 0)
    peak = _peak(dm)
    if peak <= floor and (anywhere := _peak(diff)) > floor:
        raise CalibrationError(
            f"{name}: no laser stripe on the board: the stripe (peak difference "
            f"{anywhere / scale:.1f}) lies off the board's plate (there {peak / scale:.1f}, needs "
            f"> {floor / scale:.1f}: {NOISE_K:g} noise sigmas)"
        )
    if peak <= floor:
        raise CalibrationError(
            f"{name}: no laser stripe on the board: the laser-on image is no brighter than the "
            f"lasers-off image (peak difference {peak / scale:.1f}, needs > {floor / scale:.1f}: "
            f"{NOISE_K:g} noise sigmas)"
        )
    thr = max(threshold * peak, floor * 0.5)
    axis = _stripe_axis(dm, thr, lambda uv: clearance_px(uv) > 0)
    albedo = None
    detect = None
    if normalise_albedo:
        other = light if board.circles == "light" else ~light  # the class the plate is not
        found = albedo_gain(diff_f, a * board_image.astype(np.float32) + b, plate, other, area,
                            axis, floor / scale, clearance_px)
        if found is not None:
            gain, albedo = found
            # the stripe everywhere at its level on the plate: the same threshold holds
            diff = np.clip(np.round(diff_f * gain * scale), 0, 65535).astype(np.uint16)
            dm = np.where(area, diff, 0)
            # runs are found only near pixels where the raw difference stands NOISE_K sigmas
            # above its noise: the gain lifts the dark class's noise with its stripe (and a
            # JPEG's ringing beside it), and those runs crowd the stripe's own (flagged close
            # or merged) though none of them is light; the stripe's own run keeps its extent
            # at the threshold (the mask grown by a pixel)
            strong = (diff_f > floor / scale).astype(np.uint8)
            strong = cv2.dilate(strong, np.ones((3, 3), np.uint8))
            detect = np.where(strong.astype(bool), dm, 0).astype(np.uint16)
    img = dm if axis == "column" else np.ascontiguousarray(dm.T)
    if detect is not None and axis != "column":
        detect = np.ascontiguousarray(detect.T)
    c = grey_centre(img, min_width=2.0, max_width=80.0, pad=PAD_PX, level=thr, data_max=65535.0,
                    detect=detect)
    ok = (c["flags"] & ~np.uint8(4)) == 0  # saturation of the difference is harmless
    col, v, width = c["u"][ok], c["v"][ok], c["width"][ok]
    n_centres = int(ok.sum())
    if albedo is not None and len(col):
        # a centre must stand on its own data: the albedo gain lifts the dark class's noise
        # with its stripe, and runs of that noise alone cross the threshold; the raw difference
        # at the centre (3 x 3 pixels) must stand NOISE_K sigmas above the noise
        iu, iv = (col, v) if axis == "column" else (v, col)
        iu = np.round(iu).astype(int)
        iv = np.round(iv).astype(int)
        h_img, w_img = diff_f.shape
        raw = np.max([diff_f[np.clip(iv + dv, 0, h_img - 1), np.clip(iu + du, 0, w_img - 1)]
                      for du in (-1, 0, 1) for dv in (-1, 0, 1)], axis=0)
        strong = raw > floor / scale
        col, v, width = col[strong], v[strong], width[strong]
    # each centre's window: its run ± pad ± background pixels
    half = 0.5 * width + PAD_PX + 3
    reach = int(np.ceil(half.max())) if len(half) else 0
    steps = np.arange(-reach, reach + 1)
    rows = v[:, None] + steps[None, :]
    inwin = np.abs(steps[None, :]) <= half[:, None]
    cols = np.broadcast_to(col[:, None], rows.shape)
    uv = np.stack([cols, rows], -1) if axis == "column" else np.stack([rows, cols], -1)
    centres = np.column_stack([col, v]) if axis == "column" else np.column_stack([v, col])
    # the whole window clear of every albedo edge, or, with the albedo taken out, the centre
    # clear of the pattern's edges and the window on the board
    clear = np.full(rows.shape, np.inf)
    if inwin.any():
        clear[inwin] = clearance_px(uv[inwin], pattern=albedo is None)
    good = np.all(clear >= margin_px, axis=1)
    if albedo is not None and len(centres):
        good &= clearance_px(centres.astype(np.float64)) >= margin_px
    centres = centres[good]
    if len(centres) < MIN_CENTRES:
        raise CalibrationError(
            f"{name}: no laser stripe on the board: {len(centres)} stripe centres clear of the "
            f"circles and the board's edge (of {n_centres} found), at least {MIN_CENTRES} needed"
        )
    pts = board_plane_points(camera, T, centres)
    iu = np.clip(np.round(centres[:, 0]).astype(int), 0, light.shape[1] - 1)
    iv = np.clip(np.round(centres[:, 1]).astype(int), 0, light.shape[0] - 1)
    on_other = (light if board.circles == "light" else ~light)[iv, iu]
    return PoseStripe(pts, centres, T, pose.rms_px, axis, n_centres, albedo, on_other,
                      np.asarray(det.points, dtype=np.float64), bias_correction)


def albedo_gain(
    diff: np.ndarray,
    ambient: np.ndarray,
    plate: np.ndarray,
    other: np.ndarray,
    area: np.ndarray,
    axis: str,
    floor: float,
    clearance_px: Any,
    degree: int = 3,
    min_samples: int = 8,
) -> tuple[np.ndarray, dict] | None:
    """Per-pixel gain that takes the board's albedo out of laser minus ambient, and its figures.

    The stripe is laser irradiance times albedo; the ambient image (lasers-off, scaled to the
    laser image's exposure) is room light times albedo plus the sensor's black level ``c``,
    which is not known. The stripe's own peak in each profile (log), fitted as a smooth
    function along the stripe (Legendre, ``degree``) plus a step on the ``other`` class, gives
    the classes' albedo ratio ``r``; with the classes' ambient levels ``S_p`` (``plate``) and
    ``S_o``, ``r = (S_o - c) / (S_p - c)`` gives ``c``. The gain ``(S_p - c) / (ambient - c)``
    brings the stripe everywhere to its level on the plate, through the blur of the edges too
    (to first order). None when either class has fewer than ``min_samples`` profiles whose
    peak is 2 px clear of the edges, or the classes differ too little to need it.
    """
    d = diff if axis == "column" else diff.T
    am = area if axis == "column" else area.T
    masked = np.where(am, d, -np.inf)
    rows = np.argmax(masked, axis=0)
    cols = np.arange(d.shape[1])
    peak = masked[rows, cols]
    ok = np.isfinite(peak) & (peak > floor)
    if ok.sum() < 2 * min_samples:
        return None
    cols, rows, peak = cols[ok], rows[ok], peak[ok]
    uv = np.column_stack([cols, rows]) if axis == "column" else np.column_stack([rows, cols])
    iu, iv = uv[:, 0], uv[:, 1]
    on_other, on_plate = other[iv, iu], plate[iv, iu]
    keep = (on_other | on_plate) & (clearance_px(uv.astype(np.float64)) >= 2.0)
    if (keep & on_other).sum() < min_samples or (keep & on_plate).sum() < min_samples:
        return None
    s = cols[keep].astype(np.float64)
    s = 2.0 * (s - s.min()) / max(float(np.ptp(s)), 1.0) - 1.0
    A = np.column_stack([np.polynomial.legendre.legvander(s, degree), on_other[keep]])
    y = np.log(peak[keep])
    inl = np.ones(len(y), bool)
    for _ in range(4):  # speckle and glints: profiles far off the fit say nothing of the albedo
        coef = np.linalg.lstsq(A[inl], y[inl], rcond=None)[0]
        res = y - A @ coef
        sig = 1.4826 * float(np.median(np.abs(res[inl] - np.median(res[inl])))) or 1e-6
        inl = np.abs(res) <= 3.0 * sig
    r = float(np.exp(coef[-1]))
    s_p = float(np.median(ambient[plate & area]))
    s_o = float(np.median(ambient[other & area]))
    if (r < 1.0) != (s_o < s_p) or abs(1.0 - r) < 0.05:
        return None
    c = (s_o - r * s_p) / (1.0 - r)
    lowest = min(s_o, s_p)
    if not c < lowest:  # the stripe and the ambient disagree: no gain rather than a wrong one
        return None
    shade = np.maximum(ambient - c, 0.25 * (lowest - c))
    return ((s_p - c) / shade).astype(np.float32), {"ratio": r, "black_level": c,
                                                    "profiles": int(inl.sum())}


def ambient_model(board_image: np.ndarray, laser_image: np.ndarray, step: int = 3) -> tuple[float, float]:
    """``(a, b)`` with ``laser ≈ a · board + b`` off the stripe: the same scene at another exposure.

    A robust start (a line through the medians of the laser image in bins of the board
    image's level, which the few stripe pixels cannot move), then least squares on a
    subsample without the pixels beyond 3 robust sigmas (the stripe, saturated pixels).
    """
    x = board_image[::step, ::step].astype(np.float64).ravel()
    y = laser_image[::step, ::step].astype(np.float64).ravel()
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, 33)))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(len(edges) - 2, 0))
    bins = [k for k in range(len(edges) - 1) if np.count_nonzero(idx == k) >= 10]
    if len(bins) >= 2:
        xm = np.array([np.median(x[idx == k]) for k in bins])
        ym = np.array([np.median(y[idx == k]) for k in bins])
        a, b = np.polyfit(xm, ym, 1)
    else:  # a flat lasers-off image: only an offset
        a, b = 0.0, float(np.median(y))
    for _ in range(3):
        r = y - (a * x + b)
        sigma = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 0.5)
        keep = np.abs(r - np.median(r)) <= 3.0 * sigma
        if keep.sum() < 3 or np.ptp(x[keep]) == 0:
            break
        a, b = np.polyfit(x[keep], y[keep], 1)
    return float(a), float(b)


def group_sigma(residuals: np.ndarray, groups: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """Each point's noise (N,): the robust sigma (1.4826 MAD) of its group's inlier residuals
    (all of the group's where fewer than 5 are inliers)."""
    r = np.asarray(residuals, dtype=np.float64)
    sigma = np.empty(len(r))
    for k in np.unique(groups):
        mk = groups == k
        rk = r[mk & inliers] if (mk & inliers).sum() >= 5 else r[mk]
        sigma[mk] = 1.4826 * np.median(np.abs(rk - np.median(rk)))
    return np.maximum(sigma, 1e-12)


def robust_plane(
    points: np.ndarray,
    trim: float = 3.0,
    samples: int = 300,
    seed: int = 0,
    groups: np.ndarray | None = None,
    noise_groups: np.ndarray | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Plane ``(n, d)`` through points (N, 3) and the inlier mask: LMedS start, trimmed LSQ.

    ``noise_groups`` (N,) labels points that share a noise level (e.g. pose and albedo class:
    where the noise is additive, the stripe on the dark class is the noisier; where speckle
    rules, it is not). Each group's robust sigma, measured on the residuals, trims it and
    weights it (1 / sigma^2) in the least squares; by default one sigma for all.

    ``groups`` (N,) names the board pose of each point. One pose's stripe is a line, and
    the plane of its board holds it exactly: with poses of unequal size a plain median would
    pick that board plane. So each candidate plane is drawn from two poses or more and
    scored by the median, over poses, of each pose's median residual (the largest of
    them for two poses): the plane must fit most poses, not most points.
    """
    p = np.asarray(points, dtype=np.float64)
    rng = np.random.default_rng(seed)
    g = np.zeros(len(p), dtype=np.int64) if groups is None else np.unique(groups, return_inverse=True)[1]
    ng = int(g.max()) + 1 if len(g) else 0
    idx = rng.integers(0, len(p), size=(samples * (4 if ng > 1 else 1), 3))
    if ng > 1:
        idx = idx[~((g[idx[:, 0]] == g[idx[:, 1]]) & (g[idx[:, 1]] == g[idx[:, 2]]))][:samples]
    a, b, c = p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]]
    nn = np.cross(b - a, c - a)
    norm = np.linalg.norm(nn, axis=1)
    ok = norm > 1e-9 * np.max(norm)
    nn = nn[ok] / norm[ok, None]
    dd = -np.sum(nn * a[ok], axis=1)
    res = np.abs(p @ nn.T + dd)
    per_pose = np.stack([np.median(res[g == k], axis=0) for k in range(ng)])
    med = per_pose.max(axis=0) if ng == 2 else np.median(per_pose, axis=0)
    best = int(np.argmin(med))
    n, d = nn[best], dd[best]
    ng_ = np.zeros(len(p), dtype=np.int64) if noise_groups is None else \
        np.unique(noise_groups, return_inverse=True)[1]
    inl = np.ones(len(p), dtype=bool)
    for _ in range(50):
        r = plane_distance(p, n, d)
        sigma = group_sigma(r, ng_, inl)
        new = np.abs(r) <= trim * sigma
        if new.sum() < 3:
            break
        n, d = fit_plane(p[new], 1.0 / sigma[new] ** 2)
        if np.array_equal(new, inl):
            break
        inl = new
    return n, float(d), inl


def camera_jacobian(
    camera: Camera, board: Board, stripes: list[PoseStripe], inliers: np.ndarray,
    weights: np.ndarray, normal: np.ndarray, d: float, steps: np.ndarray,
) -> np.ndarray:
    """How the fitted plane follows the camera: d(tilt e1, tilt e2, d) / d(fx fy cx cy k1 k2 p1
    p2 k3), (3, 9), by central differences of ``steps`` (9,).

    For each step every board pose is found again with the changed camera (PnP on the same
    detected points), its stripe pixels are carried onto that board plane and the plane is
    fitted again to the same inliers with the same weights. A camera error moves the planes
    with it, so that near the boards triangulation partly undoes it: drawing the camera and
    the planes independently would miss that.
    """
    E = plane_tilt_basis(normal)
    J = np.zeros((3, 9))
    for j in range(9):
        vals = []
        for sign in (1.0, -1.0):
            x = np.zeros(9)
            x[j] = sign * steps[j]
            cam = camera.perturbed(x)
            pts = np.concatenate([
                board_plane_points(cam, board_pose(cam, board, st.board_points,
                                                   bias_correction=st.bias_correction).T_cam_board,
                                   st.uv) for st in stripes])
            n, dd = fit_plane(pts[inliers], weights)
            if n @ normal < 0:
                n, dd = -n, -dd
            vals.append(np.array([(n - normal) @ E[0], (n - normal) @ E[1], dd - d]))
        J[:, j] = (vals[0] - vals[1]) / (2 * steps[j])
    return J


def _read_pose_images(view, shape, channel: str | None):
    """(lasers-off image or None, laser image, detection image or None) of one pose.

    Colour images: the stripe is measured on the laser's channel (``sensor.channel``, or the
    channel where laser minus board, brought to the laser image's exposure, is brightest); the
    board is found in the lasers-off image's luminance, or with the laser always on in the
    other channel that shows the board with most contrast and least stripe.
    """
    from crossline.io.images import read_image, read_image_channels

    la = read_image_channels(view.laser_image)
    if la.shape[:2] != tuple(shape):
        raise CalibrationError(f"{view.laser_image}: image is {la.shape[1]}x{la.shape[0]} px, "
                               f"expected {shape[1]}x{shape[0]} px")
    b = None if view.board_image is None else read_image(view.board_image, shape)
    if la.shape[2] == 1:
        return b, la[:, :, 0], None
    names = ("red", "green", "blue")
    bc = None if view.board_image is None else read_image_channels(view.board_image)
    if channel in names:
        k = names.index(channel)
    else:  # auto: the channel the stripe is brightest in, above the board or its opening
        score = []
        for j in range(3):
            ref = bc[:, :, j] if bc is not None and bc.shape[2] == 3 else remove_stripe(la[:, :, j])[0]
            # the laser image may be taken at another exposure than the board view: compare
            # it with the board view brought to its exposure, as the stripe is measured
            a, b = ambient_model(ref, la[:, :, j])
            score.append(float(np.quantile(la[:, :, j].astype(np.float32) - (a * ref.astype(np.float32) + b),
                                           0.999)))
        k = int(np.argmax(score))
    if bc is None:  # laser always on: the board in the other channel that shows it best
        best = max((j for j in range(3) if j != k), key=lambda j: float(np.std(la[::4, ::4, j])))
        return None, la[:, :, k], la[:, :, best]
    b = bc[:, :, k] if bc.shape[2] == 3 else bc[:, :, 0]
    return b, la[:, :, k], read_image(view.board_image, shape)


def run_calibrate_lasers(
    capture: str | Path,
    camera_json: str | Path,
    out: str | Path,
    *,
    threshold: float = 0.2,
    trim: float = 3.0,
    threads: int = 1,
    margin_px: float = 4.0,
) -> LaserPlanes:
    """Stage: fit the plane of each of the rig's lasers (A, or A and B) and write ``lasers.json``.

    A pose that cannot be used (board not found, no stripe on it, unreadable image) is skipped
    with its reason, listed in ``lasers.json`` and the log; the stage fails only when a laser
    keeps fewer than ``MIN_POSES`` poses, naming every pose and why.
    """
    from crossline.io.capture import open_capture

    cv2.setNumThreads(1)  # parallelism comes from our pool of `threads` workers (determinism)
    cap = open_capture(capture)
    camera = Camera.load(camera_json)
    board = cap.rig.board
    shape = (cap.rig.sensor.height, cap.rig.sensor.width)
    channel = getattr(cap.rig.sensor, "channel", None)
    lasers = tuple(getattr(cap.rig, "lasers", LASERS))

    def one(view) -> tuple[Any, PoseStripe | None, str]:
        name = str(view.laser_image.relative_to(cap.root))
        board_name = None if view.board_image is None else str(view.board_image.relative_to(cap.root))
        try:
            b, la, det = _read_pose_images(view, shape, channel)
            s = stripe_points(camera, board, b, la, threshold=threshold, margin_px=margin_px,
                              name=name, board_name=board_name, detect_image=det)
        except CrosslineError as exc:
            return view, None, str(exc)
        return view, s, ""

    jobs = [v for laser in lasers for v in cap.laser_views.get(laser, [])]
    if threads > 1:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            results = list(pool.map(one, jobs))
    else:
        results = [one(v) for v in jobs]
    planes = {}
    failures = []
    for laser in lasers:
        mine = [(v, s) for v, s, _ in results if v.laser == laser and s is not None]
        skipped = [{"pose": v.pose, "laser_image": str(v.laser_image.relative_to(cap.root)), "reason": why}
                   for v, s, why in results if v.laser == laser and s is None]
        for k in skipped:
            log.warning("laser %s: pose %s skipped: %s", laser, k["pose"], k["reason"])
        if len(mine) < MIN_POSES:
            used = [f"    - {v.pose}: usable, {len(s.points)} stripe points" for v, s in mine]
            why = [f"    - {k['pose']}: {k['reason']}" for k in skipped]
            n_views = len(cap.laser_views.get(laser, []))
            failures.append(f"  laser {laser}: {len(mine)} usable pose{'s' * (len(mine) != 1)} of "
                            f"{n_views}, at least {MIN_POSES} needed\n" + "\n".join(used + why))
            continue
        while True:
            pts = np.concatenate([s.points for _, s in mine])
            pose_of = np.concatenate([np.full(len(s.points), i) for i, (_, s) in enumerate(mine)])
            other = np.concatenate([s.on_other for _, s in mine])
            noise = 2 * pose_of + other  # pose x albedo class: groups that share a noise level
            nrm, d, inl = robust_plane(pts, trim=trim, groups=pose_of, noise_groups=noise)
            # a pose whose kept centres scatter by pixels about the others' plane found
            # something else than the stripe: skipped with its reason, while enough remain
            px = np.abs(plane_distance(pts, nrm, d)) * camera.fx / np.abs(pts[:, 2])
            rms = [float(np.sqrt(np.mean(px[(pose_of == i) & inl] ** 2)))
                   if np.any((pose_of == i) & inl) else 0.0 for i in range(len(mine))]
            worst = int(np.argmax(rms))
            if rms[worst] <= MAX_PLANE_RMS_PX or len(mine) <= MIN_POSES:
                break
            v, _ = mine.pop(worst)
            skipped.append({"pose": v.pose, "laser_image": str(v.laser_image.relative_to(cap.root)),
                            "reason": f"its stripe centres lie {rms[worst]:.1f} px RMS off the plane "
                                      f"of the other poses (at most {MAX_PLANE_RMS_PX:g} px): not all "
                                      "the stripe's (a heavily compressed image, glints?)"})
            log.warning("laser %s: pose %s skipped: %s", laser, v.pose, skipped[-1]["reason"])
        k = 0
        poses = []
        for v, s in mine:
            m = len(s.points)
            sl = inl[k : k + m]
            r = plane_distance(s.points[sl], nrm, d)
            poses.append({
                "pose": v.pose,
                "board_image": None if v.board_image is None else str(v.board_image.relative_to(cap.root)),
                "laser_image": str(v.laser_image.relative_to(cap.root)),
                "profiles": s.axis,
                "n_centres": s.n_centres,
                "albedo": s.albedo,
                "n_points": m,
                "n_used": int(sl.sum()),
                "rms_mm": float(np.sqrt(np.mean(r**2))) if len(r) else None,
                "board_rms_px": s.board_rms_px,
                "T_cam_board": s.T_cam_board,
            })
            k += m
        r = plane_distance(pts[inl], nrm, d)
        # the scatter about the plane in pixels at the points' depth: a centre is good to a
        # fraction of a pixel, so pixels of scatter mean centres that are not the stripe's
        rms_px = float(np.sqrt(np.mean((r * camera.fx / np.abs(pts[inl, 2])) ** 2)))
        if rms_px > MAX_PLANE_RMS_PX:
            per_pose = ", ".join(f"{q['pose']} {q['rms_mm']:.3f} mm" for q in poses
                                 if q["rms_mm"] is not None)
            failures.append(
                f"  laser {laser}: its stripe points lie {float(np.sqrt(np.mean(r**2))):.3f} mm RMS "
                f"off their plane, {rms_px:.1f} px at their depth (at most {MAX_PLANE_RMS_PX:g} px): "
                f"the centres are not all the stripe's (a heavily compressed image, glints?); "
                f"RMS per pose: {per_pose}")
            continue
        sigma = group_sigma(plane_distance(pts, nrm, d), noise, inl)
        cov = plane_covariance(pts[inl], nrm, d, weights=1.0 / sigma[inl] ** 2,
                               clusters=pose_of[inl])
        std = (camera.extra.get("uncertainty") or {}).get("std") or {}
        steps = np.array([float(std.get(k) or 0.0) for k in CAMERA_PARAMETERS])
        # a parameter fixed at 0 (std 0) still gets a finite step: its column is then unused
        steps = np.where(steps > 0, steps, [0.1, 0.1, 0.1, 0.1, 1e-4, 1e-4, 1e-6, 1e-6, 1e-4])
        J_cam = camera_jacobian(camera, board, [st for _, st in mine], inl, 1.0 / sigma[inl] ** 2,
                                nrm, d, steps)
        planes[laser] = LaserPlane(nrm, d, {
            "rms_mm": float(np.sqrt(np.mean(r**2))),
            "rms_px": rms_px,
            "covariance": {
                "parameters": ["tilt_e1_rad", "tilt_e2_rad", "d_mm"],
                "tilt_basis": plane_tilt_basis(nrm).tolist(),
                "matrix": cov.tolist(),
                "camera_parameters": list(CAMERA_PARAMETERS),
                "camera_jacobian": J_cam.tolist(),
                "note": "1 sigma: the weighted fit's own, or where larger the scatter between "
                        "poses (cluster-robust); n' ∝ n + a e1 + b e2, d' = d + δd. The camera "
                        "calibration's error, common to every pose, is not in the matrix: "
                        "camera_jacobian (3 x 9, per unit of each camera parameter) carries it",
            },
            "n_points": len(pts),
            "n_used": int(inl.sum()),
            "n_rejected": int((~inl).sum()),
            "poses": poses,
            "skipped_poses": skipped,
        })
        log.info("laser %s: n = %s, d = %.4f mm, RMS %.4f mm over %d points (%d rejected), "
                 "%d poses used, %d skipped", laser, np.round(nrm, 6), d, planes[laser].extra["rms_mm"],
                 inl.sum(), (~inl).sum(), len(mine), len(skipped))
    if not failures and "A" not in planes:
        failures.append(f"  the rig's lasers {list(lasers)}: a one-laser rig names its laser A")
    if failures:
        raise CalibrationError(f"capture {cap.root}: laser planes cannot be calibrated:\n"
                               + "\n".join(failures))
    result = LaserPlanes(planes["A"], planes.get("B"), {
        "parameters": {"threshold": threshold, "trim": trim, "margin_px": margin_px},
    })
    result.save(out)
    return result

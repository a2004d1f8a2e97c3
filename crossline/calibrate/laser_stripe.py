"""The laser stripe on the board in one pose: its centres and their points on the board plane.

``stripe_points`` (steps 1 to 4 of :mod:`crossline.calibrate.lasers`' docstring): the board's
pose, laser-on minus lasers-off, the threshold on the board's plate, the profiles' direction
(``_stripe_axis``), grey-centre per profile with the albedo taken out, the centres clear of the
albedo edges, and their rays met with the board plane, in a :class:`PoseStripe`. Split from
``crossline.calibrate.lasers`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.detect import detect_board
from crossline.calibrate.laser_albedo import _light_mask, albedo_gain
from crossline.calibrate.laser_background import NOISE_K, _robust_noise, ambient_model, remove_stripe
from crossline.calibrate.laser_board import _board_area, board_plane_points, edge_clearance
from crossline.calibrate.pose import board_pose
from crossline.camera import Camera
from crossline.errors import CalibrationError

__all__ = ["PoseStripe", "stripe_points"]

MIN_CENTRES = 20  # fewer stripe centres on the board than this: no stripe
PAD_PX = 3  # how far the grey-centre window reaches beyond the run above threshold


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
    corners_missing: int = 0  # chessboard corners under the stripe, left out of the pose (always on)


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


MAX_MISSING_CORNERS = 0.25  # share of a chessboard's corners the stripe may hide (always on)


def _check_under_stripe(camera: Camera, board: Board, T: np.ndarray, det, stripe_mask: np.ndarray,
                        refusal: str) -> None:
    """Accept a board pose fitted without the chessboard corners that could not be refined,
    if the laser stripe (removed from the image) drew across them: each lies within the
    refinement's reach (half a square) of the stripe's line, or its removal painted over the
    corner's window (a quarter square), and most corners are left.
    Otherwise the board was not seen well enough: raise ``refusal``.

    The line, not the stripe's pixels: on the dark squares the stripe is too faint to be
    removed, and there it spoils the corners it crosses without being in the mask. A plane's
    stripe on a flat board is a straight line (to the lens distortion over a square or two).
    """
    from crossline.calibrate.pose import project_board

    uv = project_board(camera, board, T)
    grid = uv.reshape(board.rows, board.cols, 2)
    square = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1)))
    near = np.zeros(int(det.missing.sum()), dtype=bool)
    # the stripe's pixels on the board (its corners' outline grown by a square): beyond the
    # board the stripe lies on the table, on another line
    c = grid[[0, 0, -1, -1], [0, -1, -1, 0]]
    c = c + (c - c.mean(0)) * (square / np.linalg.norm(c - c.mean(0), axis=1))[:, None]
    on_board = np.zeros(stripe_mask.shape, np.uint8)
    cv2.fillConvexPoly(on_board, np.round(c).astype(np.int32), 1)
    ys, xs = np.nonzero(stripe_mask & on_board.astype(bool))
    q = uv[det.missing]
    if len(xs) >= 2:
        vx, vy, x0, y0 = cv2.fitLine(np.column_stack([xs, ys]).astype(np.float32), cv2.DIST_HUBER,
                                     0, 0.01, 0.01).ravel()
        near = np.abs((q[:, 0] - x0) * vy - (q[:, 1] - y0) * vx) <= 0.5 * square
    # or where the removal itself painted over the corner's window (a piece it took for the
    # stripe's: the opening's residues at corners line up along the board's rows)
    dist = cv2.distanceTransform((~stripe_mask).astype(np.uint8), cv2.DIST_L2, 3)
    k = np.round(q).astype(np.int64)
    h, w = dist.shape
    inside = (k[:, 0] >= 0) & (k[:, 0] < w) & (k[:, 1] >= 0) & (k[:, 1] < h)
    near[inside] |= dist[k[inside, 1], k[inside, 0]] <= 0.25 * square
    share = float(det.missing.mean())
    if not near.all() or share > MAX_MISSING_CORNERS:
        why = (f"{int((~near).sum())} of them away from the laser stripe" if not near.all()
               else f"{100 * share:.0f} % of the corners, more than the stripe may hide "
                    f"({100 * MAX_MISSING_CORNERS:.0f} %)")
        raise CalibrationError(f"{refusal} ({why})")


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
    stripe_mask = None
    if board_image is None:
        board_image, stripe_mask = remove_stripe(laser_image)
        where, name_board = "laser image (laser always on; stripe removed)", name
        if detect_image is not None:
            detect_image, stripe_mask = remove_stripe(detect_image)
    det = detect_board(board_image if detect_image is None else detect_image, board,
                       partial=stripe_mask is not None)
    if not det.found:
        raise CalibrationError(f"{name_board}: {det.reason} in the {where} of this pose")
    pose = board_pose(camera, board, det.points, bias_correction=bias_correction)
    if det.missing is not None and det.missing.any():
        _check_under_stripe(camera, board, pose.T_cam_board, det, stripe_mask,
                            f"{name_board}: {det.reason} in the {where} of this pose")
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
                      np.asarray(det.points, dtype=np.float64), bias_correction,
                      0 if det.missing is None else int(det.missing.sum()))

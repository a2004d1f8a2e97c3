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

The code is split by idea (issue 21.3): ``laser_board`` (the board plane, its usable area and
albedo edges), ``laser_background`` (the exposure model, the stripe's removal),
``laser_albedo`` (the albedo classes and gain), ``laser_stripe`` (one pose's stripe points),
``laser_plane_fit`` (the robust plane and its camera Jacobian). This module keeps the stage
(``run_calibrate_lasers`` and the reading of a pose's images) and re-exports the names its
importers use.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.calibrate.laser_albedo import albedo_gain
from crossline.calibrate.laser_background import ambient_model, remove_stripe
from crossline.calibrate.laser_board import board_plane_points, edge_clearance
from crossline.calibrate.laser_plane_fit import camera_jacobian, group_sigma, robust_plane
from crossline.calibrate.laser_stripe import PoseStripe, stripe_points
from crossline.camera import CAMERA_PARAMETERS, Camera
from crossline.errors import CalibrationError, CrosslineError
from crossline.geometry import plane_covariance, plane_distance, plane_tilt_basis
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

MIN_POSES = 2  # usable poses per laser: one pose's stripe is a line, two span the plane
# the plane's inlier scatter, in pixels at the points' depth, beyond which its centres are
# not the stripe's (good stripes scatter by a tenth of a pixel or so)
MAX_PLANE_RMS_PX = 3.0


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
            if s.corners_missing:  # laser always on: chessboard corners the stripe spoilt
                poses[-1]["board_corners_missing"] = s.corners_missing
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

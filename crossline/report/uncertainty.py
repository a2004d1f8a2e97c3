"""Measurement uncertainty of the report's figures by Monte Carlo (GUM Supplement 1).

What is drawn, and what is not:

* **camera**: intrinsics and distortion from the bundle adjustment's covariance
  (``camera.json`` ``uncertainty.covariance``);
* **laser planes**: each plane's tilts and offset from its fit's covariance
  (``lasers.json`` ``<laser>.covariance``: the fit's own or the scatter between poses);
* **hand-eye**: ``X`` from its refinement's covariance (``handeye.json``
  ``methods.refined.uncertainty.covariance_X``), ``X_true = X exp(ω, t)``;
* **arm**: every frame's arm pose error left in the cloud, drawn by the fuse stage
  (``<scan>.arm.npz``, :mod:`crossline.io.arm_draws`): from the pose refinement's posterior
  (perturb-and-MAP on its normal equations) where the scan was refined, else from the arm's
  prior (its noise as the hand-eye views estimated it, or its stated precision; a drift
  correlated in time plus a white part); each point moves
  with its frame's drawn error. This is the error the frames of one pass share, which no
  resampling of frames sees;
* **repeatability**: the scan's frames drawn again with replacement (a bootstrap over frames):
  what the stripe centres' noise, the speckle and the arm's pose noise of each frame do to a
  figure, as this scan realised them (the arm's white part is thus counted twice, once here
  and once in ``arm``: a small overstatement, on the safe side).

Each draw re-triangulates the scan's own stripe centres: every point of the report's cloud is
carried back to its camera frame and pixel with the calibration it was made with, then forward
with the drawn calibration, and its move is added to it (so pose refinement and outlier removal
stay as the report had them). The figure is measured again with the report's own definition and
segmentation (the points the report used for each face, the ball's inliers). A camera draw
moves the laser planes with it (each plane's camera Jacobian: the boards' poses and the stripe
points found again with that camera), since the planes were fitted through the camera; the
planes' own draw adds their fit's noise, and ``X`` is drawn on its own (its share of the
camera's error is neglected). Not covered: the camera's model error where distortion terms
were fixed, the arm's systematic (volumetric) error beyond what hand-eye absorbed, an arm
whose true precision is worse than the prior (``fuse.arm_precision_mm``), the
nominal artefact's own calibration, and temperature.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from crossline.camera import Camera
from crossline.geometry import fit_plane, invert_transform, rotvec_to_matrix
from crossline.laser import LaserPlane, LaserPlanes
from crossline.report.gauge_block import gauge_groups, normal_within_frames
from crossline.scan.triangulate import triangulate

__all__ = [
    "CONTRIBUTORS",
    "CalibrationModel",
    "ScanPoints",
    "ball_bar_figures",
    "calibration_model",
    "draw_calibration",
    "freeform_figures",
    "gauge_figures",
    "monte_carlo",
    "plane_figures",
    "scan_points",
    "sphere_figures",
    "subsample",
]

CONTRIBUTORS = ("camera", "laser_planes", "handeye", "arm", "repeatability")
COVERAGE_FACTOR = 2.0
METHOD = ("GUM Supplement 1 Monte Carlo: the scan's stripe centres re-triangulated with the camera, "
          "the laser planes (moved with the camera by their camera Jacobian) and hand-eye X drawn "
          "from their covariances, every frame moved by a draw of the arm's pose error left in "
          "it (the pose refinement's posterior, else the arm's prior), and the scan's frames "
          "drawn again with replacement; each "
          "figure measured again with the report's definition and segmentation")
GN_STEPS = 6


@dataclass(frozen=True)
class CalibrationModel:
    """A calibration and the covariances it is drawn from (None: that part is not known)."""

    camera: Camera
    planes: LaserPlanes
    X: np.ndarray  # T_tool_cam
    camera_cov: np.ndarray | None = None  # (9, 9) over CAMERA_PARAMETERS
    plane_cov: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # basis, cov
    X_cov: np.ndarray | None = None  # (6, 6) over (ω, t), rad and mm
    missing: tuple[str, ...] = ()  # what has no covariance, in words
    plane_camera: dict[str, np.ndarray] = field(default_factory=dict)  # (3, 9) d plane / d camera


def calibration_model(camera: dict, lasers: dict, handeye: dict) -> CalibrationModel:
    """The model from the contents of camera.json, lasers.json and handeye.json."""
    cam = Camera.from_dict(camera)
    planes = LaserPlanes.from_dict(lasers)
    X = np.asarray(handeye["T_tool_cam"], dtype=np.float64)
    missing = []
    cov = (camera.get("uncertainty") or {}).get("covariance")
    cam_cov = None if cov is None else np.asarray(cov, dtype=np.float64)
    if cam_cov is None or cam_cov.shape != (9, 9):
        cam_cov = None
        missing.append("camera.json has no 9 x 9 uncertainty.covariance")
    plane_cov, plane_camera = {}, {}
    for name in planes.names:
        c = lasers[name].get("covariance") or {}
        try:
            plane_cov[name] = (np.asarray(c["tilt_basis"], dtype=np.float64).reshape(2, 3),
                               np.asarray(c["matrix"], dtype=np.float64).reshape(3, 3))
        except (KeyError, ValueError, TypeError):
            missing.append(f"lasers.json has no covariance of laser {name}'s plane")
            continue
        try:
            plane_camera[name] = np.asarray(c["camera_jacobian"], dtype=np.float64).reshape(3, 9)
        except (KeyError, ValueError, TypeError):
            missing.append(f"lasers.json has no camera_jacobian of laser {name}'s plane (the "
                           "camera's error is drawn as if the planes did not share it)")
    xc = (((handeye.get("methods") or {}).get("refined") or {}).get("uncertainty") or {}).get(
        "covariance_X")
    X_cov = None if xc is None else np.asarray(xc, dtype=np.float64)
    if X_cov is None or X_cov.shape != (6, 6):
        X_cov = None
        missing.append("handeye.json has no covariance of the refined X")
    return CalibrationModel(cam, planes, X, cam_cov, plane_cov, X_cov, tuple(missing),
                            plane_camera)


def _gaussian(cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    return V @ (np.sqrt(np.maximum(w, 0.0)) * rng.standard_normal(len(w)))


def draw_calibration(
    model: CalibrationModel, rng: np.random.Generator, parts: tuple[str, ...] = CONTRIBUTORS
) -> tuple[Camera, LaserPlanes, np.ndarray]:
    """One calibration drawn from the model's covariances, for the ``parts`` named (others as is).

    A drawn camera also moves each plane by the plane's camera Jacobian (the planes were fitted
    through that camera); the planes' own draw adds their fit's noise.
    """
    cam, planes, X = model.camera, model.planes, model.X
    dc = None
    if "camera" in parts and model.camera_cov is not None:
        dc = _gaussian(model.camera_cov, rng)
        cam = cam.perturbed(dc)
    own = "laser_planes" in parts and model.plane_cov
    if own or (dc is not None and model.plane_camera):
        drawn = {}
        for name in planes.names:
            pl = planes[name]
            if name in model.plane_cov:
                E, C = model.plane_cov[name]
                delta = _gaussian(C, rng) if own else np.zeros(3)
                if dc is not None and name in model.plane_camera:
                    # the planes were fitted through this camera: its error moves them too
                    delta = delta + model.plane_camera[name] @ dc
                a, b, dd = delta
                n = pl.normal + a * E[0] + b * E[1]
                s = np.linalg.norm(n)
                # d is the offset along the drawn normal, so scale with it (|n| is restored)
                pl = LaserPlane(n, (pl.d + dd) * s)
            drawn[name] = pl
        planes = LaserPlanes(drawn["A"], drawn.get("B"))
    if "handeye" in parts and model.X_cov is not None:
        xi = _gaussian(model.X_cov, rng)
        E = np.eye(4)
        E[:3, :3] = rotvec_to_matrix(xi[:3])
        E[:3, 3] = xi[3:]
        X = X @ E
    return cam, planes, X


@dataclass(frozen=True)
class ScanPoints:
    """A cloud's points with what re-triangulating them needs: pixel, laser, frame's rotation."""

    points: np.ndarray  # (N, 3) base frame, mm
    uv: np.ndarray  # (N, 2) px, the pixel each point was triangulated from
    laser: np.ndarray  # (N,) 'A' / 'B'
    frame_index: np.ndarray  # (N,) index into the frames (for the bootstrap)
    n_frames: int
    R_base_tool: np.ndarray  # (N, 3, 3) the rotation of each point's frame
    p_tool: np.ndarray  # (N, 3) the pixel's point on its plane, in the tool frame (model's X)
    frame: np.ndarray | None = None  # (N,) each point's frame number (for the arm's draws)


def scan_points(
    points: np.ndarray, laser: np.ndarray, frame: np.ndarray, frame_ids: np.ndarray,
    T_base_tool: np.ndarray, model: CalibrationModel,
) -> ScanPoints:
    """Carry each point back to its camera frame and pixel (its frame's arm pose and ``X``).

    Points whose frame is not in ``frame_ids`` are refused (ValueError): their pose is unknown.
    """
    P = np.asarray(points, dtype=np.float64)
    frame = np.asarray(frame, dtype=np.int64)
    order = np.argsort(frame_ids)
    ids = np.asarray(frame_ids, dtype=np.int64)[order]
    k = np.clip(np.searchsorted(ids, frame), 0, max(len(ids) - 1, 0))
    if len(ids) == 0 or not np.all(ids[k] == frame):
        bad = np.unique(frame[ids[k] != frame]) if len(ids) else np.unique(frame)
        raise ValueError(f"{len(bad)} frame(s) of the cloud are not in frames.csv (e.g. {bad[:3]})")
    T = np.asarray(T_base_tool, dtype=np.float64)[order][k]  # (N, 4, 4)
    p_tool = np.einsum("nji,nj->ni", T[:, :3, :3], P - T[:, :3, 3])
    Xi = invert_transform(model.X)
    uv = model.camera.project(p_tool @ Xi[:3, :3].T + Xi[:3, 3])
    laser = np.asarray(laser).astype(str)
    # the reference is the pixel's own point on its plane: a refined pose moved the cloud's
    # point off it by the correction, which is not the calibration's to undo
    q0 = triangulate(model.camera, model.planes, uv, laser)
    used, fidx = np.unique(k, return_inverse=True)
    return ScanPoints(P, uv, laser, fidx, len(used), T[:, :3, :3],
                      q0 @ model.X[:3, :3].T + model.X[:3, 3], frame)


def moved_points(sp: ScanPoints, camera: Camera, planes: LaserPlanes, X: np.ndarray) -> np.ndarray:
    """The scan's points (N, 3) re-triangulated with another calibration."""
    q = triangulate(camera, planes, sp.uv, sp.laser)
    p_tool = q @ X[:3, :3].T + X[:3, 3]
    return sp.points + np.einsum("nij,nj->ni", sp.R_base_tool, p_tool - sp.p_tool)


Figures = Callable[[np.ndarray, np.ndarray], dict[str, float]]


def _weighted_percentiles(x: np.ndarray, w: np.ndarray, q: tuple[float, ...]) -> np.ndarray:
    """Percentiles of x with integer weights (a bootstrap's multiplicities): np.percentile of
    x with each value repeated as often as its weight says."""
    if np.all(w == 1):
        return np.percentile(x, q)
    return np.percentile(np.repeat(x, w.astype(np.int64)), q)


def _weighted_plane(p: np.ndarray, w: np.ndarray, like: np.ndarray) -> tuple[np.ndarray, float]:
    n, d = fit_plane(p, w)
    return (n, d) if float(n @ like) >= 0 else (-n, -d)


def gauge_figures(g: Any, points: np.ndarray, frame: np.ndarray | None, min_frame_points: int = 20,
                  subset: np.ndarray | None = None) -> Figures:
    """The gauge block's mean height with the report's faces held fixed.

    ``g`` is the report's :class:`~crossline.report.metrics.GaugeResult` on ``points``;
    ``frame`` the frame of each point where heights are referenced per frame; ``subset``
    (indices), if given, the points the figures are evaluated on (:func:`subsample`).
    """
    top_mask, plate_mask = (g.top_mask, g.plate_mask) if subset is None else \
        (g.top_mask[subset], g.plate_mask[subset])
    top, plate = np.flatnonzero(top_mask), np.flatnonzero(plate_mask)
    # the points the plate's plane is fitted to: the report's, less its trimmed outliers
    pm = getattr(g, "plate_plane_mask", None)
    plane = plate if pm is None else np.flatnonzero(pm if subset is None else pm[subset])
    per_frame = g.reference == "frame" and frame is not None
    if per_frame:
        fr = np.asarray(frame) if subset is None else np.asarray(frame)[subset]
        ufr, pinv = np.unique(fr[plate], return_inverse=True)
        tk = np.searchsorted(ufr, fr[top]).clip(0, max(len(ufr) - 1, 0))

    within = per_frame and g.normal_from == "frames"
    if within:
        both, group = gauge_groups(fr, plate_mask, top_mask)

    def figures(P: np.ndarray, w: np.ndarray) -> dict[str, float]:
        wp, wt = w[plate], w[top]
        if not wp.sum() > 0:  # a resampling without a frame that saw the plate: no plane
            return {"mean_mm": float("nan")}
        n = None
        if within:  # the report's normal: each frame's stripes on both faces (artefacts)
            n = normal_within_frames(P[both], group, w[both], min_ratio=0.0)
        if n is None:
            if not w[plane].sum() > 0:  # only the plate's trimmed outliers drawn
                return {"mean_mm": float("nan")}
            n, d = _weighted_plane(P[plane], w[plane], g.plate_normal)
        else:
            n = n if float(n @ g.plate_normal) >= 0 else -n
            d = -float(np.average(P[plate] @ n, weights=wp))
        h = P[top] @ n + d
        if per_frame:
            res = P[plate] @ n + d
            cnt = np.bincount(pinv, weights=(wp > 0).astype(float), minlength=len(ufr))
            off = np.bincount(pinv, weights=res * (wp > 0), minlength=len(ufr)) / np.maximum(cnt, 1)
            ok = cnt[tk] >= min_frame_points
            h, wt = h - off[tk], wt * ok
        if not wt.sum() > 0:  # a resampling without a frame that saw both faces: no height
            return {"mean_mm": float("nan")}
        return {"mean_mm": float(np.average(h, weights=wt))}

    return figures


def plane_figures(r: Any, band_mm: float) -> Figures:
    """The flat plate's flatness, RMS and share within the band (the report's plane fit)."""

    def figures(P: np.ndarray, w: np.ndarray) -> dict[str, float]:
        n, d = _weighted_plane(P, w, r.normal)
        dist = (P @ n + d)[w > 0]
        ww = w[w > 0]
        lo, hi = _weighted_percentiles(dist, ww, (2.5, 97.5))
        return {"flatness_mm": float(dist.max() - dist.min()), "flatness_95_mm": float(hi - lo),
                "rms_mm": float(np.sqrt(np.average(dist**2, weights=ww))),
                "share_within_band": float(np.average(np.abs(dist) <= band_mm, weights=ww))}

    return figures


def _sphere_from(p: np.ndarray, w: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """The weighted geometric least-squares sphere (centre, radius) of points ``p``, by
    Gauss-Newton from ``x0``: a draw moves the report's sphere by microns, so a few steps
    reach it to far below them."""
    x = np.array(x0, dtype=np.float64)
    for _ in range(GN_STEPS):
        dv = p - x[:3]
        dist = np.linalg.norm(dv, axis=1)
        J = np.column_stack([-dv / dist[:, None], -np.ones(len(p))])
        r = dist - x[3]
        Jw = J * w[:, None]
        step = np.linalg.solve(Jw.T @ J, -(Jw.T @ r))
        x += step
        if np.max(np.abs(step)) < 1e-9:
            break
    return x


def sphere_figures(s: Any, subset: np.ndarray | None = None) -> Figures:
    """The ball's diameter and form error on the report's inliers (geometric fit, weighted);
    ``subset`` (indices), if given, the points the figures are evaluated on."""
    inl = np.flatnonzero(s.inlier_mask if subset is None else s.inlier_mask[subset])
    x0 = np.r_[s.centre, s.radius]

    def figures(P: np.ndarray, w: np.ndarray) -> dict[str, float]:
        p, wi = P[inl], w[inl]
        x = _sphere_from(p, wi, x0)
        keep = wi > 0
        r = (np.linalg.norm(p - x[:3], axis=1) - x[3])[keep]
        ww = wi[keep]
        # the report's D95: the 95 % of the points closest to the sphere; p95: 2.5-97.5 %
        a95, a997 = _weighted_percentiles(np.abs(r), ww, (95.0, 99.7))
        r95, r997 = r[np.abs(r) <= a95], r[np.abs(r) <= a997]
        lo, hi = _weighted_percentiles(r, ww, (2.5, 97.5))
        return {"diameter_mm": float(2 * x[3]), "form_error_mm": float(r.max() - r.min()),
                "form_error_d95_mm": float(r95.max() - r95.min()),
                "form_error_vdi_mm": float(r997.max() - r997.min()),
                "form_error_p95_mm": float(hi - lo)}

    return figures


def ball_bar_figures(b: Any, subset: np.ndarray | None = None) -> Figures:
    """The ball bar's centre distance on the report's inliers of each ball (geometric fits,
    weighted); ``b`` the report's :class:`~crossline.report.artefacts.BallBarResult`."""
    inls = [np.flatnonzero(s.inlier_mask if subset is None else s.inlier_mask[subset])
            for s in b.balls]
    x0s = [np.r_[s.centre, s.radius] for s in b.balls]

    def figures(P: np.ndarray, w: np.ndarray) -> dict[str, float]:
        c1, c2 = (_sphere_from(P[i], w[i], x0)[:3] for i, x0 in zip(inls, x0s, strict=True))
        return {"length_mm": float(np.linalg.norm(c1 - c2))}

    return figures


def freeform_figures(P0: np.ndarray, T_nominal_cloud: np.ndarray, dev: np.ndarray,
                     grad: np.ndarray, keep: np.ndarray, tolerance_mm: float,
                     subset: np.ndarray | None = None) -> Figures:
    """A freeform's deviation from its nominal shape: mean, RMS and share within ±tolerance.

    ``P0`` (N, 3) the report's points (base frame), ``T_nominal_cloud`` its alignment, ``dev``
    and ``grad`` (N,), (N, 3) each point's signed deviation and its gradient in the nominal's
    frame (:func:`crossline.report.nominal.signed_deviation`), ``keep`` (N,) the points
    compared. A draw moves the points; their deviations follow to first order (grad · move),
    and the alignment is redone to first order too (the rigid motion that best undoes the
    deviations' change, point to plane), as the report's ICP would on the drawn cloud: a
    calibration error that only moves the part rigidly changes no deviation.
    """
    pick = np.arange(len(dev)) if subset is None else np.asarray(subset)
    k = pick[np.asarray(keep)[pick]]
    R = np.asarray(T_nominal_cloud, dtype=np.float64)[:3, :3]
    Q = np.asarray(P0, dtype=np.float64)[k] @ R.T + np.asarray(T_nominal_cloud)[:3, 3]
    g, d0 = np.asarray(grad)[k], np.asarray(dev)[k]
    A = np.hstack([np.cross(Q - Q.mean(0), g), g])  # d(dev) / d(ω, t) of the alignment
    local = np.searchsorted(pick, k)  # the compared points among those the figures get
    base = np.asarray(P0, dtype=np.float64)[pick]
    tol = float(tolerance_mm)

    def figures(P: np.ndarray, w: np.ndarray) -> dict[str, float]:
        wk = w[local]
        dd = np.einsum("ni,ni->n", g, (P[local] - base[local]) @ R.T)
        Aw = A * wk[:, None]
        x = np.linalg.lstsq(Aw.T @ A, -(Aw.T @ dd), rcond=None)[0]
        d = d0 + dd + A @ x
        return {"deviation_mean_mm": float(np.average(d, weights=wk)),
                "deviation_rms_mm": float(np.sqrt(np.average(d * d, weights=wk))),
                "share_within_tolerance": float(np.average(np.abs(d) <= tol, weights=wk))}

    return figures


def subsample(n: int, max_points: int) -> np.ndarray | None:
    """Indices of every k-th of ``n`` points, k the smallest stride that leaves at most
    ``max_points`` (0: no limit), or None where ``n`` is not more than that.

    Each draw re-triangulates every point it is given: on a long scan (millions of points)
    200 draws per contributor take minutes. The draws move the points by smooth functions of
    the calibration, and a cloud is stored frame by frame along its stripes, so a regular
    stride keeps the points' spread over the surface (a random sample weights it anew: on a
    ball cap of 2000 points that changed the camera's u by 2.5x); every frame keeps points and
    is bootstrapped as before.
    """
    if max_points <= 0 or n <= max_points:
        return None
    return np.arange(0, n, -(-n // int(max_points)))


def _finite_std(x: np.ndarray, enough: bool) -> float:
    """Sample standard deviation of the finite draws; NaN where they are too few."""
    x = x[np.isfinite(x)]
    return float(np.std(x, ddof=1)) if enough and x.size >= 2 else float("nan")


def arm_moves(sp: ScanPoints, arm: Any) -> Callable[[int], np.ndarray] | None:
    """How arm draw ``d`` moves each point (N, 3), from the fuse stage's
    :class:`~crossline.io.arm_draws.ArmDraws` (draw ``d`` modulo their number), or None where
    there are no draws. A point whose frame has no draw (none should) does not move."""
    if arm is None or len(arm.draws) == 0 or len(arm.frames) == 0 or sp.frame is None:
        return None
    k = np.clip(np.searchsorted(arm.frames, sp.frame), 0, len(arm.frames) - 1)
    has = arm.frames[k] == sp.frame
    rel = sp.points - arm.origins[k]
    D = len(arm.draws)

    def move(d: int) -> np.ndarray:
        e = arm.draws[d % D][k].astype(np.float64)
        m = np.cross(e[:, :3], rel) + e[:, 3:]
        m[~has] = 0.0
        return m

    return move


def monte_carlo(
    sp: ScanPoints, model: CalibrationModel, figures: Figures, *, draws: int = 200, seed: int = 0,
    arm: Any = None,
) -> dict[str, Any]:
    """Value, standard uncertainty, U (k = 2), 95 % interval and budget of each figure.

    ``draws`` calibrations (and frame resamplings) for the combined distribution, and as many
    again for each contributor alone (the budget). The value is the figure on the report's
    points; ``u`` the standard deviation of the combined draws. ``arm``, the fuse stage's
    :class:`~crossline.io.arm_draws.ArmDraws` of the scan, moves each frame's points by a
    drawn pose error (its draws are reused in turn where they are fewer than ``draws``).
    """
    rng = np.random.default_rng(seed)
    ones = np.ones(len(sp.points))
    value = figures(sp.points, ones)
    move = arm_moves(sp, arm)

    def run(parts: tuple[str, ...]) -> dict[str, np.ndarray]:
        out: dict[str, list[float]] = {k: [] for k in value}
        calib = [p for p in parts if p not in ("repeatability", "arm")]
        # each run starts the arm's draws at a random one, so the combined run and the arm's
        # own pair them with different calibrations
        d0 = int(rng.integers(0, 1 << 30))
        for i in range(draws):
            P = sp.points
            if calib:
                cam, planes, X = draw_calibration(model, rng, tuple(calib))
                P = moved_points(sp, cam, planes, X)
            if "arm" in parts and move is not None:
                P = P - move(d0 + i)
            w = ones
            if "repeatability" in parts:
                w = np.bincount(rng.integers(0, sp.n_frames, sp.n_frames),
                                minlength=sp.n_frames)[sp.frame_index].astype(float)
            for k, v in figures(P, w).items():
                out[k].append(v)
        return {k: np.asarray(v) for k, v in out.items()}

    known = {"camera": model.camera_cov is not None, "laser_planes": bool(model.plane_cov),
             "handeye": model.X_cov is not None, "arm": move is not None,
             "repeatability": sp.n_frames > 1}
    total = run(CONTRIBUTORS)
    # a contributor without a covariance is not drawn: its u is 0, and the model says why
    alone = {c: run((c,)) for c in CONTRIBUTORS if known[c]}
    result: dict[str, Any] = {}
    for k, v in value.items():
        # a draw may leave a figure undefined (a frame resampling without a frame that saw both
        # faces of the gauge): it is counted, and the statistics are those of the other draws
        # while they are most of them; else the figure's uncertainty is not determined (NaN)
        t = total[k][np.isfinite(total[k])]
        enough = t.size >= max(2, draws // 2)
        u = _finite_std(total[k], enough)
        parts = {c: _finite_std(alone[c][k], enough) if c in alone else 0.0 for c in CONTRIBUTORS}
        var = sum(x**2 for x in parts.values())
        lo, hi = np.percentile(t, [2.5, 97.5]) if enough else (float("nan"), float("nan"))
        result[k] = {
            "value": v, "u": u, "U": COVERAGE_FACTOR * u, "k": COVERAGE_FACTOR,
            "interval_95": [float(lo), float(hi)],
            "mc_mean": float(np.mean(t)) if enough else float("nan"),
            "draws_undefined": int(draws - t.size),
            "budget": {c: {"u": x, "share": x**2 / var if var > 0 else 0.0} for c, x in parts.items()},
            "dominant": max(parts, key=parts.get),
        }
    return result

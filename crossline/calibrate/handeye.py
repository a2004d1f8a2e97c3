"""Hand-eye calibration: ``X = T_tool_cam`` from arm poses and board views (AX = XB).

Conventions (DESIGN.md §1): the arm reports ``T_base_tool``; PnP gives ``T_cam_board``; the
board is fixed, so for every view ``T_base_board = T_base_tool_i @ X @ T_cam_board_i``. For
a motion pair (i, j)::

    A = inv(T_base_tool_j) @ T_base_tool_i,   B = T_cam_board_j @ inv(T_cam_board_i),   A X = X B

(the paper's eq. 20–23). Steps:

1. Board poses by PnP on bias-corrected centres; on a board that looks the same turned in its
   plane (symmetric grid, chessboard), each view's labelling is one of several; the one used
   is chosen so that every view agrees on one board frame (:func:`resolve_labellings`): first
   by rotation consistency of motion pairs (a rotation angle is invariant under a change of
   frame, so ``θ(A) = θ(B)`` for the right labelling; a wrong one adds a half turn about the
   board normal), then confirmed with the first X: each view's implied ``T_base_board`` must
   agree with the others'.
2. The tolerance on ``θA − θB`` comes from the data: its spread is set by the arm's and the
   board poses' rotation noise (the same for every pair to first order: the noise projected on
   the pair's rotation axis), estimated robustly as σ = 1.4826 · median |θA − θB| over all
   pairs (a wrong view spoils its own V − 1 pairs, a minority). Pairs beyond ``k σ`` (``k``
   from the configuration) are rejected and counted; a view in more rejected than accepted
   pairs is left out; motion whose rotation axes are all nearly parallel is a
   :class:`CalibrationError`.
3. Chou & Kamel (1991), the paper's method: ``q_A ⊗ q_X = q_X ⊗ q_B`` stacked for every pair,
   ``q_X`` the right singular vector of the smallest singular value; then the translation by
   linear least squares from ``(R_A − I) t_X = R_X t_B − t_A``. OpenCV's five methods
   (Tsai, Park, Horaud, Andreff, Daniilidis) are run alongside.
4. Refinement: X and ``T_base_board`` jointly, minimising the reprojection error (px) of every
   board point in every view through ``T_cam_board_i = inv(X) inv(T_base_tool_i) T_base_board``
   with the calibrated camera (scipy least squares), the circle-centre bias re-predicted from
   the current estimate between rounds. First with the arm poses taken as exact
   ("reprojection"), then by maximum likelihood ("refined"): each view's arm pose gets a
   correction weighted by the arm's standard deviations against the image residuals, the
   image and arm sigmas estimated from the residuals by variance components (Förstner). The
   covariance of X that follows predicts its error (checked over many noise draws in the
   tests and in benchmarks/bench_handeye.py). The refinement starts from the algebraic
   solution (Chou–Kamel or OpenCV's) with the best board consistency.
5. The final estimate is chosen on the views, with every method scored alike by its board
   consistency (:func:`consistency_mm`, the scatter of the board's points in the base frame).
   That score is in-sample: an X fitted to the arm's noise of these views lowers it while
   moving away from the truth, so the least-scatter X is not the most accurate one (the
   benchmark shows it). The refined X is kept unless another method's consistency is better
   by more than X's own uncertainty explains: the excess of squared consistency that an error
   of X distributed as its covariance causes, ``δᵀ H δ`` with ``H`` the consistency's Gauss–
   Newton matrix, has a quantile (Welch–Satterthwaite, 99 %) that sets the margin. Beyond it
   the refinement's noise model does not fit the data and the method with the best
   consistency wins. ``selection`` in handeye.json says which won, the margin, and how it
   compares with the best OpenCV method.

The code is split by idea (issue 21.3): ``handeye_solvers`` (motion pairs, Chou & Kamel,
OpenCV's methods), ``handeye_pairs`` (board labellings, the pairs' mismatch, the motion
check), ``handeye_refine`` (the refinement and its noise model), ``handeye_selection`` (board
consistency and the final choice). This module keeps the stage (``HandEye``,
``solve_handeye``, ``run_calibrate_handeye``) and re-exports the names its importers use.
"""

from __future__ import annotations

import itertools
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.board import Board
from crossline.calibrate.detect import board_symmetries
from crossline.calibrate.handeye_pairs import (
    MISMATCH_K,
    check_motion,
    mismatch_sigma,
    resolve_labellings,
    symmetry_transforms,
)
from crossline.calibrate.handeye_refine import (
    SIGMA_FLOORS,
    arm_noise_estimate,
    point_uncertainty,
    refine_handeye,
)
from crossline.calibrate.handeye_selection import consistency_margin, consistency_mm, select_estimate
from crossline.calibrate.handeye_solvers import (
    OPENCV_METHODS,
    chou_kamel,
    motion_pairs,
    opencv_handeye,
    pair_residuals,
)
from crossline.calibrate.pose import board_pose
from crossline.camera import Camera
from crossline.errors import CalibrationError, CrosslineError
from crossline.geometry import rotation_angle
from crossline.io.atomic import write_json
from crossline.io.values import rigid_transform

__all__ = [
    "OPENCV_METHODS",
    "HandEye",
    "HandEyeFileError",
    "check_motion",
    "chou_kamel",
    "consistency_margin",
    "consistency_mm",
    "mismatch_sigma",
    "motion_pairs",
    "opencv_handeye",
    "pair_residuals",
    "point_uncertainty",
    "refine_handeye",
    "resolve_labellings",
    "run_calibrate_handeye",
    "select_estimate",
    "symmetry_transforms",
]

log = logging.getLogger(__name__)


class HandEyeFileError(CrosslineError, ValueError):
    """handeye.json cannot be read or holds no rigid T_tool_cam (names the file)."""


@dataclass(frozen=True)
class HandEye:
    """The hand-eye result as stored in ``handeye.json``: ``T_tool_cam`` and everything else."""

    T_tool_cam: np.ndarray
    method: str = "refined"
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        T = np.asarray(self.T_tool_cam, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_tool_cam must be 4x4, got shape {T.shape}")
        object.__setattr__(self, "T_tool_cam", T)

    def to_dict(self) -> dict[str, Any]:
        """JSON mapping with ``T_tool_cam``, ``method`` and the extras."""
        out = dict(self.extra)
        out.update(T_tool_cam=self.T_tool_cam.tolist(), method=self.method)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> HandEye:
        """From a mapping with ``T_tool_cam``, a rigid transform, and optionally ``method``, a
        text; ValueError naming the key and what was expected otherwise."""
        T = rigid_transform(data, "T_tool_cam")
        method = data.get("method", "refined")
        if not isinstance(method, str):
            raise ValueError(f"'method' = {method!r}: expected the name of the method, a text")
        extra = {k: v for k, v in data.items() if k not in ("T_tool_cam", "method")}
        return cls(T, method, extra)

    def arm_noise(self) -> dict[str, float] | None:
        """The arm's pose noise per axis that the refinement estimated from the views' residuals
        (``sigma_mm``, ``sigma_rad``, ``views``); None where the file holds no such estimate."""
        nm = ((self.extra.get("methods") or {}).get("refined") or {}).get("noise_model") or {}
        s_mm, s_rad = nm.get("arm_sigma_mm"), nm.get("arm_sigma_rad")
        ok = all(isinstance(v, (int, float)) and np.isfinite(v) and v > 0 for v in (s_mm, s_rad))
        if not ok:
            return None
        return {"sigma_mm": float(s_mm), "sigma_rad": float(s_rad),
                "views": len(self.extra.get("board_poses") or [])}

    def save(self, path: str | Path) -> None:
        """Write ``handeye.json`` atomically."""
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> HandEye:
        """Read ``handeye.json``; HandEyeFileError naming the file and what is wrong."""
        path = Path(path)
        try:
            return cls.from_dict(json.loads(path.read_text()))
        except (KeyError, ValueError, TypeError) as exc:
            raise HandEyeFileError(f"{path}: not a hand-eye file: {exc}") from exc


# ----------------------------------------------------------------------------- stage


def solve_handeye(
    camera: Camera,
    board: Board,
    points: np.ndarray,
    T_base_tool: np.ndarray,
    names: list[str],
    *,
    mismatch_k: float = MISMATCH_K,
    bias_correction: bool = True,
) -> HandEye:
    """All methods and the chosen X from measured points (V, N, 2) and arm poses (V, 4, 4).

    Motion pairs whose rotation-angle mismatch exceeds ``mismatch_k`` robust sigmas of all
    pairs' mismatches are rejected (module docstring, step 2).
    """
    V = len(points)
    if V < 3:
        raise CalibrationError(f"hand-eye calibration needs at least 3 views with the board found, got {V}")
    fits = [board_pose(camera, board, p, bias_correction=bias_correction) for p in points]
    T0 = np.array([f.T_cam_board for f in fits])
    Tc, sym = resolve_labellings(T_base_tool, T0, board)
    S = symmetry_transforms(board)
    # the points relabelled alike: the pose T @ S sees point k where the detection had perm[k]
    perms = board_symmetries(board)
    pts = np.array([p[perms[s]] for p, s in zip(points, sym, strict=True)])
    all_pairs = list(itertools.combinations(range(V), 2))
    A, B = motion_pairs(T_base_tool, Tc, all_pairs)
    thA, thB = rotation_angle(A[:, :3, :3]), rotation_angle(B[:, :3, :3])
    sigma_m = mismatch_sigma(thA, thB)
    tol = mismatch_k * sigma_m
    keep = np.abs(thA - thB) <= tol
    rejected = [
        {"pair": [names[i], names[j]], "theta_A_deg": float(np.degrees(thA[k])),
         "theta_B_deg": float(np.degrees(thB[k]))}
        for k, (i, j) in enumerate(all_pairs) if not keep[k]
    ]
    for r in rejected:
        log.warning("hand-eye pair %s rejected: rotation angles %.4f vs %.4f deg differ by more than "
                    "%.4g deg (%g robust sigmas of all pairs' mismatches)",
                    r["pair"], r["theta_A_deg"], r["theta_B_deg"], np.degrees(tol), mismatch_k)
    # a view in more rejected than accepted pairs is the culprit (its arm pose or its image):
    # it is left out of everything that uses absolute poses (OpenCV, the refinement)
    bad_count = np.zeros(V, dtype=int)
    for k, (i, j) in enumerate(all_pairs):
        if not keep[k]:
            bad_count[i] += 1
            bad_count[j] += 1
    use = bad_count <= (V - 1) / 2
    rejected_views = [
        {"image": names[v], "rejected_pairs": int(bad_count[v]), "pairs": V - 1}
        for v in range(V) if not use[v]
    ]
    for r in rejected_views:
        log.warning("%s: left out of the hand-eye solution: %d of its %d motion pairs have "
                    "mismatching rotation angles", r["image"], r["rejected_pairs"], r["pairs"])
    in_use = np.array([use[i] and use[j] for i, j in all_pairs])
    keep &= in_use
    if keep.sum() < 2 or use.sum() < 3:
        raise CalibrationError(
            f"hand-eye calibration: only {int(keep.sum())} of {len(all_pairs)} motion pairs have "
            f"matching rotation angles (|theta_A - theta_B| <= {np.degrees(tol):.4g} deg, "
            f"{mismatch_k:g} robust sigmas of all pairs' mismatches); check that poses.csv matches "
            f"the images"
        )
    motion = check_motion(A[keep])
    Ak, Bk = A[keep], B[keep]
    all_names, all_fits, all_Tc, all_sym = names, fits, Tc, sym
    u = np.nonzero(use)[0]
    T_base_tool, Tc, pts = T_base_tool[u], Tc[u], pts[u]
    names = [names[k] for k in u]
    methods: dict[str, dict[str, Any]] = {}

    def record(name: str, X: np.ndarray) -> None:
        rot, tr = pair_residuals(X, Ak, Bk)
        methods[name] = {
            "T_tool_cam": X,
            "rotation_residual_deg_rms": float(np.degrees(np.sqrt(np.mean(rot**2)))),
            "translation_residual_mm_rms": float(np.sqrt(np.mean(tr**2))),
            "board_consistency_mm": consistency_mm(X, T_base_tool, Tc, board),
        }

    X_ck = chou_kamel(Ak, Bk)
    record("chou_kamel", X_ck)
    for name in OPENCV_METHODS:
        try:
            record(name, opencv_handeye(T_base_tool, Tc, name))
        except cv2.error as exc:  # pragma: no cover - OpenCV failures are reported, not fatal
            methods[name] = {"error": str(exc).strip().splitlines()[-1]}
    # image noise from the single-view fits (6 pose parameters each), arm noise from X_ck
    n_obs = pts.shape[1] * 2
    # (rms_px is the RMS of 2-D residuals: per coordinate it is rms / sqrt 2)
    # the floors lie far below any real noise; they keep exact (synthetic) data well conditioned
    sigma_px = max(float(np.sqrt(np.mean([f.rms_px**2 for f in fits]) / 2 * n_obs / (n_obs - 6))),
                   SIGMA_FLOORS["image_px"])
    # the refinement starts from the algebraic solution the views agree with best
    algebraic = ["chou_kamel", *(m for m in OPENCV_METHODS if "T_tool_cam" in methods[m])]
    start = min(algebraic, key=lambda m: methods[m]["board_consistency_mm"])
    X_start = methods[start]["T_tool_cam"]
    s_mm, s_rad, Tbb0 = arm_noise_estimate(X_start, T_base_tool, Tc)
    s_mm, s_rad = max(s_mm, SIGMA_FLOORS["arm_mm"]), max(s_rad, SIGMA_FLOORS["arm_rad"])
    plain = refine_handeye(camera, board, pts, T_base_tool, X_start, Tbb0, bias_correction=bias_correction)
    record("reprojection", plain.X)
    methods["reprojection"]["reprojection_rms_px"] = plain.rms_px
    # the pose comparison charges the board poses' own error to the arm: the refinement
    # re-estimates all three sigmas from its residuals (variance components)
    ref = refine_handeye(camera, board, pts, T_base_tool, plain.X, plain.T_base_board, sigma_px=sigma_px,
                         arm_sigma_mm=s_mm, arm_sigma_rad=s_rad, bias_correction=bias_correction,
                         estimate_sigmas=True)
    X, Tbb, res = ref.X, ref.T_base_board, ref.residuals
    record("refined", X)
    methods["refined"]["reprojection_rms_px"] = ref.rms_px
    # what the noise allows: X's uncertainty at the boards' distance, on the optical axis
    z = float(np.median(Tc[:, 2, 3]))
    methods["refined"]["uncertainty"] = {
        "covariance_X": ref.covariance_X,
        "rotation_deg_1sigma": float(np.degrees(np.sqrt(np.trace(ref.covariance_X[:3, :3])))),
        "translation_mm_1sigma": float(np.sqrt(np.trace(ref.covariance_X[3:, 3:]))),
        "board_distance_mm": z,
        "point_mm_1sigma_at_board_distance": float(
            point_uncertainty(X, ref.covariance_X, np.array([[0.0, 0.0, z]]))[0]
        ),
    }
    methods["refined"]["noise_model"] = {
        "image_sigma_px": ref.sigmas["image_px"], "arm_sigma_mm": ref.sigmas["arm_mm"],
        "arm_sigma_rad": ref.sigmas["arm_rad"],
        "initial": {"image_sigma_px": sigma_px, "arm_sigma_mm": s_mm, "arm_sigma_rad": s_rad},
        "variance_factors": ref.variance_factors, "reweightings": ref.sigma_iterations,
        "arm_corrections_rms_mm": float(np.sqrt(np.mean(ref.arm_corrections[:, 3:] ** 2))),
        "arm_corrections_rms_rad": float(np.sqrt(np.mean(ref.arm_corrections[:, :3] ** 2))),
    }
    selection = select_estimate(methods, ref.covariance_X, T_base_tool, Tc, board)
    selection["refinement_start"] = start
    chosen = selection["method"]
    if chosen != "refined":
        log.warning("hand-eye: %s chosen over the refined X: its board consistency %.4f mm beats the "
                    "refined %.4f mm by more than X's uncertainty explains (%.4f mm^2 margin)",
                    chosen, methods[chosen]["board_consistency_mm"],
                    methods["refined"]["board_consistency_mm"], selection["margin_mm2"])
        X = methods[chosen]["T_tool_cam"]
    view_rms = np.sqrt(np.mean(np.sum(res**2, -1), -1))
    extra = {
        "methods": methods,
        "T_base_board": Tbb,
        "pairs": {
            "total": len(all_pairs),
            "used": int(keep.sum()),
            "rejected": int((~keep).sum()),
            "angle_tolerance_deg": float(np.degrees(tol)),
            "mismatch_k": mismatch_k,
            "mismatch_sigma_deg": float(np.degrees(sigma_m)),
            "mismatch_rms_deg": float(np.degrees(np.sqrt(np.mean((thA - thB) ** 2)))),
            "rejected_pairs": rejected,
            "rejected_views": rejected_views,
            **motion,
        },
        "board_poses": [
            {"image": n, "used": bool(use[k]), "T_cam_board": T,
             "labelling_turn_deg": float(np.degrees(np.arctan2(S[s][1, 0], S[s][0, 0]))),
             "pnp_rms_px": f.rms_px,
             "refined_rms_px": float(view_rms[int(np.searchsorted(u, k))]) if use[k] else None}
            for k, (n, T, s, f) in enumerate(zip(all_names, all_Tc, all_sym, all_fits, strict=True))
        ],
        "residuals": {n: r for n, r in zip(names, res, strict=True)},
        "reprojection_rms_px": methods["refined"]["reprojection_rms_px"],
        "selection": selection,
    }
    return HandEye(X, chosen, extra)


def run_calibrate_handeye(
    capture: str | Path,
    camera_json: str | Path,
    out: str | Path,
    *,
    mismatch_k: float = MISMATCH_K,
    threads: int = 1,
) -> HandEye:
    """Stage: solve X = T_tool_cam from ``calibration/handeye`` and write ``handeye.json``."""
    from crossline.calibrate.camera import detect_views
    from crossline.io.capture import open_capture

    cv2.setNumThreads(1)  # parallelism comes from our pool of `threads` workers (determinism)
    cap = open_capture(capture)
    camera = Camera.load(camera_json)
    board = cap.rig.board
    shape = (cap.rig.sensor.height, cap.rig.sensor.width)
    names = [str(p.relative_to(cap.root)) for p in cap.handeye_images]
    dets = detect_views(cap.handeye_images, board, shape, threads)
    skipped = []
    for n, d in zip(names, dets, strict=True):
        if not d.found:
            log.warning("%s: skipped: %s", n, d.reason)
            skipped.append({"image": n, "reason": d.reason})
    use = [k for k, d in enumerate(dets) if d.found]
    if len(use) < 3:
        lines = "\n".join(f"  - {s['image']}: {s['reason']}" for s in skipped)
        raise CalibrationError(
            f"capture {cap.root}: calibration/handeye: hand-eye calibration needs at least 3 views "
            f"with the board found, got {len(use)} of {len(names)}" + (f":\n{lines}" if lines else "")
        )
    try:
        he = solve_handeye(
            camera, board, np.array([dets[k].points for k in use]), cap.handeye_T_base_tool[use],
            [names[k] for k in use], mismatch_k=mismatch_k,
        )
    except CalibrationError as exc:
        # what the solver finds wrong is in the arm poses (degenerate motion) or in how they
        # match the views (rotation angles): the file that holds them is named
        raise CalibrationError(f"capture {cap.root}: calibration/handeye/poses.csv (the arm poses of "
                               f"{len(use)} views with the board found): {exc}") from None
    he.extra["skipped_views"] = skipped
    he.save(out)
    sel, pairs = he.extra["selection"], he.extra["pairs"]
    log.info("hand-eye: %d views, %d/%d pairs used (mismatch sigma %.4f deg, cut %.4f deg); "
             "reprojection RMS %.4f px; %s chosen, board consistency %.4f mm (best OpenCV: %s "
             "%.4f mm)", len(use), pairs["used"], pairs["total"], pairs["mismatch_sigma_deg"],
             pairs["angle_tolerance_deg"], he.extra["reprojection_rms_px"], he.method,
             sel["board_consistency_mm"][he.method], sel.get("best_opencv", "-"),
             sel.get("best_opencv_consistency_mm", float("nan")))
    return he

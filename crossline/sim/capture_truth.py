"""The capture's truth: the ``truth.json`` record and the true centreline rows of truth/.

``truth.json`` (format ``crossline-truth/1``; only validation may read it):

* ``camera``: ``K``, ``dist`` (k1, k2, p1, p2, k3), ``image_size``;
* ``lasers.A|B``: ``normal``, ``d`` (cam frame, n.p + d = 0), ``emitter_cam``,
  ``fan_centre_cam``, ``fan_half_angle_deg``, ``fan_rolloff``, ``wavelength_nm``, ``waist_mm``,
  ``m2``, ``focus_mm``, ``rayleigh_mm``, ``thickness_model``, ``peak_electrons``,
  ``speckle_contrast``, ``speckle_grain_px``;
* ``T_tool_cam`` (the true X), ``T_base_board`` (the hand-eye board), 4x4 lists;
* ``board``: rig.yaml's board plus ``light_albedo``, ``dark_albedo``, ``plate_rect_mm``,
  ``thickness_mm``, ``background_albedo``;
* ``sensor``: ``bit_depth``, ``full_well_e``, ``gain_e_per_dn``, ``read_noise_e``,
  ``black_level_dn``, ``prnu``, ``psf_sigma_px``, ``shot_noise``, ``vignetting``,
  ``scan_window``, ``frame_rate``; ``lighting``: the ambient model and its levels;
* ``arm_noise``: the model (see ``crossline.sim.arm``) and its numbers;
* ``calibration``: ``camera[<image>].T_cam_board``, ``laser_A|laser_B[<pose>].T_cam_board``,
  ``handeye[<image>]``: ``T_base_tool`` (true), ``T_cam_board``, ``error_position_mm``,
  ``error_rotation_rad`` (reported minus true);
* ``scans.<name>``: the DESIGN.md keys (gauge: ``height``, ``plate_plane_base``,
  ``top_plane_base``; plate: ``plane_base``; ball: ``diameter``, ``center_base``; part: ``mesh``
  = ``truth/part.ply``; ball bar: ``diameter``, ``length``, ``centers_base`` (the two centres,
  ``length`` apart), with ``direction_base``, ``yaw_deg``, ``incline_deg``, ``stems``) plus
  ``centrelines`` (``truth/<scan>_centrelines.parquet``: frame, laser, u (full-sensor column), v
  (full-sensor row, sub-pixel), x_cam, y_cam, z_cam (the surface point on the sheet's centre
  plane), visible (= lit and unoccluded), lit, unoccluded, surface (which primitive), cos_view
  and cos_incidence (cosines between the surface normal and the directions to the camera and to
  the emitter: a stripe on a face seen at grazing angle is visible but covers a sliver of a
  pixel), and the true profile along the column there: peak_e (electrons per pixel area at the
  sheet's centre: white irradiance x albedo x vignetting, before the PSF and the speckle; NaN
  where the ray meets another surface first), sigma_px (its Gaussian sigma along the column,
  before the PSF: w(s) / 2 over the plane distance's change per row) and background_e (the
  blurred ambient electrons at the pixel)), ``poses`` (``truth/<scan>_poses.parquet``: frame,
  time_s, lasers, the true T_base_tool as x, y, z, qw, qx, qy, qz, and the reported-minus-true
  errors err_x, err_y, err_z (mm, base) and err_rx, err_ry, err_rz (rad, flange)), ``surfaces``,
  ``frames``, ``pattern``, ``trajectory`` and ``render_stats`` (an inclined sweep's
  ``trajectory`` adds ``incline_deg``); gauge adds ``block`` (centre, axes, size), ball
  ``stem``, part ``design`` (the analytic surface) and ``mesh_triangles``.

Split from ``crossline.sim.capture`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

from crossline.sim import arm as arm_mod
from crossline.sim.capture_jobs import Output
from crossline.sim.colour import ColourSensor
from crossline.sim.presets import RigPreset


def _frame_table(frame: int, laser: str, rows: dict):
    """The true centreline rows of one laser in one frame as a table."""
    import pandas as pd

    df = pd.DataFrame(rows)
    df.insert(0, "laser", laser)
    df.insert(0, "frame", frame)
    return df


def _truth_json(rig: RigPreset, seed: int, quick: bool, bits: int, pattern: list[str],
                truth_cal: dict, scan_truth: dict, output: Output = Output()) -> dict:  # noqa: B008
    from crossline.sim.sheet import LaserSheet

    s = rig.sensor
    b = rig.board
    dbits = output.data_bits or bits
    sensor = {
        "bit_depth": bits, "full_well_e": s.full_well_e,
        "gain_e_per_dn": s.gain_e_per_dn(dbits), "read_noise_e": s.read_noise_e,
        "black_level_dn": s.black_dn(dbits), "prnu": s.prnu, "psf_sigma_px": s.psf_sigma_px,
        "shot_noise": "Poisson below 30 e-, Gaussian sqrt(e) above",
        "vignetting": "cos^4 of the field angle",
        "scan_window": list(s.scan_window), "frame_rate": s.frame_rate,
        "pixel_pitch_um": s.pixel_pitch_um, "f_number": s.f_number,
    }
    if output.data_bits is not None:
        sensor["data_bits"] = dbits
    if output.colour is not None:
        from crossline.sim.colour import AMBIENT_GAINS

        sensor["colour"] = {
            "mosaic": "RGGB Bayer, red at even rows and columns of the full sensor; demosaiced "
                      "bilinearly (OpenCV)",
            "channel": output.colour, "ambient_gains_rgb": list(AMBIENT_GAINS),
            "laser_gains_rgb": {k: ColourSensor(output.colour, {k: v.wavelength_nm}).laser[k].tolist()
                                for k, v in rig.lasers.items()},
        }
    return {
        "format": "crossline-truth/1",
        "simulated": True,
        "preset": rig.name,
        "seed": seed,
        "quick": bool(quick),
        "camera": {"K": [list(r) for r in s.K], "dist": list(s.dist),
                   "image_size": [s.width, s.height]},
        "lasers": {k: LaserSheet(k, v).to_dict() for k, v in rig.lasers.items()},
        "T_tool_cam": rig.T_tool_cam,
        "T_base_board": rig.T_base_board,
        "board": {**b.board.to_dict(), "light_albedo": b.light_albedo, "dark_albedo": b.dark_albedo,
                  "plate_rect_mm": list(b.plate_rect()), "thickness_mm": b.thickness_mm,
                  "background_albedo": b.background_albedo},
        "sensor": sensor,
        "lighting": {"board_views_e_white": rig.ambient_board_e,
                     "scan_exposure_e_white": rig.ambient_scan_e,
                     "model": "e = e_white * albedo * (0.6 + 0.4 max(0, N.up)) * (1 + grad.(P-ref)) "
                              "* cos^4; laser images of calibration use the scan exposure"},
        "arm_noise": arm_mod.noise_to_dict(rig.arm),
        "table_z_base": rig.table_z_mm,
        "calibration": truth_cal,
        "scans": scan_truth,
    }

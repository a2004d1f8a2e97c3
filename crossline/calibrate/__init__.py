"""Calibration stages: camera (Zhang), laser planes (§2.5 of the paper), hand-eye (AX = XB).

Module map: ``detect`` (board detection, sub-pixel circle centres), ``bias`` (perspective bias
of circle centres), ``pose`` (board pose by PnP), ``lm`` (Levenberg–Marquardt on the normal
equations), ``camera``, ``lasers``, ``handeye`` (the stages, each with its
``run_calibrate_*``), ``synthetic`` (a small board renderer for tests). The camera stage's
parts: ``camera_fit`` (Zhang's start, the bundle adjustment and bias iterations),
``camera_uncertainty`` (the predicted projection error), ``camera_model_selection`` (which
distortion coefficients to fix). The laser stage's parts: ``laser_board`` (board plane, edge
clearance), ``laser_background`` (the lasers-off model and stripe removal), ``laser_albedo``
(albedo gain), ``laser_stripe`` (the stripe's centres on a pose), ``laser_plane_fit`` (robust
plane and its camera Jacobian). The hand-eye stage's: ``handeye_solvers`` (AX = XB: Chou-Kamel
and OpenCV's), ``handeye_pairs`` (motion pairs and their checks), ``handeye_refine`` (bundle
refinement and its uncertainty), ``handeye_selection`` (the board-consistency choice between
estimates).
"""

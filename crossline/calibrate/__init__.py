"""Calibration stages: camera (Zhang), laser planes (§2.5 of the paper), hand-eye (AX = XB).

Module map: ``detect`` (board detection, sub-pixel circle centres), ``bias`` (perspective
bias of circle centres), ``pose`` (board pose by PnP), ``lm`` (Levenberg–Marquardt on the
normal equations), ``camera``, ``lasers``, ``handeye`` (the stages, each with its
``run_calibrate_*``), ``synthetic`` (a small board renderer for tests).
"""

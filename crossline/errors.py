"""Errors that crossline reports to users: each names the file and what was expected."""

from __future__ import annotations

__all__ = ["CalibrationError", "CrosslineError", "StageError"]


class CrosslineError(Exception):
    """Base of every error caused by the input rather than by a bug; the CLI exits with 2."""


class CalibrationError(CrosslineError):
    """A calibration that cannot be trusted: too few usable views, no stripe, degenerate motion."""


class StageError(CrosslineError):
    """A scan stage that cannot go on: no stripe in any frame, no reference frames, ..."""

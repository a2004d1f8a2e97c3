"""The speckle bound on a stripe centre (Dorsch, Häusler & Herrmann 1994), by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crossline.report.speckle import centre_bound_px, smoothing_gain


def test_centre_bound_by_hand():
    # C lambda N (1 + m) / pi: 0.15 x 0.405 um x 8 x 1.085 / pi = 0.1679 um, 0.0700 px of 2.4 um
    assert centre_bound_px(0.15, 405.0, 8.0, 2.4, 0.085) == pytest.approx(
        0.15 * 0.405 * 8.0 * 1.085 / math.pi / 2.4, rel=1e-12)
    assert centre_bound_px(0.15, 405.0, 8.0, 2.4, 0.085) == pytest.approx(0.0700, abs=1e-4)
    # fully developed speckle (C = 1) through an f/2 lens on 5 um pixels at 650 nm
    assert centre_bound_px(1.0, 650.0, 2.0, 5.0) == pytest.approx(0.0828, abs=1e-4)
    assert centre_bound_px(0.0, 650.0, 2.0, 5.0) == 0.0
    with pytest.raises(ValueError):
        centre_bound_px(0.15, 405.0, 0.0, 2.4)


def test_smoothing_gain_is_the_centre_noise_of_a_quadratic_fit():
    # Savitzky-Golay, quadratic, 7 points: centre weights (-2, 3, 6, 7, 6, 3, -2) / 21
    assert smoothing_gain(7) == pytest.approx(math.sqrt(147 / 441), rel=1e-12)
    rng = np.random.default_rng(0)
    x = rng.standard_normal((200000, 7))
    w = np.array([-2, 3, 6, 7, 6, 3, -2]) / 21
    assert np.std(x @ w) == pytest.approx(smoothing_gain(7), rel=0.01)
    assert smoothing_gain(1) == 1.0 and smoothing_gain(6) == smoothing_gain(7)

"""A colour sensor: an RGGB Bayer mosaic under the pixels, demosaiced by the camera.

Every pixel collects one channel. Room light is white: the board shows in all three
channels, with the raw (not white-balanced) gains ``AMBIENT_GAINS``. A laser's light falls
on each channel by the channel's spectral sensitivity at its wavelength (Gaussian curves,
``SENSITIVITY``), normalised so that its own channel (``channel``) collects what a grey
sensor would: a red laser shows mainly in red, a little in green, hardly in blue. The
mosaic is digitised like a grey image (noise per pixel), then demosaiced bilinearly by
OpenCV, as a camera's own pipeline would, into (H, W, 3) red, green, blue.

The mosaic is fixed to the sensor: red at even rows and columns of the full sensor, so a
window at an odd offset starts on another colour (and OpenCV's code for it differs).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["AMBIENT_GAINS", "BANDS_NM", "CHANNELS", "ColourSensor", "laser_wavelength"]

CHANNELS = ("red", "green", "blue")
AMBIENT_GAINS = (0.9, 1.0, 0.8)  # raw response of R, G, B to the room's white light
SENSITIVITY = ((610.0, 45.0), (540.0, 40.0), (460.0, 35.0))  # (peak nm, sigma nm) of R, G, B
BANDS_NM = {"red": (600.0, 700.0), "green": (500.0, 570.0), "blue": (400.0, 490.0)}
NOMINAL_NM = {"red": 650.0, "green": 520.0, "blue": 450.0}
# OpenCV's demosaicing code for the 2 x 2 block a window starts on (row parity, column parity)
_CODES = {(0, 0): cv2.COLOR_BayerBG2RGB,  # R G / G B
          (0, 1): cv2.COLOR_BayerGB2RGB,  # G R / B G
          (1, 0): cv2.COLOR_BayerGR2RGB,  # G B / R G
          (1, 1): cv2.COLOR_BayerRG2RGB}  # B G / G R


def laser_wavelength(channel: str, wavelength_nm: float) -> float:
    """The laser's wavelength if it lies in the channel's band, else the band's nominal one."""
    lo, hi = BANDS_NM[channel]
    return float(wavelength_nm) if lo <= wavelength_nm <= hi else NOMINAL_NM[channel]


def _response(wavelength_nm: float) -> np.ndarray:
    return np.array([np.exp(-0.5 * ((wavelength_nm - p) / s) ** 2) for p, s in SENSITIVITY])


class ColourSensor:
    """Channel gains of the mosaic for ambient light and for each laser, and the demosaicing."""

    def __init__(self, channel: str, wavelengths_nm: dict[str, float]):
        if channel not in CHANNELS:
            raise ValueError(f"colour channel must be one of {CHANNELS}, got {channel!r}")
        self.channel = channel
        k = CHANNELS.index(channel)
        self.ambient = np.asarray(AMBIENT_GAINS, np.float32)
        self.laser = {}
        for name, wl in wavelengths_nm.items():
            r = _response(wl)
            self.laser[name] = (r / r[k]).astype(np.float32)
        self._maps: dict = {}

    def channel_map(self, window) -> np.ndarray:
        """Channel index (0 R, 1 G, 2 B) of every pixel of a window (h, w), int8."""
        key = tuple(int(v) for v in window)
        if key not in self._maps:
            x0, y0, w, h = key
            r = (np.arange(h) + y0) % 2
            c = (np.arange(w) + x0) % 2
            # R at (even, even), B at (odd, odd), G elsewhere
            self._maps[key] = np.where(r[:, None] == c[None, :], 2 * r[:, None], 1).astype(np.int8)
        return self._maps[key]

    def ambient_gain(self, window) -> np.ndarray:
        """Per-pixel gain (h, w) of the mosaic for white light."""
        return self.ambient[self.channel_map(window)]

    def laser_gain(self, name: str, window, rows: slice, cols: slice) -> np.ndarray:
        """Per-pixel gain of the mosaic for one laser, over a sub-region of the window."""
        return self.laser[name][self.channel_map(window)[rows, cols]]

    def demosaic(self, mosaic: np.ndarray, window) -> np.ndarray:
        """(h, w, 3) red, green, blue from the digitised mosaic of a window (same dtype)."""
        x0, y0 = int(window[0]), int(window[1])
        return cv2.cvtColor(mosaic, _CODES[(y0 % 2, x0 % 2)])

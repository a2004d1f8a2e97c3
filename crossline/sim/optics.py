"""Camera rays through the distortion, and the sensor: PSF, speckle, noise, quantisation.

Rays. Every sample ray must reproject to its sensor position to well under 0.001 px. The
exact inverse of the distortion (Newton, ``crossline.camera.undistort_normalized``) is
computed on a coarse grid of sensor positions (every ``GRID_STEP`` px) and carried to every
pixel centre (and to the 2 x 2 sample positions of the scan window) by a tensor-product
cubic spline in float64 (matrix products); a sample at another sub-pixel offset gets one step
of the local inverse Jacobian of the distortion from its pixel centre (second-order error
< 1.4e-5 px within half a pixel). ``tests/test_sim_optics.py`` checks the reprojection of
random samples over the whole sensor, corners included: < 1e-4 px.

Sensor. The optical image (electrons per pixel, float) goes through, in this order: PSF
blur (Gaussian, sigma ``psf_sigma_px``, lens and pixel crosstalk), photo-response
non-uniformity (a fixed per-pixel gain map), shot noise (Poisson; the Gaussian limit above 30
electrons, where the two differ by far less than the read noise), full-well clipping, read
noise (Gaussian, electrons), conversion to DN with the black level, rounding and clipping to
the bit depth.

Speckle. A laser stripe on a rough surface is speckled. The image-plane (subjective) speckle
grain is about lambda x f-number = 0.405 um x 8 ~ 3.2 um, one pixel of a 2.4 um sensor, so
the field is correlated over ~1 px: white Gaussian noise filtered by a Gaussian of sigma
``speckle_grain_px`` and renormalised, turned into a log-normal multiplicative field of mean 1
and contrast (std/mean) ``speckle_contrast``. Fully developed speckle has contrast 1; a
multimode 405 nm diode (a few longitudinal modes over ~1 nm on a surface rough on the
~10 um scale), the depolarising matte surface (two independent polarisation patterns) and
the integration over the pixel each reduce it, to about 0.1-0.25 (Dorsch, Häusler &
Herrmann, Appl. Opt. 33, 1994 report 0.1-0.3 for such triangulation sensors). The paper's
rig uses 0.15. A new field is drawn for every frame and laser: between frames the arm moves
the stripe by ~0.3 mm, far more than the sheet's thickness, which decorrelates the pattern.
The speckle multiplies the laser light after the PSF, since its grain is already the
image-plane grain the aperture forms.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.interpolate import CubicSpline

from crossline.camera import Camera, undistort_normalized

__all__ = [
    "GRID_STEP",
    "RayTable",
    "SensorModel",
    "pixel_offsets",
    "speckle_field",
]

GRID_STEP = 16  # px between exact (Newton) undistortions; the spline carries them to every pixel


def distortion_jacobian(xy: np.ndarray, dist) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entries (a, b, c) of the symmetric Jacobian [[a, b], [b, c]] of the distortion at xy (N, 2)."""
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    c = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, c


def _spline_matrix(coarse: np.ndarray, fine: np.ndarray) -> np.ndarray:
    """Matrix M (len(fine), len(coarse)) with M @ f(coarse) = cubic spline of f at fine."""
    return CubicSpline(coarse, np.eye(len(coarse)), axis=0)(fine)


class RayTable:
    """Exact undistorted normalised coordinates for the pixels of a sensor window."""

    def __init__(self, camera: Camera, window: tuple[int, int, int, int]):
        self.camera = camera
        x0, y0, w, h = window
        self.window = (int(x0), int(y0), int(w), int(h))
        u = np.arange(x0, x0 + w, dtype=np.float64)
        v = np.arange(y0, y0 + h, dtype=np.float64)
        uc = np.arange(x0 - 2 * GRID_STEP, x0 + w + 2 * GRID_STEP, GRID_STEP, dtype=np.float64)
        vc = np.arange(y0 - 2 * GRID_STEP, y0 + h + 2 * GRID_STEP, GRID_STEP, dtype=np.float64)
        U, V = np.meshgrid(uc, vc)
        xy = camera.undistort(np.stack([U.ravel(), V.ravel()], -1)).reshape(len(vc), len(uc), 2)
        self._coarse_grid = (uc, vc, xy)
        Mu = _spline_matrix(uc, u)
        Mv = _spline_matrix(vc, v)
        self.xy = np.empty((h, w, 2))
        for k in range(2):
            self.xy[..., k] = Mv @ xy[..., k] @ Mu.T
        self._half: np.ndarray | None = None

    def half_grid(self) -> np.ndarray:
        """Undistorted coordinates (2h, 2w, 2) of the 2 x 2 samples of every pixel.

        Entry (2 r + b, 2 c + a) is the sample at offset (a - 0.5, b - 0.5) / 2 from the
        centre of window pixel (r, c), by the same spline as the pixel centres.
        """
        if self._half is None:
            x0, y0, w, h = self.window
            uc, vc, xy = self._coarse_grid
            u = x0 - 0.25 + 0.5 * np.arange(2 * w)
            v = y0 - 0.25 + 0.5 * np.arange(2 * h)
            Mu = _spline_matrix(uc, u)
            Mv = _spline_matrix(vc, v)
            half = np.empty((2 * h, 2 * w, 2))
            for k in range(2):
                half[..., k] = Mv @ xy[..., k] @ Mu.T
            self._half = half
        return self._half

    def sample_xy_2x2(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Undistorted coordinates (N, 4, 2) of the 2 x 2 samples (``pixel_offsets(2)`` order)."""
        half = self.half_grid()
        out = np.empty((len(rows), 4, 2))
        for s, (a, b) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
            out[:, s] = half[2 * rows + b, 2 * cols + a]
        return out

    def pixel_xy(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (N, 2) of window pixels (row, col indices)."""
        return self.xy[rows, cols]

    def sample_xy(self, rows: np.ndarray, cols: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Undistorted coordinates (N, S, 2) of samples at sub-pixel ``offsets`` (S, 2) (du, dv).

        One step of the inverse distortion Jacobian from the pixel centre: its second-order
        error within half a pixel is below 2e-6 px for the paper's lens and 1.4e-5 px for the
        compact rig's (``tests/test_sim_optics.py`` checks < 1e-4 px everywhere).
        """
        cam = self.camera
        xy0 = self.xy[rows, cols]  # (N, 2)
        ja, jb, jc = distortion_jacobian(xy0, cam.dist)  # d(distorted)/d(undistorted)
        det = ja * jc - jb * jb
        # offsets in distorted normalised units (no skew in our K)
        dx = (offsets[:, 0] / cam.fx)[None, :]
        dy = (offsets[:, 1] / cam.fy)[None, :]
        xy = np.empty((len(rows), len(offsets), 2))
        xy[..., 0] = xy0[:, :1] + (jc / det)[:, None] * dx - (jb / det)[:, None] * dy
        xy[..., 1] = xy0[:, 1:] - (jb / det)[:, None] * dx + (ja / det)[:, None] * dy
        return xy


def exact_xy(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Undistorted normalised coordinates of arbitrary pixels by Newton (slow, exact)."""
    return undistort_normalized(camera.pixels_to_normalized(uv), camera.dist)


def pixel_offsets(n: int) -> np.ndarray:
    """Offsets (n*n, 2) (du, dv) of an n x n grid of samples centred in the pixel."""
    g = (np.arange(n) + 0.5) / n - 0.5
    du, dv = np.meshgrid(g, g)
    return np.stack([du.ravel(), dv.ravel()], -1)


def speckle_field(rng: np.random.Generator, mask: np.ndarray, contrast: float,
                  grain_px: float) -> np.ndarray:
    """Multiplicative log-normal speckle (mean 1, std ``contrast``) correlated over ~1 px.

    Drawn where ``mask`` (the laser band) is set, and 1 elsewhere: white Gaussian noise on the
    band grown by the filter's reach, Gaussian-filtered, renormalised to unit variance.
    """
    reach = int(np.ceil(4 * grain_px)) if grain_px > 0 else 0
    grown = cv2.dilate(mask, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)) if reach else mask
    idx = np.nonzero(grown.ravel())[0]
    g = np.zeros(mask.shape, np.float32)
    g.ravel()[idx] = rng.standard_normal(idx.size, dtype=np.float32)
    if grain_px > 0:
        g = cv2.GaussianBlur(g, (0, 0), grain_px, borderType=cv2.BORDER_CONSTANT)
        # renormalise to unit variance: the sum of squared kernel weights (2-D Gaussian)
        g *= np.float32(2.0 * np.sqrt(np.pi) * grain_px)
    s = np.sqrt(np.log1p(contrast**2))
    field = np.exp(np.float32(s) * g - np.float32(s * s / 2)).astype(np.float32)
    field[mask == 0] = 1.0
    return field


class SensorModel:
    """Electrons to digital numbers: PSF, PRNU, shot and read noise, clipping, quantisation."""

    def __init__(self, spec, bit_depth: int, prnu_map: np.ndarray | None):
        self.spec = spec
        self.bits = bit_depth
        self.gain = spec.gain_e_per_dn(bit_depth)
        self.black = spec.black_dn(bit_depth)
        self.top = 2**bit_depth - 1
        self.prnu_map = prnu_map  # full-sensor map, or None

    def blur(self, img: np.ndarray) -> np.ndarray:
        """Gaussian PSF blur of an electron image (float32)."""
        if self.spec.psf_sigma_px <= 0:
            return img
        return cv2.GaussianBlur(img, (0, 0), self.spec.psf_sigma_px, borderType=cv2.BORDER_REFLECT)

    def digitise(self, electrons: np.ndarray, rng: np.random.Generator,
                 window: tuple[int, int, int, int], noise: bool = True) -> np.ndarray:
        """DN image (uint8/uint16) of an electron image that is already blurred."""
        e = electrons.astype(np.float32, copy=True)
        if self.prnu_map is not None:
            x0, y0, w, h = window
            e *= self.prnu_map[y0 : y0 + h, x0 : x0 + w]
        np.maximum(e, 0.0, out=e)
        fw = self.spec.full_well_e
        if noise:
            # shot and read noise in one Gaussian draw (their sum is Gaussian) where the well
            # cannot fill; Poisson below 30 e-; shot, clip, then read noise near saturation
            lo_e, hi_e = float(e.min()), float(e.max())
            none = np.zeros(0, np.int64)
            low = np.nonzero((e < 30.0).ravel())[0] if lo_e < 30.0 else none
            near_full = fw - 6.0 * np.sqrt(fw)
            high = np.nonzero((e > near_full).ravel())[0] if hi_e > near_full else none
            flat = e.ravel()
            lam_low = flat[low].astype(np.float64)
            e_high = flat[high].astype(np.float64)
            sig = e + np.float32(self.spec.read_noise_e**2)
            np.sqrt(sig, out=sig)
            sig *= rng.standard_normal(e.shape, dtype=np.float32)
            e += sig
            if lam_low.size:
                flat[low] = (rng.poisson(lam_low) + self.spec.read_noise_e
                             * rng.standard_normal(lam_low.size)).astype(np.float32)
            if e_high.size:
                shot = np.minimum(e_high + np.sqrt(e_high) * rng.standard_normal(e_high.size), fw)
                flat[high] = (shot + self.spec.read_noise_e
                              * rng.standard_normal(e_high.size)).astype(np.float32)
        else:
            np.minimum(e, fw, out=e)
        e *= np.float32(1.0 / self.gain)
        e += np.float32(self.black)
        np.rint(e, out=e)
        np.clip(e, 0, self.top, out=e)
        dn = e
        return dn.astype(np.uint16 if self.bits == 16 else np.uint8)

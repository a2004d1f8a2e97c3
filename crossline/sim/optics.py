"""Camera rays through the distortion, and the sensor: PSF, speckle, noise, quantisation.

Rays. Every sample ray must reproject to its sensor position to well under 0.001 px. The
exact inverse of the distortion (Newton, ``crossline.camera.undistort_normalized``) is
computed on a coarse grid of sensor positions (every ``GRID_STEP`` px) and carried to every
pixel centre (and to the 2 x 2 sample positions of the scan window) by a tensor-product
cubic spline in float64 (matrix products; the render runs BLAS on one thread, see
``crossline.sim.capture``); a sample at another sub-pixel offset gets one step of the local
inverse Jacobian of the distortion from its pixel centre (second-order error < 1.4e-5 px
within half a pixel).
``tests/test_sim_optics.py`` checks the reprojection of random samples over the whole
sensor, corners included: < 1e-4 px.

Sensor. The optical image (electrons per pixel, float) goes through, in this order: PSF
blur (Gaussian, sigma ``psf_sigma_px``, lens and pixel crosstalk), photo-response
non-uniformity (a fixed per-pixel gain map), shot noise (Poisson; the Gaussian limit above 30
electrons, where the two differ by far less than the read noise), full-well clipping, read
noise (Gaussian, electrons), conversion to DN with the black level, rounding and clipping to
the ADC's data bits (``data_bits``: a 12-bit camera writes 0..4095 into 16-bit images). The
image is worked through in bands of rows that fit the CPU cache; the arithmetic and the
draws are those of one pass over the whole image.

Random draws. Every Gaussian of the sensor model, the speckle and the PRNU map comes from
``standard_normal_f32``: the Box-Muller transform of the generator's 64-bit words (two 32-bit
uniforms, two float32 normals per word), exact N(0, 1) to float32 precision with tails to
6.7 sigma, faster than numpy's float32 ziggurat. The dark (Poisson) and
near-saturation pixels keep numpy's Poisson and float64 normals. Each image has its own
generator (seeded by kind and index), so a capture does not depend on the number of workers.

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
image-plane grain the aperture forms. ``benchmarks/bench_speckle.py`` draws the same stripes
as coherent imaging (the amplitude PSF over the rough surface's random phases, squared,
mixed to contrast C) and compares the centres' scatter with this field's.
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
    "lattice_offsets",
    "pixel_offsets",
    "speckle_field",
    "standard_normal_f32",
]

GRID_STEP = 16  # px between exact (Newton) undistortions; the spline carries them to every pixel
HALF_ROWS = 32  # pixel rows per band in which the 2 x 2 sample positions are splined
NOISE_BLOCK = 1 << 16  # pixels per band of rows in digitise (cache-sized)


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
        self._half: np.ndarray | None = None  # 2 x 2 samples, (h, w, 4, 2), see sample_xy_2x2

    def sample_xy_2x2(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Undistorted coordinates (N, 4, 2) of the 2 x 2 samples (``pixel_offsets(2)`` order).

        Sample (a, b) of window pixel (r, c) sits at offset ((a - 0.5) / 2, (b - 0.5) / 2)
        from its centre; the same tensor-product spline as the pixel centres carries the
        coarse Newton grid there (computed on first use; see ``_half_grid``).
        """
        if self._half is None:
            self._half = self._half_grid()
        return self._half[rows, cols]

    def _half_grid(self) -> np.ndarray:
        """The 2 x 2 samples of every pixel, (h, w, 4, 2): a pixel's four side by side.

        The spline runs along u first (few coarse rows), then along v in bands of
        HALF_ROWS pixel rows: a third of the products of the other order, and no temporary
        larger than a band. Bands of fixed size (and one BLAS thread, set by the render): the
        same bytes in any process.
        """
        x0, y0, w, h = self.window
        uc, vc, xy = self._coarse_grid
        Mu = _spline_matrix(uc, x0 - 0.25 + 0.5 * np.arange(2 * w))
        Mv = _spline_matrix(vc, y0 - 0.25 + 0.5 * np.arange(2 * h))
        half = np.empty((h, w, 4, 2))
        along_u = [np.ascontiguousarray(xy[..., k] @ Mu.T) for k in range(2)]  # (len(vc), 2w)
        for r0 in range(0, h, HALF_ROWS):
            r1 = min(r0 + HALF_ROWS, h)
            for k in range(2):
                b = Mv[2 * r0 : 2 * r1] @ along_u[k]  # rows 2 r + b, columns 2 c + a
                b = b.reshape(r1 - r0, 2, w, 2).transpose(0, 2, 1, 3)  # [r, c, b, a]
                half[r0:r1, :, :, k] = b.reshape(r1 - r0, w, 4)  # sample a + 2 b
        return half

    def pixel_xy(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (N, 2) of window pixels (row, col indices)."""
        return self.xy[rows, cols]

    def sample_xy(self, rows: np.ndarray, cols: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Undistorted coordinates (N, S, 2) of samples at sub-pixel ``offsets`` (du, dv), the same
        (S, 2) for every pixel or (N, S, 2) one set per pixel.

        One step of the inverse distortion Jacobian from the pixel centre: its second-order
        error within half a pixel is below 2e-6 px for the paper's lens and 1.4e-5 px for the
        compact rig's (``tests/test_sim_optics.py`` checks < 1e-4 px everywhere).
        """
        cam = self.camera
        xy0 = self.xy[rows, cols]  # (N, 2)
        ja, jb, jc = distortion_jacobian(xy0, cam.dist)  # d(distorted)/d(undistorted)
        det = ja * jc - jb * jb
        # offsets in distorted normalised units (no skew in our K)
        off = np.broadcast_to(offsets, (len(rows), *np.shape(offsets)[-2:]))
        dx = off[..., 0] / cam.fx
        dy = off[..., 1] / cam.fy
        xy = np.empty(off.shape)
        xy[..., 0] = xy0[:, :1] + (jc / det)[:, None] * dx - (jb / det)[:, None] * dy
        xy[..., 1] = xy0[:, 1:] - (jb / det)[:, None] * dx + (ja / det)[:, None] * dy
        return xy


def standard_normal_f32(rng: np.random.Generator, n: int, out: np.ndarray | None = None) -> np.ndarray:
    """``n`` independent standard normal float32 draws (into ``out`` if given), Box-Muller.

    Each 64-bit word of the generator's stream gives two 32-bit uniforms u1 in (0, 1] and
    u2 in [0, 1) and two normals ``sqrt(-2 ln u1) (cos, sin)(2 pi u2)``, stored side by
    side: drawing n1 (even) and then n2 values gives the same values as drawing n1 + n2 at
    once. The transform is exact; in float32 the draws are N(0, 1) to float32 precision,
    with tails to 6.7 sigma (P(|z| > 6.7) = 2e-11 for a true normal). Faster than numpy's
    float32 ziggurat, which spends its time on per-sample branches.
    """
    m = (n + 1) // 2
    if out is None:
        out = np.empty(n, np.float32)
    words = rng.bit_generator.random_raw(m).view(np.uint32).reshape(m, 2)
    r = words[:, 0].astype(np.float32)
    r *= np.float32(2.0**-32)
    r += np.float32(2.0**-33)
    np.log(r, out=r)
    r *= np.float32(-2.0)
    np.sqrt(r, out=r)
    th = words[:, 1].astype(np.float32)
    th *= np.float32(2.0 * np.pi * 2.0**-32)
    k = n // 2  # full pairs; an odd n keeps the last cosine
    pairs = out[: 2 * k].reshape(k, 2)
    np.multiply(r[:k], np.cos(th[:k]), out=pairs[:, 0])
    np.multiply(r[:k], np.sin(th[:k]), out=pairs[:, 1])
    if n > 2 * k:
        out[n - 1] = r[k] * np.cos(th[k])
    return out


def exact_xy(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Undistorted normalised coordinates of arbitrary pixels by Newton (slow, exact)."""
    return undistort_normalized(camera.pixels_to_normalized(uv), camera.dist)


def pixel_offsets(n: int) -> np.ndarray:
    """Offsets (n*n, 2) (du, dv) of an n x n grid of samples centred in the pixel."""
    g = (np.arange(n) + 0.5) / n - 0.5
    du, dv = np.meshgrid(g, g)
    return np.stack([du.ravel(), dv.ravel()], -1)


def lattice_offsets(rows: np.ndarray, cols: np.ndarray, n: int) -> np.ndarray:
    """Offsets (N, n*n, 2) (du, dv) of n*n samples in each pixel (rows, cols): a sheared grid,
    one sample per cell of an n x n grid and each in its own one of n*n columns and rows
    ("n-rooks"), shifted per pixel by a deterministic low-discrepancy amount within a column.

    A regular n x n grid sees an edge parallel to the pixel rows or columns at only n
    positions, so the imaged edge is quantised to 1/n px, coherently all along it: a
    fronto-parallel chessboard's corners then sit up to ~0.2 px off with n = 4. The sheared
    grid quantises such an edge to 1/n² px with the same rays, and the per-pixel shift (an R2
    sequence over the pixel index, within +-1/(2 n²)) makes what is left unbiased and
    uncorrelated from pixel to pixel, as the exact integral over the pixel would be.
    """
    k = np.arange(n * n)
    i, j = np.divmod(k, n)
    base = np.stack([(n * i + j + 0.5) / (n * n) - 0.5, (n * j + i + 0.5) / (n * n) - 0.5], -1)
    g = 1.32471795724474602596  # the plastic number: R2 = (1/g, 1/g²) fills the square evenly
    idx = np.asarray(rows, dtype=np.float64) * 65536.0 + np.asarray(cols, dtype=np.float64)
    shift = (np.stack([np.mod(0.5 + idx / g, 1.0), np.mod(0.5 + idx / (g * g), 1.0)], -1) - 0.5) / (n * n)
    return base[None, :, :] + shift[:, None, :]


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
    g.ravel()[idx] = standard_normal_f32(rng, idx.size)
    if grain_px > 0:
        g = cv2.GaussianBlur(g, (2 * reach + 1, 2 * reach + 1), grain_px,
                             borderType=cv2.BORDER_CONSTANT)
    # the field only where the band is (a small part of its bounding box): 1 elsewhere
    at = np.flatnonzero(mask)
    ga = g.ravel()[at]
    if grain_px > 0:
        # renormalise to unit variance by the sampled kernel's own sum of squared weights: a
        # grain under a pixel is sampled coarsely, and the continuous Gaussian's 1 / (4 pi
        # sigma^2) would leave such a field with a contrast above C
        k1 = cv2.getGaussianKernel(2 * reach + 1, grain_px, cv2.CV_64F).ravel()
        ga *= np.float32(1.0 / float((k1 * k1).sum()))
    s = np.sqrt(np.log1p(contrast**2))
    field = np.ones(mask.shape, np.float32)
    field.ravel()[at] = np.exp(np.float32(s) * ga - np.float32(s * s / 2))
    return field


class SensorModel:
    """Electrons to digital numbers: PSF, PRNU, shot and read noise, clipping, quantisation."""

    def __init__(self, spec, bit_depth: int, prnu_map: np.ndarray | None,
                 data_bits: int | None = None):
        self.spec = spec
        self.bits = bit_depth  # the container (8 or 16)
        # the ADC's range: a 12-bit camera writes 0..4095 into its 16-bit images
        self.data_bits = int(data_bits or bit_depth)
        self.gain = spec.gain_e_per_dn(self.data_bits)
        self.black = spec.black_dn(self.data_bits)
        self.top = 2**self.data_bits - 1
        self.prnu_map = prnu_map  # full-sensor map, or None

    def blur(self, img: np.ndarray) -> np.ndarray:
        """Gaussian PSF blur of an electron image (float32)."""
        if self.spec.psf_sigma_px <= 0:
            return img
        return cv2.GaussianBlur(img, (0, 0), self.spec.psf_sigma_px, borderType=cv2.BORDER_REFLECT)

    def digitise(self, electrons: np.ndarray, rng: np.random.Generator,
                 window: tuple[int, int, int, int], noise: bool = True) -> np.ndarray:
        """DN image (uint8/uint16) of an electron image that is already blurred.

        Works through the image in bands of rows that fit in the CPU cache (one pass per band
        instead of ~15 passes over the whole image); every pixel gets the same arithmetic and
        the same random draws, in the same order, as a whole-image pass.
        """
        e_all = np.asarray(electrons)
        h, w = e_all.shape
        x0, y0 = window[0], window[1]
        prnu = None if self.prnu_map is None else self.prnu_map[y0 : y0 + h, x0 : x0 + w]
        out = np.empty((h, w), np.uint16 if self.bits == 16 else np.uint8)
        fw = self.spec.full_well_e
        near_full = fw - 6.0 * np.sqrt(fw)
        read2 = np.float32(self.spec.read_noise_e**2)
        inv_gain, black = np.float32(1.0 / self.gain), np.float32(self.black)
        step = max(1, NOISE_BLOCK // max(w, 1))
        step += step % 2 if w % 2 else 0  # an even number of draws per band (but the last)
        lows, highs = [], []
        z = np.empty(step * w, np.float32) if noise else None
        sig = np.empty(step * w, np.float32) if noise else None
        for r0 in range(0, h, step):
            r1 = min(r0 + step, h)
            n = (r1 - r0) * w
            if prnu is not None:
                e = np.multiply(e_all[r0:r1], prnu[r0:r1], dtype=np.float32).reshape(-1)
            else:
                e = e_all[r0:r1].astype(np.float32).reshape(-1)
            np.maximum(e, 0.0, out=e)
            if noise:
                # shot and read noise in one Gaussian draw (their sum is Gaussian) where the
                # well cannot fill; Poisson below 30 e-; shot, clip, then read noise near
                # saturation (those few pixels are redrawn after the whole image)
                if e.min() < 30.0:
                    i = np.nonzero(e < 30.0)[0]
                    lows.append((i + r0 * w, e[i].astype(np.float64)))
                if e.max() > near_full:
                    i = np.nonzero(e > near_full)[0]
                    highs.append((i + r0 * w, e[i].astype(np.float64)))
                s_ = sig[:n]
                np.add(e, read2, out=s_)
                np.sqrt(s_, out=s_)
                s_ *= standard_normal_f32(rng, n, out=z[:n])
                e += s_
            else:
                np.minimum(e, fw, out=e)
            out[r0:r1] = self._to_dn(e, inv_gain, black).reshape(r1 - r0, w)
        if lows:
            idx = np.concatenate([i for i, _ in lows])
            lam = np.concatenate([v for _, v in lows])
            v = (rng.poisson(lam) + self.spec.read_noise_e * rng.standard_normal(lam.size)).astype(np.float32)
            out.reshape(-1)[idx] = self._to_dn(v, inv_gain, black)
        if highs:
            idx = np.concatenate([i for i, _ in highs])
            e_high = np.concatenate([v for _, v in highs])
            shot = np.minimum(e_high + np.sqrt(e_high) * rng.standard_normal(e_high.size), fw)
            v = (shot + self.spec.read_noise_e * rng.standard_normal(e_high.size)).astype(np.float32)
            out.reshape(-1)[idx] = self._to_dn(v, inv_gain, black)
        return out

    def _to_dn(self, e: np.ndarray, inv_gain: np.float32, black: np.float32) -> np.ndarray:
        """Electrons (float32, modified in place) to rounded, clipped DN values (float32)."""
        e *= inv_gain
        e += black
        np.rint(e, out=e)
        np.clip(e, 0, self.top, out=e)
        return e

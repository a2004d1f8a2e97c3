"""Render images of a virtual rig: board views, laser stripes, scan frames, and the true stripe.

Every pixel value comes from rays traced from sensor positions through the exact inverse of
the lens distortion (``crossline.sim.optics``) into an analytic scene (``crossline.sim.scene``).
Three kinds of light:

* Board views (lasers off, bright ambient light), ``render_ambient_full``: rays on every 4th
  pixel centre find the surfaces; cells free of edges interpolate the smooth shading, every
  pixel near an albedo edge (circle rims, squares) or a change of surface is traced, and the
  pixels an edge crosses are supersampled with ``EDGE_SS`` x ``EDGE_SS`` (64) rays on a sheared
  grid (``optics.lattice_offsets``: an edge along the pixel rows or columns is resolved to
  1/64 px, not 1/8, and what is left is unbiased from pixel to pixel).
* Scan-exposure ambient (faint room light), ``render_ambient_coarse``: traced every
  ``COARSE_STEP`` px and interpolated bilinearly; it only makes the faint background.
* Laser light, ``render_band``: traced at full resolution inside the *band*, the pixels that can
  receive light from a sheet. The band comes from the exact curves where the sheet's centre
  plane meets the scene's surfaces (``Scene.sections``), projected and dilated by the image
  distance over which the plane distance reaches ``BAND_SIGMAS`` w on that surface (from the
  local gradient, with 10 % margin) plus the pixel footprint; surfaces the centre plane misses
  but that come within reach of the sheet's tail add the sections of parallel planes. Steps,
  occlusion boundaries and limbs cannot hide a stripe segment: every section curve is drawn,
  visible or not. Inside the band each pixel gets 2 x 2 samples; pixels whose samples see
  different surfaces or shadow states, that border another surface, lie on an albedo edge, or
  see a stripe narrower than 1 px (sigma) get 4 x 4. Every lit sample casts a shadow ray to its
  emitter.

The same curves give the true centreline (``stripe_truth``): for every image column, where the
projected curve of the centre plane crosses the column (solved to 1e-9 px), with the 3-D point
and whether it is lit (facing the emitter, inside the fan, not shadowed) and seen (facing the
camera, first along its ray).

The code lives in modules beside this one (issue 21.3): ``rig_model`` (``RigModel``,
``Light``, the sampling steps the renderers share), ``ambient`` (board views and the faint
scan-exposure light), ``stripe`` (section curves, the band mask and the true centreline) and
``band`` (laser light inside the band). This one composes an image (``render_image``) and
re-exports the names its importers use, so ``from crossline.sim.render import ...`` works
as before.
"""

from __future__ import annotations

import cv2
import numpy as np

from crossline.sim.ambient import EDGE_SS, render_ambient_coarse, render_ambient_full
from crossline.sim.ambient import _differs_at as _differs_at
from crossline.sim.ambient import _face_albedo as _face_albedo
from crossline.sim.band import render_band
from crossline.sim.optics import speckle_field
from crossline.sim.rig_model import COARSE_STEP, Light, RigModel
from crossline.sim.scene import Scene
from crossline.sim.stripe import stripe_truth

__all__ = [
    "COARSE_STEP",
    "EDGE_SS",
    "Light",
    "RigModel",
    "render_image",
    "stripe_truth",
]


# ----------------------------------------------------------------------------- images


def _nonzero(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.nonzero`` of a uint8 image (rows, cols in row-major order), by OpenCV (faster)."""
    pts = cv2.findNonZero(mask)
    if pts is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pts = pts.reshape(-1, 2).astype(np.int64)
    return pts[:, 1].copy(), pts[:, 0].copy()


def _background_at(img: np.ndarray, window, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The blurred ambient electrons (window image) at the pixels of full-sensor (u, v)."""
    x0, y0, w, h = window
    r = np.clip(np.rint(np.asarray(v) - y0).astype(np.int64), 0, h - 1)
    c = np.clip(np.asarray(u, dtype=np.int64) - x0, 0, w - 1)
    return img[r, c].astype(np.float64)


def render_image(model: RigModel, scene: Scene, light: Light, window, lasers: tuple[str, ...],
                 rng: np.random.Generator, ambient: str = "coarse", noise: bool = True,
                 speckle: bool = True, truth: bool = True, colour=None):
    """One image: DN array, true centreline rows per laser, and render statistics.

    ``colour`` (a ``crossline.sim.colour.ColourSensor``): the image is a Bayer mosaic,
    digitised and demosaiced into (h, w, 3) red, green, blue.
    """
    if ambient == "full":
        amb = render_ambient_full(model, scene, light, window)
    else:
        amb = render_ambient_coarse(model, scene, light, window)
    img = model.sensor.blur(amb)
    if colour is not None:
        img *= colour.ambient_gain(window)
    sheets = [model.lasers[k] for k in lasers]
    rows_by_laser = {}
    stats = {}
    if sheets:
        mask = np.zeros(amb.shape, np.uint8)
        for sh in sheets:
            m, rows, _ = stripe_truth(model, scene, sh, window, truth=truth)
            mask |= m
            if rows is not None:
                rows["background_e"] = _background_at(img, window, rows["u"], rows["v"])
            rows_by_laser[sh.name] = rows
        ys, xs = _nonzero(mask)
        vals, stats = render_band(model, scene, sheets, window, ys, xs)
        if ys.size:
            pad = 8
            y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, mask.shape[0])
            x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, mask.shape[1])
            sub_mask = mask[y0:y1, x0:x1]
            for k, sh in enumerate(sheets):
                sub = np.zeros((y1 - y0, x1 - x0), np.float32)
                sub[ys - y0, xs - x0] = vals[k]
                sub = model.sensor.blur(sub)
                if speckle and sh.spec.speckle_contrast > 0:
                    sub *= speckle_field(rng, sub_mask, sh.spec.speckle_contrast,
                                         sh.spec.speckle_grain_px)
                if colour is not None:
                    sub *= colour.laser_gain(sh.name, window, slice(y0, y1), slice(x0, x1))
                img[y0:y1, x0:x1] += sub
    dn = model.sensor.digitise(img, rng, window, noise=noise)
    if colour is not None:
        dn = colour.demosaic(dn, window)
    return dn, rows_by_laser, stats

"""Laser light inside the band: per-sheet electrons of the band's pixels, adaptively supersampled.

``render_band`` traces ``BAND_SS`` x ``BAND_SS`` samples in every band pixel
(``_laser_samples``: the sheets' irradiance, albedo, vignetting and a shadow ray to each
emitter) and traces ``FINE_SS`` x ``FINE_SS`` again in the pixels whose samples see different
surfaces or shadow states, that border another surface, lie on an albedo edge, or see a
stripe narrower than 1 px (sigma). Split from ``crossline.sim.render`` (issue 21.3), which
re-exports the names its importers use.
"""

from __future__ import annotations

import numpy as np

from crossline.sim.ambient import _differs_at
from crossline.sim.optics import pixel_offsets
from crossline.sim.rig_model import CHUNK, ORIGIN, RigModel, _rays, vignetting
from crossline.sim.scene import Scene, norm3, rowdot, take_rows
from crossline.sim.sheet import BAND_SIGMAS, LaserSheet
from crossline.sim.stripe import _plane_gradient_px

__all__ = ["BAND_SS", "FINE_SS", "render_band"]

BAND_SS = 2  # samples per axis in the smooth part of a laser band
FINE_SS = 4  # samples per axis where the band's integrand is not smooth


def _laser_samples(model: RigModel, scene: Scene, sheets: list[LaserSheet], xy: np.ndarray):
    """Per-sheet electrons at undistorted sample coordinates (N, 2), with refinement cues.

    Returns electrons (len(sheets), N), surface codes (N,), shadow state per sheet (0 dark,
    1 lit, 2 shadowed), whether the stripe is narrower than 1 px (sigma) there, and whether
    an albedo edge lies within the sample's pixel footprint.
    """
    cam = model.camera
    d = _rays(xy)
    t, pid, face = scene.trace(ORIGIN, d)
    hit = np.isfinite(t)
    n = len(d)
    out = np.zeros((len(sheets), n))
    code = np.where(hit, pid.astype(np.int32) * 16 + face, -1)
    shadow = np.zeros((len(sheets), n), np.int8)
    narrow = np.zeros(n, bool)
    edge = np.zeros(n, bool)
    hi = np.nonzero(hit)[0]
    if hi.size == 0:
        return out, code, shadow, narrow, edge
    P = t[hi, None] * take_rows(d, hi)
    near = np.zeros((len(sheets), hi.size), bool)
    fw = []
    for k, sh in enumerate(sheets):
        f = sh.distance(P)
        w = sh.width(norm3(P - sh.e))
        near[k] = np.abs(f) < BAND_SIGMAS * w
        fw.append((f, w))
    ja = np.nonzero(near.any(0))[0]
    if ja.size == 0:
        return out, code, shadow, narrow, edge
    Pa = take_rows(P, ja)
    ia = hi[ja]
    N, alb, edist = scene.shade(Pa, pid[ia], face[ia], edges=scene.textured)
    if edist is not None:
        dist = norm3(Pa)
        cos = np.abs(rowdot(N, Pa)) / dist
        edge[ia] = edist < dist / (min(cam.fx, cam.fy) * np.maximum(cos, 1e-3))
    vig = vignetting(xy.take(ia, axis=0))
    for k, sh in enumerate(sheets):
        j = np.nonzero(near[k, ja])[0]
        if j.size == 0:
            continue
        f, w = fw[k][0][ja[j]], fw[k][1][ja[j]]
        Pj, Nj = take_rows(Pa, j), take_rows(N, j)
        E = sh.irradiance(Pj, Nj, f)
        lit = np.flatnonzero(E > 0)  # facing the emitter (cosine > 0) and inside the fan
        if lit.size:
            blk = scene.blocked(take_rows(Pj, lit), sh.e, on=pid[ia[j[lit]]])
            E[lit[blk]] = 0.0
            shadow[k, ia[j[lit]]] = np.where(blk, 2, 1)
        out[k, ia[j]] = E * alb[j] * vig[j]
        # the stripe's width in the image: sigma = w/2 over |grad f| (mm per px)
        sig = np.flatnonzero(np.abs(f) < 2.0 * w)
        if sig.size:
            grad = _plane_gradient_px(take_rows(Pj, sig), take_rows(Nj, sig), sh.n, cam)
            narrow[ia[j[sig]]] |= 0.5 * w[sig] < 1.0 * grad
    return out, code, shadow, narrow, edge


def render_band(model: RigModel, scene: Scene, sheets: list[LaserSheet], window,
                rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, dict]:
    """Laser electrons (len(sheets), n) of band pixels (rows, cols), adaptively supersampled."""
    table = model.table(window)
    stats = {"band_px": int(rows.size), "fine_px": 0, "samples": 0}
    if rows.size == 0:
        return np.zeros((len(sheets), 0), np.float32), stats
    offs = pixel_offsets(BAND_SS)
    S = len(offs)
    n = rows.size
    vals = np.zeros((len(sheets), n))
    pcode = np.zeros(n, np.int32)
    refine = np.zeros(n, bool)
    step = max(1, CHUNK // S)
    fast = BAND_SS == 2 and tuple(window) == model.scan_window
    for a in range(0, n, step):
        r, c = rows[a : a + step], cols[a : a + step]
        xy = (table.sample_xy_2x2(r, c) if fast else table.sample_xy(r, c, offs)).reshape(-1, 2)
        e, code, shadow, narrow, edge = _laser_samples(model, scene, sheets, xy)
        m = len(r)
        vals[:, a : a + m] = e.reshape(len(sheets), m, S).mean(2)
        code = code.reshape(m, S)
        pcode[a : a + m] = code[:, 0]
        ref = np.any(code != code[:, :1], axis=1)
        sh = shadow.reshape(len(sheets), m, S)
        ref |= np.any((sh.max(2) == 2) & (sh.min(2) < 2), axis=0)
        ref |= narrow.reshape(m, S).any(1) | edge.reshape(m, S).any(1)
        refine[a : a + m] = ref
        stats["samples"] += m * S
    # pixels next to another surface inside the band (within the band's bounding box)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    cimg = np.full((r1 - r0 + 2, c1 - c0 + 2), -2, np.int32)  # with a border
    cimg[rows - r0 + 1, cols - c0 + 1] = pcode
    refine |= _differs_at(cimg, rows - r0, cols - c0, ignore=-2)
    ri = np.nonzero(refine)[0]
    stats["fine_px"] = int(ri.size)
    if ri.size:
        offs4 = pixel_offsets(FINE_SS)
        S4 = len(offs4)
        step = max(1, CHUNK // S4)
        for a in range(0, ri.size, step):
            sel = ri[a : a + step]
            xy = table.sample_xy(rows[sel], cols[sel], offs4).reshape(-1, 2)
            e, _, _, _, _ = _laser_samples(model, scene, sheets, xy)
            vals[:, sel] = e.reshape(len(sheets), len(sel), S4).mean(2)
            stats["samples"] += len(sel) * S4
    return vals.astype(np.float32), stats

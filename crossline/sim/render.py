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
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from crossline.camera import Camera, distort_normalized
from crossline.sim.optics import (
    RayTable,
    SensorModel,
    exact_xy,
    lattice_offsets,
    pixel_offsets,
    speckle_field,
    standard_normal_f32,
)
from crossline.sim.scene import Curve, Scene, dot3, empty3, norm3, rowdot, take_rows
from crossline.sim.sheet import BAND_SIGMAS, LaserSheet

__all__ = [
    "COARSE_STEP",
    "EDGE_SS",
    "Light",
    "RigModel",
    "render_image",
    "stripe_truth",
]

EDGE_SS = 8  # samples per axis (a sheared grid: 64 rays) on albedo and geometric edges (board views)
BAND_SS = 2  # samples per axis in the smooth part of a laser band
FINE_SS = 4  # samples per axis where the band's integrand is not smooth
COARSE_STEP = 8  # px between rays of the faint scan-exposure ambient light
NODE_STEP = 4  # px between the first rays of a board view (edges are then traced per pixel)
CHUNK = 1 << 15  # rays traced at once: the temporaries of a chunk stay in the CPU cache
ORIGIN = np.zeros(3)


@dataclass(frozen=True)
class Light:
    """Ambient light: electrons on a white surface facing ``up``, a gentle gradient."""

    e_white: float
    up: np.ndarray  # unit vector towards the light (camera frame)
    grad: np.ndarray  # relative change per mm (camera frame)
    ref: np.ndarray  # point where the gradient is zero (camera frame)

    def electrons(self, P: np.ndarray, N: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        """Electrons (before vignetting) from points with normals and albedos."""
        k = 0.6 + 0.4 * np.maximum(0.0, dot3(N, self.up))
        return self.e_white * albedo * k * (1.0 + dot3(P - self.ref, self.grad))


def vignetting(xy: np.ndarray) -> np.ndarray:
    """Natural cos^4 fall-off of the field angle for undistorted normalised coordinates."""
    r2 = xy[..., 0] ** 2 + xy[..., 1] ** 2
    return 1.0 / (1.0 + r2) ** 2


class RigModel:
    """The rig's camera, lasers and sensor, with per-process caches of rays."""

    def __init__(self, preset, bit_depth: int | None = None, seed: int = 0,
                 data_bits: int | None = None):
        self.preset = preset
        s = preset.sensor
        self.camera = Camera(np.array(s.K), np.array(s.dist), (s.width, s.height))
        self.bits = int(bit_depth or s.bit_depth)
        # the ADC's bits inside the container: the rig's (or the container's), at most the container's
        self.data_bits = min(int(data_bits or s.data_bits or self.bits), self.bits)
        self.lasers = {k: LaserSheet(k, v) for k, v in preset.lasers.items()}
        self.sensor_window = (0, 0, s.width, s.height)
        self.scan_window = tuple(int(v) for v in s.scan_window)
        rng = np.random.default_rng([int(seed), 1001])
        prnu = standard_normal_f32(rng, s.height * s.width).reshape(s.height, s.width)
        self.prnu = (1.0 + np.float32(s.prnu) * prnu).astype(np.float32)
        self.sensor = SensorModel(s, self.bits, self.prnu, self.data_bits)
        self._tables: dict = {}
        self._coarse: dict = {}
        self._bounds: dict = {}

    def table(self, window) -> RayTable:
        """Exact rays of every pixel of a window (cached).

        The table reaches NODE_STEP px beyond the window's right and bottom edges, so that the
        grid of every NODE_STEP-th pixel centre (board views) covers the whole window.
        """
        window = tuple(window)
        if window not in self._tables:
            x0, y0, w, h = window
            self._tables[window] = RayTable(self.camera, (x0, y0, w + NODE_STEP, h + NODE_STEP))
        return self._tables[window]

    def coarse(self, window):
        """Exact rays on the coarse ambient grid of a window: (xy (ch, cw, 2))."""
        window = tuple(window)
        if window not in self._coarse:
            x0, y0, w, h = window
            cw, ch = -(-w // COARSE_STEP), -(-h // COARSE_STEP)
            u = x0 + COARSE_STEP * np.arange(cw) + (COARSE_STEP - 1) / 2
            v = y0 + COARSE_STEP * np.arange(ch) + (COARSE_STEP - 1) / 2
            U, V = np.meshgrid(u, v)
            xy = exact_xy(self.camera, np.stack([U.ravel(), V.ravel()], -1)).reshape(ch, cw, 2)
            self._coarse[window] = xy
        return self._coarse[window]

    def bounds(self, window, margin: float):
        """Undistorted normalised bounds (xmin, xmax, ymin, ymax) of a window plus margin px."""
        key = (tuple(window), margin)
        if key not in self._bounds:
            x0, y0, w, h = window
            a = np.linspace(0, 1, 101)
            u0, u1 = x0 - 0.5 - margin, x0 + w - 0.5 + margin
            v0, v1 = y0 - 0.5 - margin, y0 + h - 0.5 + margin
            pts = np.concatenate([
                np.stack([u0 + a * (u1 - u0), np.full_like(a, v0)], -1),
                np.stack([u0 + a * (u1 - u0), np.full_like(a, v1)], -1),
                np.stack([np.full_like(a, u0), v0 + a * (v1 - v0)], -1),
                np.stack([np.full_like(a, u1), v0 + a * (v1 - v0)], -1),
            ])
            xy = exact_xy(self.camera, pts)
            pad = 0.02 * (np.ptp(xy[:, 0]) + np.ptp(xy[:, 1]))
            self._bounds[key] = (xy[:, 0].min() - pad, xy[:, 0].max() + pad,
                                 xy[:, 1].min() - pad, xy[:, 1].max() + pad)
        return self._bounds[key]

    def project(self, P: np.ndarray) -> np.ndarray:
        """Pixels of camera-frame points (z > 0)."""
        return self.camera.project(P)


# ----------------------------------------------------------------------------- tracing


def _rays(xy: np.ndarray) -> np.ndarray:
    """Camera rays (x, y, 1) of undistorted coordinates (N, 2), column-major (N, 3)."""
    d = empty3(len(xy))
    d[:, 0] = xy[:, 0]
    d[:, 1] = xy[:, 1]
    d[:, 2] = 1.0
    return d


def _ambient_light(scene: Scene, light: Light, xy: np.ndarray) -> np.ndarray:
    """Ambient electrons only (no edge information) for undistorted coordinates (N, 2)."""
    d = _rays(xy)
    t, pid, face = scene.trace(ORIGIN, d)
    hit = np.isfinite(t)
    e = np.zeros(len(d))
    if hit.any():
        hit = np.flatnonzero(hit)
        P = t[hit, None] * take_rows(d, hit)
        N, alb, _ = scene.shade(P, pid[hit], face[hit])
        e[hit] = light.electrons(P, N, alb) * vignetting(xy.take(hit, axis=0))
    return e


def _ambient_samples(scene: Scene, light: Light, xy: np.ndarray, cam: Camera,
                     with_edges: bool = False):
    """Ambient electrons, surface code and edge flag for undistorted coordinates (N, 2).

    With ``with_edges`` also the distance to the nearest albedo/face edge and the pixel
    footprint (mm) of every ray.
    """
    d = _rays(xy)
    t, pid, face = scene.trace(ORIGIN, d)
    hit = np.isfinite(t)
    e = np.zeros(len(d))
    code = np.full(len(d), -1, np.int32)
    near_edge = np.zeros(len(d), bool)
    edge_all = np.zeros(len(d))
    fp_all = np.full(len(d), np.inf)
    alb_all = np.zeros(len(d))
    if hit.any():
        hit = np.flatnonzero(hit)
        P = t[hit, None] * take_rows(d, hit)
        N, alb, edge = scene.shade(P, pid[hit], face[hit], edges=True)
        e[hit] = light.electrons(P, N, alb) * vignetting(xy.take(hit, axis=0))
        code[hit] = pid[hit].astype(np.int32) * 16 + face[hit]
        dist = norm3(P)
        cos = np.abs(rowdot(N, P)) / dist
        footprint = dist / (min(cam.fx, cam.fy) * np.maximum(cos, 1e-3))
        near_edge[hit] = edge < 1.0 * footprint
        edge_all[hit] = edge
        fp_all[hit] = footprint
        alb_all[hit] = alb
    if with_edges:
        return e, code, near_edge, edge_all, fp_all, alb_all
    return e, code, near_edge


def _ambient_nodes(model: RigModel, window) -> np.ndarray:
    """Rays (nh, nw, 2) of every NODE_STEP-th pixel centre, covering the window (from its table)."""
    w, h = window[2], window[3]
    xy = model.table(window).xy
    nh = -(-(h - 1) // NODE_STEP) + 1
    nw = -(-(w - 1) // NODE_STEP) + 1
    return xy[: nh * NODE_STEP : NODE_STEP, : nw * NODE_STEP : NODE_STEP]


def _differs_at(code: np.ndarray, rows: np.ndarray, cols: np.ndarray, ignore: int) -> np.ndarray:
    """Whether any 8-neighbour of the listed pixels holds another code (``ignore`` matches none).

    ``code`` carries a border of ``ignore`` one pixel wide: ``rows``, ``cols`` index the image
    inside it (``code[rows + 1, cols + 1]``), so no neighbour falls outside the array.
    """
    W = code.shape[1]
    flat = code.reshape(-1)
    at = (rows + 1) * W + (cols + 1)
    mine = flat.take(at)
    out = np.zeros(rows.size, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx == 0 and dy == 0:
                continue
            other = flat.take(at + (dy * W + dx))
            out |= (other != mine) & (other != ignore)
    return out


def render_ambient_full(model: RigModel, scene: Scene, light: Light, window) -> np.ndarray:
    """Ambient electrons of every pixel, supersampled on edges (board views).

    Rays are traced on the grid of every 4th pixel centre first (the nodes). Within a 4 x 4
    cell whose corners see the same surface the shading (light x vignetting) is smooth and is
    interpolated bilinearly (error below 1e-4 of the signal); the albedo is exact:

    * the distance to the nearest albedo or face edge is 1-Lipschitz on the surface, so a pixel
      whose distance bound from some corner (that corner's edge distance minus the pixel's
      distance to it, in mm, with 25 % margin) exceeds its half diagonal holds no edge and has
      that corner's albedo;
    * every other pixel of such a cell is supersampled EDGE_SS x EDGE_SS: the sample rays meet
      the corners' face (its exact plane) and the albedo is averaged over the samples.

    Cells whose corners see different surfaces (silhouettes, the plate's sides), and the cells
    around them, are traced pixel by pixel, and pixels at an edge or beside another surface
    are supersampled with full tracing of every sample.
    """
    w, h = window[2], window[3]
    nodes = _ambient_nodes(model, window)
    nh, nw = nodes.shape[:2]
    flat = nodes.reshape(-1, 2)
    parts = [_ambient_samples(scene, light, flat[a : a + CHUNK], model.camera, with_edges=True)
             for a in range(0, len(flat), CHUNK)]
    e, code, _, edge, fp, alb = (np.concatenate(x) for x in zip(*parts, strict=True))
    shade = np.where(alb > 0, e / np.where(alb > 0, alb, 1.0), 0.0)
    e = e.reshape(nh, nw).astype(np.float32)
    code = code.reshape(nh, nw)
    edge, fp, alb = edge.reshape(nh, nw), fp.reshape(nh, nw), alb.reshape(nh, nw)
    clear = edge > NODE_STEP / np.sqrt(2.0) * 1.25 * fp
    same = (code[:-1, :-1] == code[1:, :-1]) & (code[:-1, :-1] == code[:-1, 1:]) & \
           (code[:-1, :-1] == code[1:, 1:]) & (code[:-1, :-1] >= 0)
    smooth = same & clear[:-1, :-1] & clear[1:, :-1] & clear[:-1, 1:] & clear[1:, 1:]
    # a thin surface (a plate's side seen edge-on) may hide between two corners that see the
    # same surface: the cells around every change of surface are traced pixel by pixel
    mixed = cv2.dilate((~same).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    edgy = ~smooth & ~mixed
    # node (i, j) sits on pixel (4 i, 4 j): pixel (r, c) reads the nodes at (r / 4, c / 4)
    M = np.array([[1.0 / NODE_STEP, 0.0, 0.0], [0.0, 1.0 / NODE_STEP, 0.0]])
    img = cv2.warpAffine(e, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REPLICATE)
    table = model.table(window)
    S = EDGE_SS * EDGE_SS

    def cell_pixels(cells):
        ci, cj = np.nonzero(cells)
        oy, ox = np.divmod(np.arange(NODE_STEP * NODE_STEP), NODE_STEP)
        r = (ci[:, None] * NODE_STEP + oy[None, :]).ravel()
        c = (cj[:, None] * NODE_STEP + ox[None, :]).ravel()
        keep = (r < h) & (c < w)
        return r[keep], c[keep]

    # --- cells on one surface with an edge near: albedo by the Lipschitz bound, or supersampled.
    # Corner values are gathered per cell, and every quantity that depends on the pixel only
    # through its offset (oy, ox) in the cell (its bilinear weights, its distance to each
    # corner) is a table of NODE_STEP^2 entries: (cells, offsets) arrays, raveled in the
    # order of cell_pixels.
    ci, cj = np.nonzero(edgy)
    if ci.size:
        oy, ox = np.divmod(np.arange(NODE_STEP * NODE_STEP), NODE_STEP)
        rows = (ci[:, None] * NODE_STEP + oy[None, :]).ravel()
        cols = (cj[:, None] * NODE_STEP + ox[None, :]).ravel()
        keep = (rows < h) & (cols < w)
        rows, cols = rows[keep], cols[keep]
        ti, tj = oy / NODE_STEP, ox / NODE_STEP  # pixel (4 i + oy, 4 j + ox) in cell (i, j)
        corner = {(di, dj): (ci + di, cj + dj) for di in (0, 1) for dj in (0, 1)}
        sf = shade.reshape(nh, nw)
        f00, f01, f10, f11 = (sf[corner[k]][:, None] for k in ((0, 0), (0, 1), (1, 0), (1, 1)))
        sh = ((1 - ti) * ((1 - tj) * f00 + tj * f01) + ti * ((1 - tj) * f10 + tj * f11)).ravel()[keep]
        best = np.full((ci.size, ti.size), -np.inf)
        best_alb = np.zeros((ci.size, ti.size))
        fpmax = np.zeros(ci.size)
        for (di, dj), at in corner.items():
            fpc = fp[at]
            fpmax = np.maximum(fpmax, fpc)
            dpx = np.hypot(oy - di * NODE_STEP, ox - dj * NODE_STEP)
            b = edge[at][:, None] - (1.25 * dpx)[None, :] * fpc[:, None]
            better = b > best
            best = np.where(better, b, best)
            best_alb = np.where(better, alb[at][:, None], best_alb)
        fpmax = np.repeat(fpmax, ti.size)[keep]
        best, best_alb = best.ravel()[keep], best_alb.ravel()[keep]
        inner = best > 0.75 * 1.25 * fpmax
        img[rows[inner], cols[inner]] = (sh[inner] * best_alb[inner]).astype(np.float32)
        er, ec, esh, efp = rows[~inner], cols[~inner], sh[~inner], fpmax[~inner]
        ecode = code[er // NODE_STEP, ec // NODE_STEP]
        # the rest: the exact edge distance at the pixel centre decides
        a_c, on_c, e_c = _face_albedo(scene, ecode, table.xy[er, ec], edges=True)
        clear_c = on_c & (e_c > 0.75 * 1.25 * efp)
        img[er[clear_c], ec[clear_c]] = (a_c[clear_c] * esh[clear_c]).astype(np.float32)
        er, ec, esh, ecode = er[~clear_c], ec[~clear_c], esh[~clear_c], ecode[~clear_c]
        step = max(1, CHUNK // S)
        fallback = []
        for a in range(0, er.size, step):
            r, c, cc = er[a : a + step], ec[a : a + step], ecode[a : a + step]
            sxy = table.sample_xy(r, c, lattice_offsets(r, c, EDGE_SS)).reshape(-1, 2)
            a_s, on = _face_albedo(scene, np.repeat(cc, S), sxy)
            on = on.reshape(-1, S).all(1)
            img[r[on], c[on]] = (a_s.reshape(-1, S).mean(1)[on] * esh[a : a + step][on]).astype(np.float32)
            fallback.append((r[~on], c[~on]))
        mixed_px = (np.concatenate([f[0] for f in fallback]),
                    np.concatenate([f[1] for f in fallback])) if fallback else None
    else:
        mixed_px = None
    # --- cells where surfaces change: every pixel traced, edges fully supersampled
    rows, cols = cell_pixels(mixed)
    if mixed_px is not None:
        rows, cols = np.concatenate([rows, mixed_px[0]]), np.concatenate([cols, mixed_px[1]])
    if rows.size:
        r0, c0 = rows.min(), cols.min()
        shape = (rows.max() - r0 + 1, cols.max() - c0 + 1)
        pcode = np.full((shape[0] + 2, shape[1] + 2), -3, np.int32)  # with a border
        near = np.zeros(shape, bool)
        for a in range(0, rows.size, CHUNK):
            r, c = rows[a : a + CHUNK], cols[a : a + CHUNK]
            ev, cv_, nr = _ambient_samples(scene, light, table.xy[r, c], model.camera)
            img[r, c] = ev
            pcode[r - r0 + 1, c - c0 + 1] = cv_
            near[r - r0, c - c0] = nr
        flag = near[rows - r0, cols - c0] | _differs_at(pcode, rows - r0, cols - c0, ignore=-3)
        rows, cols = rows[flag], cols[flag]
        step = max(1, CHUNK // S)
        for a in range(0, len(rows), step):
            r, c = rows[a : a + step], cols[a : a + step]
            sxy = table.sample_xy(r, c, lattice_offsets(r, c, EDGE_SS)).reshape(-1, 2)
            es = _ambient_samples(scene, light, sxy, model.camera)[0]
            img[r, c] = es.reshape(-1, S).mean(1)
    return img


def _face_albedo(scene: Scene, codes: np.ndarray, xy: np.ndarray, edges: bool = False):
    """Albedo where camera rays (undistorted xy) meet the face of each surface code.

    Returns the albedos, whether each ray meets the face inside its outline (else the pixel
    must be traced in full) and, with ``edges``, the distance (mm) to the nearest albedo edge
    or face border.
    """
    n = len(xy)
    if n and (codes == codes[0]).all():  # the common case: one face, no masks and copies
        groups = [(int(codes[0]), None)]
    else:
        groups = [(int(c), codes == c) for c in np.unique(codes)]
    out = np.zeros(n)
    on = np.zeros(n, bool)
    edist = np.zeros(n) if edges else None
    for c, m in groups:
        prim = scene.prims[c // 16]
        face = c % 16
        xm = xy if m is None else xy[m]
        if hasattr(prim, "face_planes"):
            a, ok, em = _box_face_albedo(prim, face, xm[:, 0], xm[:, 1], edges)
        else:  # planes and curved surfaces: trace them exactly
            d = _rays(xm)
            t, pid, fc = scene.trace(ORIGIN, d)
            ok = np.isfinite(t) & (pid == prim.pid) & (fc == face)
            P = t[ok, None] * d[ok]
            a = np.zeros(len(d))
            em = np.zeros(len(d))
            if ok.any():
                _, a[ok], em[ok] = scene.shade(P, pid[ok], fc[ok], edges=True)
        if m is None:
            out, on = a, ok
            if edges:
                edist = em
        else:
            out[m] = a
            on[m] = ok
            if edges:
                edist[m] = em
    if edges:
        return out, on, edist
    return out, on


def _box_face_albedo(prim, face: int, x: np.ndarray, y: np.ndarray, edges: bool):
    """Albedo, inside-the-outline flag and edge distance where rays (x, y, 1) meet a box face.

    The arithmetic is ``Box.local`` of the hit points written out per coordinate, only for
    the coordinates needed (the two in the face, and the texture's).
    """
    _, p0, nf = prim.face_planes()[face]
    t = (p0 @ nf) / (x * nf[0] + y * nf[1] + nf[2])  # the ray (x, y, 1) meets the face plane
    a0, a1, a2 = t * x - prim.c[0], t * y - prim.c[1], t - prim.c[2]  # hit point - box centre
    R = prim.R
    axis = face // 2
    tex = prim.textures.get(face)
    need = {j for j in range(3) if j != axis} | ({0, 1} if tex is not None else set())
    q = {j: a0 * R[0, j] + a1 * R[1, j] + a2 * R[2, j] for j in sorted(need)}
    inside = None
    slack = None
    for j in range(3):
        if j != axis:
            aq = np.abs(q[j])
            inside = aq <= prim.h[j] if inside is None else inside & (aq <= prim.h[j])
            if edges:
                sj = prim.h[j] - aq
                slack = sj if slack is None else np.minimum(slack, sj)
    if tex is not None:
        a, em = tex.xy(q[0], q[1], edges)
        if edges:
            slack = np.minimum(slack, em)
    else:
        a = np.full(len(x), prim.albedo_value)
    return a, inside & (t > 0), slack


def render_ambient_coarse(model: RigModel, scene: Scene, light: Light, window) -> np.ndarray:
    """Faint ambient electrons on a coarse grid, interpolated bilinearly to every pixel."""
    xy = model.coarse(window)
    ch, cw = xy.shape[:2]
    e = _ambient_light(scene, light, xy.reshape(-1, 2))
    img = e.reshape(ch, cw).astype(np.float32)
    big = cv2.resize(img, (cw * COARSE_STEP, ch * COARSE_STEP), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(big[: window[3], : window[2]])


# ----------------------------------------------------------------------------- curves


def _clip_line(p, u, t0, t1, bounds, zmin):
    """Parameter interval of the line p + t u inside the view frustum (undistorted bounds)."""
    xmin, xmax, ymin, ymax = bounds
    # a + b t >= 0 for each constraint
    cons = [
        (p[2] - zmin, u[2]),
        (p[0] - xmin * p[2], u[0] - xmin * u[2]),
        (xmax * p[2] - p[0], xmax * u[2] - u[0]),
        (p[1] - ymin * p[2], u[1] - ymin * u[2]),
        (ymax * p[2] - p[1], ymax * u[2] - u[1]),
    ]
    lo, hi = t0, t1
    for a, b in cons:
        if abs(b) < 1e-15:
            if a < 0:
                return None
            continue
        r = -a / b
        if b > 0:
            lo = max(lo, r)
        else:
            hi = min(hi, r)
    return (lo, hi) if lo < hi else None


@dataclass
class CurveSamples:
    """Dense samples of one section curve: parameters, points, normals, pixels, validity."""

    curve: Curve
    t: np.ndarray
    P: np.ndarray
    N: np.ndarray
    uv: np.ndarray
    valid: np.ndarray  # a surface point of the scene, in front of the camera
    in_view: np.ndarray


def _project(cam: Camera, P: np.ndarray, zmin: float) -> np.ndarray:
    uv = np.full((len(P), 2), np.nan)
    ok = P[:, 2] > zmin
    if ok.any():
        uv[ok] = cam.normalized_to_pixels(distort_normalized(P[ok, :2] / P[ok, 2:3], cam.dist))
    return uv


def _in_bounds(P, bounds, zmin):
    xmin, xmax, ymin, ymax = bounds
    z = P[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = P[:, 0] / z, P[:, 1] / z
    return (z > zmin) & (x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)


def sample_curve(curve: Curve, scene: Scene, cam: Camera, bounds, zmin: float = 1.0,
                 spacing_px: float = 1.0) -> CurveSamples | None:
    """Samples of a curve no more than ``spacing_px`` apart in the image, validity refined."""
    t0, t1 = curve.t0, curve.t1
    if not curve.closed:
        P0, _, _ = curve.fn(np.array([0.0, 1.0]))
        clip = _clip_line(P0[0], P0[1] - P0[0], t0, t1, bounds, zmin)
        if clip is None:
            return None
        t0, t1 = clip
    n0 = 512 if curve.closed else 129
    t = np.linspace(t0, t1, n0)
    P, _, _ = curve.fn(t)
    vis = _in_bounds(P, bounds, zmin)
    if not vis.any():
        return None
    uv = _project(cam, P, zmin)
    seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
    both = vis[:-1] | vis[1:]
    seg = np.where(both & np.isfinite(seg), seg, 0.0)
    nsub = np.clip(np.ceil(seg / spacing_px), 1, 20000).astype(int)
    nsub = np.where(both, nsub, 1)
    # keep only intervals that touch the view
    idx = np.repeat(np.arange(len(nsub)), nsub)
    first = np.repeat(np.cumsum(nsub) - nsub, nsub)
    frac = (np.arange(nsub.sum()) - first) / nsub[idx]
    tt = t[idx] + frac * np.diff(t)[idx]
    tt = np.append(tt[np.repeat(both, nsub)], t[-1])
    tt = np.unique(tt)
    return _evaluate(curve, scene, cam, bounds, zmin, tt)


def _validity(curve, scene, P, v0, zmin):
    ok = v0 & (P[:, 2] > zmin)
    if ok.any():
        ok[ok] = ~scene.inside_other(P[ok], curve.prim)
    return ok


def _evaluate(curve, scene, cam, bounds, zmin, t, refine: bool = True) -> CurveSamples:
    P, N, v0 = curve.fn(t)
    valid = _validity(curve, scene, P, v0, zmin)
    if refine:
        flip = np.nonzero(valid[:-1] != valid[1:])[0]
        if flip.size:
            a, b = t[flip].copy(), t[flip + 1].copy()
            va = valid[flip]
            for _ in range(48):
                m = 0.5 * (a + b)
                Pm, _, vm0 = curve.fn(m)
                vm = _validity(curve, scene, Pm, vm0, zmin)
                same = vm == va
                a = np.where(same, m, a)
                b = np.where(same, b, m)
            tb = np.where(va, a, b)  # the boundary, on its valid side
            t = np.unique(np.concatenate([t, tb]))
            P, N, v0 = curve.fn(t)
            valid = _validity(curve, scene, P, v0, zmin)
    uv = _project(cam, P, zmin)
    return CurveSamples(curve, t, P, N, uv, valid, _in_bounds(P, bounds, zmin))


def _column_crossings(cs: CurveSamples, cam: Camera, scene: Scene, zmin: float):
    """Points of a sampled curve at every integer image column it crosses (valid parts)."""
    u = cs.uv[:, 0]
    ok = cs.valid[:-1] & cs.valid[1:] & np.isfinite(u[:-1]) & np.isfinite(u[1:])
    ua, ub = u[:-1], u[1:]
    lo = np.floor(np.minimum(ua, ub)) + 1
    hi = np.floor(np.maximum(ua, ub))
    cnt = np.where(ok, np.maximum(hi - lo + 1, 0), 0).astype(int)
    if cnt.sum() == 0:
        return None
    seg = np.repeat(np.arange(len(cnt)), cnt)
    k = lo[seg] + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    ta, tb = cs.t[seg].copy(), cs.t[seg + 1].copy()
    fa, fb = ua[seg] - k, ub[seg] - k
    # Illinois (regula falsi) on u(t) - k inside the bracket; converged roots leave the set
    side = np.zeros(len(k), int)
    t_out = 0.5 * (ta + tb)
    act = np.arange(len(k))
    kk = k.copy()
    for _ in range(60):
        with np.errstate(divide="ignore", invalid="ignore"):
            tm = np.where(fb != fa, (ta * fb - tb * fa) / (fb - fa), 0.5 * (ta + tb))
        tm = np.where((tm - ta) * (tm - tb) <= 0, tm, 0.5 * (ta + tb))
        P, _, _ = cs.curve.fn(tm)
        fm = _project(cam, P, zmin)[:, 0] - kk
        t_out[act] = tm
        done = np.abs(fm) < 1e-9
        if done.all():
            break
        left = np.sign(fm) == np.sign(fa)
        ta = np.where(left, tm, ta)
        fa = np.where(left, fm, fa)
        tb = np.where(left, tb, tm)
        fb = np.where(left, fb, fm)
        # Illinois: halve the stale end's value to keep superlinear convergence
        fb = np.where(left & (side == 1), fb / 2, fb)
        fa = np.where(~left & (side == -1), fa / 2, fa)
        side = np.where(left, 1, -1)
        keep = ~done
        act, ta, tb, fa, fb, side, kk = (x[keep] for x in (act, ta, tb, fa, fb, side, kk))
    tm = t_out
    P, N, _ = cs.curve.fn(tm)
    uv = _project(cam, P, zmin)
    return k.astype(np.int64), uv[:, 1], P, N


def _plane_gradient_px(P, N, n_plane, cam: Camera) -> np.ndarray:
    """|grad f| (mm per px) of the plane distance f seen across the image on a surface.

    A pixel step moves the ray by (1/fx, 0, 0) (or (0, 1/fy, 0)) in normalised coordinates;
    the hit point moves within the tangent plane: dP = z (dr - N (N . dr) / (N . r)).
    Distortion changes the local scale by a few per cent; callers add margin.
    """
    r = P / P[:, 2:3]
    Nr = rowdot(N, r)
    Nr = np.where(np.abs(Nr) < 1e-9, 1e-9, Nr)
    z = P[:, 2]
    g = []
    for axis, f in ((0, cam.fx), (1, cam.fy)):
        e = np.zeros(3)
        e[axis] = 1.0 / f
        dP = z[:, None] * (e[None, :] - N * (dot3(N, e) / Nr)[:, None])
        g.append(dot3(dP, n_plane))
    return np.hypot(g[0], g[1])


BAND_MARGIN = 1.1  # safety factor on the band's half-width (distortion, curvature)


def _band_radius(P, N, n_plane, half_mm, cam: Camera):
    """Image radius (px) in which the plane distance changes by ``half_mm`` on the surface.

    Plus 1 px for the pixel's footprint (half diagonal 0.71 px); the PSF spreads the light
    beyond the band afterwards (the blur runs over the whole image region).
    """
    grad = _plane_gradient_px(P, N, n_plane, cam)
    rad = BAND_MARGIN * half_mm / np.maximum(grad, 1e-12) + 1.0
    return np.minimum(rad, 300.0)


def _cap_sections(prim, n, d, reach: float, step: float) -> list:
    """Sections of planes parallel to the sheet, within ``reach``, on surfaces it does not cut.

    The sheet's Gaussian tail lights surfaces up to BAND_SIGMAS w from its centre plane even
    where the centre plane misses them (a ball just below the sheet, a face beside an edge).
    """
    out = []
    offsets = np.arange(step, reach + 1e-12, step)
    if hasattr(prim, "face_planes"):
        uncut = [f for f, _, _ in prim.face_planes()
                 if f not in prim.hidden and not prim.sections(n, d, faces=(f,))]
        if not uncut:
            return out
        for o in offsets:
            for s in (-1.0, 1.0):
                out.extend(prim.sections(n, d + s * o, faces=tuple(uncut)))
        return out
    if prim.sections(n, d):
        return out
    for o in offsets:
        for s in (-1.0, 1.0):
            out.extend(prim.sections(n, d + s * o))
    return out


def stripe_truth(model: RigModel, scene: Scene, sheet: LaserSheet, window, margin: float = 64.0,
                 truth: bool = True):
    """Band mask (window sized, uint8) and true centreline rows of one sheet in one image."""
    cam = model.camera
    x0, y0, w, h = window
    bounds = model.bounds(window, margin)
    zmin = 1.0
    base = []
    for c in scene.sections(sheet.n, sheet.d):
        cs = sample_curve(c, scene, cam, bounds, zmin)
        if cs is not None:
            base.append(cs)
    s_all = [norm3(cs.P[cs.valid & cs.in_view] - sheet.e) for cs in base]
    s_all = np.concatenate(s_all) if s_all else np.zeros(0)
    s_hi = s_all.max() + 20.0 if s_all.size else sheet.s0 + 2 * sheet.zr
    w_ref = float(sheet.width(np.array([sheet.s0, s_hi])).max())
    mask = np.zeros((h, w), np.uint8)
    for cs in base:
        good = cs.valid & cs.in_view & np.isfinite(cs.uv[:, 0])
        if good.any():
            rad = np.zeros(len(good))
            half = BAND_SIGMAS * sheet.width(norm3(cs.P[good] - sheet.e))
            rad[good] = _band_radius(cs.P[good], cs.N[good], sheet.n, half, cam)
            _draw_band(mask, cs.uv - np.array([x0, y0]), rad, good)
    for prim in scene.prims:
        for c in _cap_sections(prim, sheet.n, sheet.d, BAND_SIGMAS * w_ref, w_ref):
            cs = sample_curve(c, scene, cam, bounds, zmin, spacing_px=2.0)
            if cs is None:
                continue
            good = cs.valid & cs.in_view & np.isfinite(cs.uv[:, 0])
            if good.any():
                rad = np.zeros(len(good))
                rad[good] = _band_radius(cs.P[good], cs.N[good], sheet.n, w_ref, cam)
                _draw_band(mask, cs.uv - np.array([x0, y0]), rad, good)
    rows = None
    if truth:
        parts = []
        for cs in base:
            res = _column_crossings(cs, cam, scene, zmin)
            if res is None:
                continue
            u, v, P, N = res
            inside = (u >= x0) & (u < x0 + w) & (v >= y0 - 0.5) & (v < y0 + h - 0.5)
            if not inside.any():
                continue
            u, v, P, N = u[inside], v[inside], P[inside], N[inside]
            parts.append((u, v, P, N, np.full(len(u), cs.curve.prim)))
        if parts:
            u, v, P, N, prim = (np.concatenate(x) for x in zip(*parts, strict=True))
            seen = _unoccluded(scene, P, N)
            lit = _lit(scene, sheet, P, N)
            # how squarely the camera sees the surface and the sheet lights it: a stripe on a
            # face seen at grazing angle is true but nearly invisible
            cos_view = -rowdot(N, P) / norm3(P)
            to_e = sheet.e - P
            cos_inc = rowdot(N, to_e) / norm3(to_e)
            order = np.lexsort((v, u))
            rows = {
                "u": u[order], "v": v[order], "x_cam": P[order, 0], "y_cam": P[order, 1],
                "z_cam": P[order, 2], "visible": (seen & lit)[order], "lit": lit[order],
                "unoccluded": seen[order], "surface": np.array(
                    [scene.prims[i].name for i in prim[order]], dtype=object),
                "cos_view": cos_view[order], "cos_incidence": cos_inc[order],
            }
    return mask, rows, w_ref


def _draw_band(mask, uv, rad, good):
    """Thick polylines through consecutive good samples (sub-pixel, round joins)."""
    shift = 2
    idx = np.nonzero(good)[0]
    if idx.size == 0:
        return
    # split into runs of consecutive indices, then into chunks of similar radius
    breaks = np.nonzero(np.diff(idx) != 1)[0] + 1
    for run in np.split(idx, breaks):
        for a in range(0, len(run), 24):
            ch = run[max(a - 1, 0) : a + 24]
            pts = np.rint(uv[ch] * (1 << shift)).astype(np.int32)
            thick = int(2 * np.ceil(rad[ch].max()) + 1)
            if len(ch) == 1:
                cv2.circle(mask, tuple(int(x) for x in pts[0]), thick // 2 * (1 << shift), 1, -1,
                           cv2.LINE_8, shift)
            else:
                cv2.polylines(mask, [pts.reshape(-1, 1, 2)], False, 1, thick, cv2.LINE_8, shift)


def _unoccluded(scene: Scene, P: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Points that face the camera and are the first hit along their camera ray."""
    front = rowdot(N, P) < 0
    t, _, _ = scene.trace(ORIGIN, P, tmin=1e-9)
    return front & (t >= 1.0 - 1e-9)


def _lit(scene: Scene, sheet: LaserSheet, P: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Points that face the emitter, lie in its fan and see it without obstruction."""
    toward = rowdot(N, sheet.e - P) > 0
    fan = sheet.in_fan(P) > 0
    ok = toward & fan
    if ok.any():
        ok[ok] = ~scene.blocked(P[ok], sheet.e)
    return ok


# ----------------------------------------------------------------------------- laser band


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


# ----------------------------------------------------------------------------- images


def _nonzero(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.nonzero`` of a uint8 image (rows, cols in row-major order), by OpenCV (faster)."""
    pts = cv2.findNonZero(mask)
    if pts is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pts = pts.reshape(-1, 2).astype(np.int64)
    return pts[:, 1].copy(), pts[:, 0].copy()


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

"""Ambient light: board views supersampled on their edges, and the faint scan-exposure light.

``render_ambient_full`` (board views, lasers off) traces every ``NODE_STEP``-th pixel centre,
interpolates the cells free of edges, takes the albedo of pixels near an edge from the
edge-distance bound or from ``EDGE_SS`` x ``EDGE_SS`` samples on the face (``_face_albedo``,
``_box_face_albedo``), and traces the cells where surfaces change pixel by pixel;
``render_ambient_coarse`` traces every ``COARSE_STEP`` px and interpolates bilinearly.
``_differs_at`` (whether a pixel borders another surface) is shared with the laser band.
Split from ``crossline.sim.render`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

import cv2
import numpy as np

from crossline.camera import Camera
from crossline.sim.optics import lattice_offsets
from crossline.sim.rig_model import CHUNK, COARSE_STEP, NODE_STEP, ORIGIN, Light, RigModel, _rays, vignetting
from crossline.sim.scene import Scene, norm3, rowdot, take_rows

__all__ = ["EDGE_SS", "render_ambient_coarse", "render_ambient_full"]

EDGE_SS = 8  # samples per axis (a sheared grid: 64 rays) on albedo and geometric edges (board views)


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

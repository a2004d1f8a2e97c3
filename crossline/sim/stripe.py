"""The true stripe: where a sheet's centre plane meets the scene, as seen in the image.

The section curves of the scene (``Scene.sections``) are sampled densely in the image
(``sample_curve``, ``CurveSamples``; the borders of their valid parts refined by bisection).
``stripe_truth`` draws from them the band mask, the pixels that can receive a sheet's light
(each curve dilated by ``_band_radius``, plus the sections of parallel planes that the sheet's
tail reaches, ``_cap_sections``), and solves the true centreline at every image column a
curve crosses (``_column_crossings``), with whether each point is lit and seen. Split from
``crossline.sim.render`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from crossline.camera import Camera, distort_normalized
from crossline.sim.rig_model import ORIGIN, RigModel
from crossline.sim.scene import Curve, Scene, dot3, norm3, rowdot
from crossline.sim.sheet import BAND_SIGMAS, LaserSheet

__all__ = ["BAND_MARGIN", "CurveSamples", "sample_curve", "stripe_truth"]

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
    the hit point moves within the tangent plane: dP = z (dr - r (N . dr) / (N . r)).
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
        dP = z[:, None] * (e[None, :] - r * (dot3(N, e) / Nr)[:, None])
        g.append(dot3(dP, n_plane))
    return np.hypot(g[0], g[1])


def _plane_change_per_row(P, N, n_plane, cam: Camera) -> np.ndarray:
    """d f / d v (mm per px): the change of the plane distance f from one image row to the next
    on the surface's tangent plane at P (normal N).

    The ray r = P / z moves by dr = (0, 1/fy, 0); its hit on the plane N . X = N . P moves by
    dP = z (dr - r (N . dr) / (N . r)) (to first order; distortion changes the scale by a few
    per cent).
    """
    r = P / P[:, 2:3]
    Nr = rowdot(N, r)
    Nr = np.where(np.abs(Nr) < 1e-9, 1e-9, Nr)
    dr = np.array([0.0, 1.0 / cam.fy, 0.0])
    dP = P[:, 2:3] * (dr[None, :] - r * (dot3(N, dr) / Nr)[:, None])
    return dot3(dP, n_plane)


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
            seen, hit_pid, hit_face = _unoccluded(scene, P, N)
            lit = _lit(scene, sheet, P, N)
            # how squarely the camera sees the surface and the sheet lights it: a stripe on a
            # face seen at grazing angle is true but nearly invisible
            cos_view = -rowdot(N, P) / norm3(P)
            to_e = sheet.e - P
            cos_inc = rowdot(N, to_e) / norm3(to_e)
            peak_e, sigma_px = _profile_truth(scene, sheet, cam, P, N, prim, hit_pid, hit_face)
            order = np.lexsort((v, u))
            rows = {
                "u": u[order], "v": v[order], "x_cam": P[order, 0], "y_cam": P[order, 1],
                "z_cam": P[order, 2], "visible": (seen & lit)[order], "lit": lit[order],
                "unoccluded": seen[order], "surface": np.array(
                    [scene.prims[i].name for i in prim[order]], dtype=object),
                "cos_view": cos_view[order], "cos_incidence": cos_inc[order],
                "peak_e": peak_e[order], "sigma_px": sigma_px[order],
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


def _unoccluded(scene: Scene, P: np.ndarray, N: np.ndarray):
    """Points that face the camera and are the first hit along their camera ray; the first
    hit's primitive index and face."""
    front = rowdot(N, P) < 0
    t, pid, face = scene.trace(ORIGIN, P, tmin=1e-9)
    return front & (t >= 1.0 - 1e-9), pid, face


def _profile_truth(scene: Scene, sheet: LaserSheet, cam: Camera, P: np.ndarray, N: np.ndarray,
                   prim: np.ndarray, hit_pid: np.ndarray, hit_face: np.ndarray):
    """The true stripe profile along the image column at centreline points: its peak
    (electrons per pixel area: white irradiance x albedo x vignetting, before the PSF and the
    speckle; NaN where the camera ray meets another surface first) and its Gaussian sigma
    along the column (px, before the PSF: w(s) / 2 over |d f / d v|)."""
    from crossline.sim.rig_model import vignetting

    own = (hit_pid == np.array([scene.prims[i].pid for i in prim], dtype=hit_pid.dtype))
    alb = np.full(len(P), np.nan)
    if own.any():
        j = np.flatnonzero(own)
        _, a, _ = scene.shade(P[j], hit_pid[j], hit_face[j])
        alb[j] = a
    peak = sheet.irradiance(P, N, np.zeros(len(P))) * alb * vignetting(P[:, :2] / P[:, 2:3])
    gv = _plane_change_per_row(P, N, sheet.n, cam)
    sigma = 0.5 * sheet.width(norm3(P - sheet.e)) / np.maximum(np.abs(gv), 1e-12)
    return peak, sigma


def _lit(scene: Scene, sheet: LaserSheet, P: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Points that face the emitter, lie in its fan and see it without obstruction."""
    toward = rowdot(N, sheet.e - P) > 0
    fan = sheet.in_fan(P) > 0
    ok = toward & fan
    if ok.any():
        ok[ok] = ~scene.blocked(P[ok], sheet.e)
    return ok

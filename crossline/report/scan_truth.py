"""A scan's figures against the simulator's truth, for the report's validation part.

``_label_truth`` (wrong A/B labels against the true centre lines), ``_speckle_limit`` (the
speckle bound on a stripe's centre against the centres' achieved sigma), ``_gauge_truth``
and ``_plane4`` (a gauge block against its true planes), ``read_mesh`` and
``_mesh_deviation`` (a freeform's points against its true mesh). Split from
``crossline.report.accuracy`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from crossline.robust import MAD_TO_SIGMA

__all__ = ["read_mesh", "surface_distances", "uncertainty_coverage"]

# the report stage's logger, as before the split: its records keep their name
log = logging.getLogger("crossline.report.accuracy")


def _label_truth(points: Path, centrelines: Path, files: list) -> dict[str, Any] | None:
    """Wrong A/B labels of the AB-frame points against the simulator's true centre lines."""
    import pandas as pd

    from crossline.report import metrics as mt

    if not centrelines.is_file():
        return None
    files.append(("capture", f"truth/{centrelines.name}", centrelines))
    try:
        p = pd.read_parquet(points, columns=["frame", "laser", "lasers", "u", "v"])
        t = pd.read_parquet(centrelines, columns=["frame", "laser", "u", "v", "visible"])
    except Exception as exc:  # pyarrow raises several types for broken files
        log.warning("label validation skipped: %s", exc)
        return None
    p = p[p["lasers"] == "AB"]
    t = t[t["visible"]]
    return mt.label_errors(p["frame"].to_numpy(), p["laser"].to_numpy(), p["u"].to_numpy(),
                           p["v"].to_numpy(), t["frame"].to_numpy(), t["laser"].to_numpy(),
                           t["u"].to_numpy(), t["v"].to_numpy())


def _mixture_sigma(sigmas: np.ndarray) -> float:
    """Robust sigma (1.4826 x the median absolute value) of zero-mean normal errors whose
    sigmas are ``sigmas``, one draw each: what the achieved robust sigma estimates."""
    from scipy.special import ndtr

    s = np.asarray(sigmas, dtype=np.float64)
    s = s[np.isfinite(s) & (s > 0)]
    if s.size == 0:
        return float("nan")
    lo, hi = 0.0, 10.0 * float(s.max())
    for _ in range(60):  # the median of |e|: the share of |e| <= q is 1/2
        q = 0.5 * (lo + hi)
        if float(np.mean(2.0 * ndtr(q / s) - 1.0)) < 0.5:
            lo = q
        else:
            hi = q
    return MAD_TO_SIGMA * 0.5 * (lo + hi)


SENSOR_ROWS = 20000  # true centre points per laser the sensor bound is evaluated at, at most
STRIPE_ROWS = 2000  # of those, the points the bound of speckle and sensor together is taken at


def _sensor_profiles(centrelines: Path | None, sensor: dict,
                     found: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, dict] | None:
    """Per laser: the true profiles of the visible centre points as they reach the pixels (peak
    and sigma after the PSF, background) from truth/<scan>_centrelines.parquet, along the
    profile the extractor took there (column or row) and its cosine to the line's normal, at
    the (frame, column) keys where the pipeline found a point of that laser (``found``: the
    sorted keys frame * 2^20 + column and the profile's axis there, 0 column, 1 row, -1
    unknown: the row where the line is steeper than 45 deg), and the sensor's read noise with
    the ADC's rounding (gain^2 / 12) and PRNU."""
    import pandas as pd

    need = ["frame", "laser", "u", "v", "visible", "peak_e", "sigma_px", "background_e"]
    if centrelines is None or not centrelines.is_file() or sensor.get("read_noise_e") is None:
        return None
    try:
        t = pd.read_parquet(centrelines, columns=need)
    except Exception:  # pyarrow raises several types; an older capture lacks the profile columns
        return None
    psf = float(sensor.get("psf_sigma_px") or 0.0)
    read = float(np.hypot(float(sensor["read_noise_e"]), float(sensor.get("gain_e_per_dn") or 0.0)
                          / np.sqrt(12.0)))
    prnu = float(sensor.get("prnu") or 0.0)
    out = {}
    for name, g in t[t["visible"]].groupby("laser"):
        g = g.sort_values(["frame", "u"], kind="stable")
        a, s, b = (g[c].to_numpy(np.float64) for c in ("peak_e", "sigma_px", "background_e"))
        cos_c, cos_r = _line_cosines(g["frame"].to_numpy(np.int64), g["u"].to_numpy(np.int64),
                                     g["v"].to_numpy(np.float64))
        key = g["frame"].to_numpy(np.int64) * (1 << 20) + g["u"].to_numpy(np.int64)
        keys, axes = found.get(str(name), (np.zeros(0, np.int64), np.zeros(0, np.int8)))
        at = np.searchsorted(keys, key).clip(0, max(keys.size - 1, 0))
        ok = np.isfinite(a) & np.isfinite(s) & np.isfinite(b) & (a > 0) & (s > 0)
        ok &= (keys[at] == key) if keys.size else np.zeros(key.size, bool)
        axis = axes[at] if keys.size else np.full(key.size, -1)
        # a column profile of a steep line holds several pixels of its length, a row one about one
        row = (axis == 1) | ((axis < 0) & (cos_r > cos_c))
        cos_p = np.where(row, cos_r, cos_c)
        a, s, b, cos_c, cos_p = a[ok], s[ok], b[ok], cos_c[ok], cos_p[ok]
        if a.size > SENSOR_ROWS:  # a fixed sample: the same report from the same capture
            k = np.random.default_rng(0).choice(a.size, SENSOR_ROWS, replace=False)
            a, s, b, cos_c, cos_p = a[k], s[k], b[k], cos_c[k], cos_p[k]
        if a.size < 10:
            continue
        # the truth's sigma runs along the column: across the line it is s cos_c; the PSF
        # widens that, keeping the electrons (the peak falls by the same ratio); the profile
        # the extractor takes crosses the line at cosine cos_p, so it is 1 / cos_p as wide
        sn = s * cos_c
        st = np.hypot(sn, psf)
        out[str(name)] = {"peak_e": a * sn / st, "sigma_px": st / cos_p, "background_e": b,
                          "read_noise_e": read, "prnu": prnu, "cosine": cos_p}
    return out


def _line_cosines(frame: np.ndarray, u: np.ndarray,
                  v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per true centre point, from the line's slope (:func:`~crossline.report.validation.
    true_line_at`): the cosines between the line's normal and the column, and the row (the
    two profiles the extractor can take)."""
    from crossline.report.validation import true_line_at

    span = int(u.max(initial=0)) + 4
    key = (frame * span + u).astype(np.float64)
    order = np.lexsort((v, key))
    _, slope = true_line_at(key[order], v[order], span, frame, u.astype(np.float64), v)
    h = np.hypot(1.0, slope)
    return 1.0 / h, np.abs(slope) / h


SPACING_ROWS = 2_000_000  # points read for the spacing along the stripes, at most
NEXT_PX = 6.0  # px across: the farthest a stripe's point one profile on may lie (a steep cut)
CROSS_SPAN = 1e5  # px: more than any frame's extent (a key for sorting by profile, then across)


def stripe_spacing_mm(points: Path) -> dict[str, float]:
    """Per laser: the median distance (mm) between a stripe's points one profile apart (the
    next column, or row for a row-profiled stripe) in the same frame, the nearest across of
    the stripe pieces there, from the first ``SPACING_ROWS`` points of the points file."""
    import pyarrow.parquet as pq

    from crossline.io.columns import LASER_CODES, laser_codes_of

    f = pq.ParquetFile(points)
    names = set(f.schema_arrow.names)
    need = ["frame", "laser", "u", "v", "x", "y", "z"]
    if not set(need) <= names:
        return {}
    cols = need + (["axis"] if "axis" in names else [])
    parts, n = [], 0
    for g in range(f.num_row_groups):
        t = f.read_row_group(g, columns=cols)
        parts.append(t)
        n += t.num_rows
        if n >= SPACING_ROWS:
            break
    if not parts:
        return {}
    import pyarrow as pa

    t = pa.concat_tables(parts)
    frame = t["frame"].to_numpy().astype(np.int64)
    laser = laser_codes_of(t["laser"])
    axis = t["axis"].to_numpy().astype(np.int64) if "axis" in cols else np.zeros(t.num_rows, np.int64)
    trace = np.where(axis == 1, t["v"].to_numpy(), t["u"].to_numpy())
    cross = np.where(axis == 1, t["u"].to_numpy(), t["v"].to_numpy())
    xyz = np.stack([t[c].to_numpy() for c in ("x", "y", "z")], 1)
    out = {}
    for name, code in LASER_CODES.items():
        m = np.flatnonzero((laser == code) & np.isfinite(trace) & np.isfinite(cross))
        if m.size < 3:
            continue
        # each point's neighbour one profile on, in the same frame and profile axis: of the
        # points there (one per stripe piece), the one nearest across, if within NEXT_PX
        span = int(np.rint(trace[m]).max()) + 2
        key = (frame[m] * 2 + axis[m]) * span + np.rint(trace[m]).astype(np.int64)
        o = np.lexsort((cross[m], key))
        k, c, idx = key[o], cross[m][o], m[o]
        comp = k.astype(np.float64) * CROSS_SPAN + c
        q = (k + 1).astype(np.float64) * CROSS_SPAN + c
        at = np.searchsorted(comp, q)
        best = np.full(k.size, -1)
        gap = np.full(k.size, np.inf)
        for j in (at - 1, at):
            jj = j.clip(0, k.size - 1)
            d = np.abs(c[jj] - c)
            take = (j >= 0) & (j < k.size) & (k[jj] == k + 1) & (d < gap)
            best, gap = np.where(take, jj, best), np.where(take, d, gap)
        ok = gap <= NEXT_PX
        if ok.sum() >= 10:
            out[name] = float(np.median(np.linalg.norm(xyz[idx[ok]] - xyz[idx[best[ok]]], axis=1)))
    return out


def _speckle_limit(centre: dict, truth: dict, points: Path, smooth_px: int | None = None,
                   centrelines: Path | None = None) -> dict[str, Any] | None:
    """Per laser: the speckle bound on one profile's centre (px, :mod:`crossline.report.speckle`,
    from the rig's optics in truth.json), the same after the centre lines' smoothing
    (``smooth_px`` columns, as if the columns' speckle were independent: the lower end), the
    centres' achieved robust sigma against the true lines, and its ratio to each.

    With the true centre lines' profiles (``centrelines``: peak, sigma, background of each
    true point where the pipeline found one), also the sensor's bound (shot and read noise,
    Cramér-Rao, one per true point) and the combined bound (speckle of the rig's contrast and
    grain and the sensor's noise together, for each profile's width:
    :func:`~crossline.report.speckle.stripe_bound_px`), each summarised as the robust sigma of
    errors drawn with the points' bounds, like the achieved sigma; and the achieved sigma's
    ratio to the combined bound, for one profile and after the smoothing (neighbouring profiles
    sharing speckle grains).
    """
    from crossline.io.columns import LASER_CODES, read_columns
    from crossline.report import speckle as sp
    from crossline.scan.centreline import half_amplitude_columns

    sensor, cam = truth.get("sensor") or {}, truth.get("camera") or {}
    pitch, fno = sensor.get("pixel_pitch_um"), sensor.get("f_number")
    if not (pitch and fno and cam.get("K") and centre):
        return None
    try:
        z = read_columns(points, ["frame", "laser", "u", "z_cam", "axis"])
    except Exception:  # pyarrow raises several types for broken files
        return None
    if "z_cam" not in z or "laser" not in z:  # an older points file without camera coordinates
        return None
    found = {}
    if "frame" in z and "u" in z:
        key = z["frame"].astype(np.int64) * (1 << 20) + np.rint(z["u"]).astype(np.int64)
        axis = z["axis"].astype(np.int8) if "axis" in z else np.full(key.size, -1, np.int8)
        for n, c in LASER_CODES.items():
            keys, first = np.unique(key[z["laser"] == c], return_index=True)
            found[n] = (keys, axis[z["laser"] == c][first])
    profiles = _sensor_profiles(centrelines, sensor, found) or {}
    try:
        spacing = stripe_spacing_mm(points)
    except Exception:  # pyarrow raises several types for broken files
        spacing = {}
    ripple = half_amplitude_columns(int(smooth_px)) if smooth_px else float("inf")
    fx = float(cam["K"][0][0])
    out: dict[str, Any] = {}
    for name, ce in centre.items():
        las = (truth.get("lasers") or {}).get(name) or {}
        zl = z["z_cam"][z["laser"] == LASER_CODES.get(name, -1)].astype(np.float64)
        if not (las.get("speckle_contrast") is not None and las.get("wavelength_nm") and zl.size):
            continue
        # magnification at the points' median depth: f / z, f = fx * pitch
        m = fx * float(pitch) * 1e-3 / float(np.median(zl))
        b = sp.centre_bound_px(float(las["speckle_contrast"]), float(las["wavelength_nm"]),
                            float(fno), float(pitch), m)
        gain = sp.smoothing_gain(int(smooth_px)) if smooth_px else 1.0
        sig = ce["sigma_px"]
        row = {"bound_px": b, "achieved_sigma_px": sig,
               "ratio": sig / b if b > 0 else None,
               "smooth_px": smooth_px, "bound_smoothed_px": b * gain,
               "ratio_smoothed": sig / (b * gain) if b > 0 else None,
               "contrast": float(las["speckle_contrast"]),
               "wavelength_nm": float(las["wavelength_nm"]), "f_number": float(fno),
               "pixel_um": float(pitch), "magnification": m}
        if name in spacing:
            # the lateral resolution the smoothing leaves along the stripe: the points' spacing
            # and the ripple it passes at half amplitude
            row.update({"spacing_mm": spacing[name],
                        "half_amplitude_mm": spacing[name] * ripple if np.isfinite(ripple) else None})
        pr = profiles.get(name)
        if pr is not None:
            # one profile's bound, along it; across the line (as the achieved sigma) it is
            # the profile's cosine to the line's normal times that
            each = pr["cosine"] * sp.sensor_bound_px(pr["peak_e"], pr["sigma_px"],
                                                     pr["background_e"], pr["read_noise_e"],
                                                     pr["prnu"])
            sb = _mixture_sigma(each)
            # speckle and sensor together, for each profile's width (a fixed sample: a
            # covariance matrix per profile costs far more than the sensor's sums)
            k = np.arange(each.size)
            if k.size > STRIPE_ROWS:
                k = np.sort(np.random.default_rng(0).choice(k.size, STRIPE_ROWS, replace=False))
            grain = las.get("speckle_grain_px") or sp.grain_px(
                float(las["wavelength_nm"]), float(fno), float(pitch))
            one, smooth = sp.stripe_bound_px(
                pr["peak_e"][k], pr["sigma_px"][k], pr["background_e"][k], pr["read_noise_e"],
                pr["prnu"], contrast=float(las["speckle_contrast"]), grain=float(grain),
                step_px=1.0 / pr["cosine"][k], smooth_px=int(smooth_px) if smooth_px else None)
            cb = _mixture_sigma(pr["cosine"][k] * one)
            cbs = _mixture_sigma(pr["cosine"][k] * smooth) if smooth is not None else cb
            row.update({
                "sensor_bound_px": sb, "combined_bound_px": cb, "grain_px": float(grain),
                "ratio_combined": sig / cb if cb > 0 else None,
                "combined_bound_smoothed_px": cbs,
                "ratio_combined_smoothed": sig / cbs if cbs > 0 else None,
                "sensor": {"points": int(each.size),
                           "peak_e": float(np.median(pr["peak_e"])),
                           "sigma_px": float(np.median(pr["sigma_px"])),
                           "background_e": float(np.median(pr["background_e"])),
                           "read_noise_e": pr["read_noise_e"], "prnu": pr["prnu"]}})
        out[name] = row
    return out or None


# figures compared with the truth that have a Monte Carlo U: error key in the scan's truth ->
# the uncertainty's figure
COVERED = {"mean_error_mm": "mean_mm", "diameter_error_mm": "diameter_mm",
           "length_error_mm": "length_mm"}


def uncertainty_coverage(truth: dict[str, Any], figures: dict[str, Any]) -> dict[str, Any]:
    """Each truth-compared error over the expanded uncertainty U of its figure: the normalised
    error E_n = error / U (as ISO 13528 scores a result against a reference value whose own
    uncertainty is nil); U covers the error where |E_n| <= 1.

    An uncertainty that misses the truth on many rigs leaves out a contributor: the validation
    shows it beside the error rather than only the error.
    """
    out: dict[str, Any] = {}
    for key, fig in COVERED.items():
        err, u = truth.get(key), (figures.get(fig) or {}).get("U")
        if not (isinstance(err, int | float) and isinstance(u, int | float)) or not np.isfinite(u) \
                or u <= 0:
            continue
        en = float(err) / float(u)
        out[fig] = {"error_mm": float(err), "U_mm": float(u), "E_n": en, "covered": abs(en) <= 1.0}
    return out


def _plane4(v: list, like: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    n = np.asarray(v[:3], dtype=np.float64)
    s = np.linalg.norm(n)
    n, d = n / s, float(v[3]) / s
    if like is not None and float(n @ like) < 0:
        n, d = -n, -d
    return n, d


def surface_distances(points: np.ndarray, truth_scan: dict[str, Any],
                      near_mm: float = 0.2) -> dict[str, np.ndarray]:
    """Signed distances (mm, + outside the part) from each true surface of a scan (``ball``,
    ``gauge top``, ``gauge plate``, ``plate``) of the ``points`` (base frame) within
    ``near_mm`` of it: a surface's points in the median sit on it when nothing is biased."""
    out = {}
    if "center_base" in truth_scan and "diameter" in truth_scan:
        r = np.linalg.norm(points - np.asarray(truth_scan["center_base"], dtype=np.float64), axis=1)
        out["ball"] = r - float(truth_scan["diameter"]) / 2
    up = np.array([0.0, 0.0, 1.0])  # the faces look up (the base frame's z): + above them
    for key, surface in (("top_plane_base", "gauge top"), ("plate_plane_base", "gauge plate"),
                         ("plane_base", "plate")):
        if key in truth_scan:
            n, d = _plane4(truth_scan[key], up)
            out[surface] = points @ n + d
    return {k: v[np.abs(v) < near_mm] for k, v in out.items()}


def _gauge_truth(g: Any, P: np.ndarray, tscan: dict, nominal: float) -> dict[str, Any]:
    from crossline.report import metrics as mt

    t: dict[str, Any] = {"true_height_mm": float(tscan.get("height", nominal))}
    f = g.figures()
    t["mean_error_mm"] = f["mean_mm"] - t["true_height_mm"]
    t["central_length_error_mm"] = f["central_length_mm"] - t["true_height_mm"]
    if "plate_plane_base" in tscan:
        nt, dt = _plane4(tscan["plate_plane_base"], g.plate_normal)
        h = P[g.top_mask] @ nt + dt
        t["heights_over_true_plate"] = {"mean_mm": float(h.mean()),
                                        "std_mm": float(h.std(ddof=1)) if h.size > 1 else 0.0,
                                        "error_mm": float(h.mean()) - t["true_height_mm"]}
        dev = P[g.plate_mask] @ nt + dt
        t["plate_points_to_true_plate"] = mt.deviation_stats(dev)
        t["plate_normal_angle_deg"] = float(np.degrees(mt.angle_between(nt, g.plate_normal)))
    if "top_plane_base" in tscan:
        nt, dt = _plane4(tscan["top_plane_base"], g.plate_normal)
        t["top_points_to_true_top"] = mt.deviation_stats(P[g.top_mask] @ nt + dt)
    return t


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (float64) and triangles of a PLY mesh.

    Binary little-endian PLYs with ``double``/``float`` x, y, z and ``list uchar int``
    triangles (as the simulator writes them) are read exactly here; anything else through
    Open3D.
    """
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    head = data[:end].decode("ascii", "replace").splitlines() if end > 0 else []
    if "format binary_little_endian 1.0" in head:
        nv = nf = 0
        vprops: list[tuple[str, str]] = []
        flist = None
        element = None
        types = {"double": "<f8", "float": "<f4", "float64": "<f8", "float32": "<f4",
                 "uchar": "u1", "uint8": "u1", "int": "<i4", "int32": "<i4", "uint": "<u4",
                 "uint32": "<u4"}
        ok = True
        for ln in head:
            w = ln.split()
            if w[:1] == ["element"]:
                element = w[1]
                if element == "vertex":
                    nv = int(w[2])
                elif element == "face":
                    nf = int(w[2])
                else:
                    ok = False
            elif w[:1] == ["property"] and element == "vertex":
                ok &= w[1] in types
                vprops.append((w[-1], types.get(w[1], "u1")))
            elif w[:2] == ["property", "list"] and element == "face":
                flist = (types.get(w[2]), types.get(w[3]))
        if ok and flist is not None and None not in flist and {"x", "y", "z"} <= {n for n, _ in vprops}:
            off = end + len(b"end_header\n")
            vt = np.dtype(vprops)
            V = np.frombuffer(data, vt, nv, off)
            ft = np.dtype([("n", flist[0]), ("i", flist[1], (3,))])
            F = np.frombuffer(data, ft, nf, off + nv * vt.itemsize)
            if (F["n"] == 3).all():
                return (np.column_stack([V[k].astype(np.float64) for k in "xyz"]),
                        F["i"].astype(np.int64))
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).copy()


def _mesh_deviation(P: np.ndarray, path: Path, files: list,
                    towards: np.ndarray | None = None) -> np.ndarray | None:
    """Signed distance of the points to the true mesh, positive outside (towards the scanner)."""
    from crossline.report.metrics import mesh_signed_distance

    if not path.is_file():
        log.warning("%s: the true mesh is missing; no freeform validation", path)
        return None
    files.append(("capture", str(path.name if path.parent.name != "truth" else
                                 f"truth/{path.name}"), path))
    V, F = read_mesh(path)
    if len(F) == 0:
        log.warning("%s: the true mesh has no triangles", path)
        return None
    dev = mesh_signed_distance(P, V, F)
    if towards is not None:
        # the scanner sees the outside: if the triangles' area-weighted normal points away
        # from it, the mesh is wound inwards and the sign is flipped
        a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        if float(np.cross(b - a, c - a).sum(0) @ towards) < 0:
            dev = -dev
    return dev

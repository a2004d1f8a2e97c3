"""From labelled stripe centres to 3-D points: pixels -> camera frame (eq. 8) -> arm base.

Each centre ``(u, v)`` (full-sensor px) is undistorted with the calibrated camera, its ray
through the camera centre is intersected with the plane of the centre's laser
(``Z = -D / (n . r)``, the paper's eq. 8 for any ray) and the point is carried to the base
frame with its frame's arm pose: ``p_base = T_base_tool(frame) @ T_tool_cam @ p_cam``.

:func:`run_triangulate` streams the stripes file row group by row group (a row group is a
fixed slice of frames), labels the centres (:mod:`crossline.scan.labels`), triangulates and
writes ``points/<scan>.parquet`` with the counts of the labelling in its metadata and in a
sidecar ``points/<scan>.json``: memory does not grow with the scan's length.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from crossline.camera import Camera
from crossline.errors import StageError
from crossline.geometry import transform_points
from crossline.io.atomic import atomic_path, write_json
from crossline.io.values import rigid_transform
from crossline.laser import LaserPlanes
from crossline.scan.centreline import (
    blocked_ends,
    image_space,
    link_traces,
    smooth_along,
    trace_position,
    trace_space,
)
from crossline.scan.cross_order import CrossOrder
from crossline.scan.frames import keep_freed_memory
from crossline.scan.labels import Disambiguator, check_pattern, reference_gap
from crossline.scan.sheet_curvature import (
    CellSums,
)
from crossline.scan.stripes import MERGED, STRIPES_SCHEMA, read_stripes_meta

log = logging.getLogger(__name__)

__all__ = ["POINTS_SCHEMA", "load_handeye", "run_triangulate", "to_base", "triangulate"]

POINTS_SCHEMA = pa.schema(
    [
        ("frame", pa.int64()),
        ("laser", pa.string()),
        ("lasers", pa.string()),
        ("u", pa.float64()),
        ("v", pa.float64()),
        ("x_cam", pa.float64()),
        ("y_cam", pa.float64()),
        ("z_cam", pa.float64()),
        ("x", pa.float64()),
        ("y", pa.float64()),
        ("z", pa.float64()),
        ("strength", pa.float32()),
        ("width", pa.float32()),
        ("ridge", pa.float32()),
        ("flags", pa.uint8()),
        ("ref_dist", pa.float32()),
        ("width_n", pa.float32()),  # the profile's width across the stripe, px (the extractor's)
        ("axis", pa.uint8()),  # 0: the centre's profile ran along its column, 1: along its row
    ]
)
_META_KEY = b"crossline"
_LASER_NAMES = pa.array(["A", "B"], pa.string())  # a labelled point's laser, by code 0 / 1
MIN_TRACE_COLUMNS = 3  # shorter traces are dropped with the trimmed stripe ends
# the stripes file's columns triangulate reads (of STRIPES_SCHEMA's types)
_STRIPE_COLUMNS = ("frame", "lasers", "u", "v", "strength", "width", "width_n", "ridge", "flags", "axis")


def triangulate(
    camera: Camera, planes: LaserPlanes, uv: np.ndarray, laser: np.ndarray
) -> np.ndarray:
    """Camera-frame points (N, 3) of centres (N, 2) px lit by ``laser`` (N,) of 'A'/'B' (eq. 8)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    laser = np.asarray(laser)
    out = np.full((uv.shape[0], 3), np.nan)
    r = camera.rays(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    for name in ("A", "B"):
        m = laser == name
        if m.any():
            out[m] = planes[name].intersect_rays(r[m])
    return out


def to_base(points_cam: np.ndarray, T_base_tool: np.ndarray, T_tool_cam: np.ndarray,
            index: np.ndarray | None = None) -> np.ndarray:
    """Base-frame points (N, 3) from camera-frame points (N, 3) and T_base_tool (4, 4) or (N, 4, 4).

    With ``index`` (N,), ``T_base_tool`` is one pose per frame (F, 4, 4) and point i takes
    pose ``index[i]``.
    """
    return transform_points(np.asarray(T_base_tool, dtype=np.float64) @ T_tool_cam, points_cam, index)


def load_handeye(path: str | Path) -> np.ndarray:
    """``T_tool_cam`` (4x4, rigid) from handeye.json; StageError naming the file otherwise."""
    path = Path(path)
    try:
        return rigid_transform(json.loads(path.read_text()), "T_tool_cam")
    except ValueError as exc:
        raise StageError(f"{path}: not a hand-eye file: {exc}") from exc


def _load_calibration(camera_json, lasers_json) -> tuple[Camera, LaserPlanes]:
    """The camera and the laser planes; their readers' errors name the file and the key."""
    return Camera.load(camera_json), LaserPlanes.load(lasers_json)


def _check_stripe_columns(path: str | Path, schema: pa.Schema) -> None:
    """Raise :class:`StageError` naming ``path`` unless it has the columns triangulate reads,
    each of the type the stripe extractor writes (:data:`crossline.scan.stripes.STRIPES_SCHEMA`)."""
    wrong = []
    for name in _STRIPE_COLUMNS:
        want = STRIPES_SCHEMA.field(name).type
        i = schema.get_field_index(name)
        if i < 0:
            wrong.append(f"no column '{name}'")
        elif schema.field(i).type != want:
            wrong.append(f"column '{name}' is {schema.field(i).type}")
    if wrong:
        expected = ", ".join(f"{n} ({STRIPES_SCHEMA.field(n).type})" for n in _STRIPE_COLUMNS)
        raise StageError(f"{path}: not a stripes file of the extractor: {'; '.join(wrong)} "
                         f"(expected the columns {expected})")


def _check_stripe_rows(path: str | Path, frame: np.ndarray, u: np.ndarray, v: np.ndarray) -> None:
    """Raise :class:`StageError` naming ``path`` where a row group's centres are not finite or
    its rows are out of frame order (the extractor writes neither)."""
    bad = ~(np.isfinite(u) & np.isfinite(v))
    if bad.any():
        i = int(np.argmax(bad))
        raise StageError(f"{path}: {int(bad.sum())} stripe centre(s) with a non-finite 'u' or 'v' "
                         f"(first: frame {frame[i]}, u = {u[i]}, v = {v[i]}); the stripe extractor "
                         f"writes finite centres only: extract the scan's stripes again")
    back = np.flatnonzero(np.diff(frame) < 0)
    if len(back):
        i = int(back[0])
        raise StageError(f"{path}: rows out of frame order (frame {frame[i + 1]} after frame "
                         f"{frame[i]}); a stripes file lists its frames in increasing order")


def _check_lasers(states: np.ndarray, scan: str, rig_lasers: tuple[str, ...], planes: Any,
                  lasers_json: str | Path) -> None:
    """Raise :class:`StageError` if a frame lights a laser the rig or lasers.json lacks."""
    used = sorted({x for s in set(map(str, states)) if s != "off" for x in ("A", "B") if x in s})
    foreign = [x for x in used if x not in rig_lasers]
    if foreign:
        raise StageError(f"scan {scan}: frames.csv has frames lit by laser {', '.join(foreign)}, "
                         f"but rig.yaml names the lasers {list(rig_lasers)}")
    missing = []
    for x in used:
        try:
            planes[x]
        except (KeyError, AttributeError):
            missing.append(x)
    if missing:
        raise StageError(f"{lasers_json}: has no plane for laser {', '.join(missing)}, which "
                         f"scan {scan} uses")


def _only_lasers(counts: dict[str, Any], lasers: tuple[str, ...]) -> dict[str, Any]:
    """The labelling counts without the entries of lasers (and laser states) the rig lacks."""
    keep = {*lasers, "off", *(("AB",) if len(lasers) > 1 else ())}
    out: dict[str, Any] = {}
    for k, v in counts.items():
        if isinstance(v, dict) and set(v) <= {"A", "B", "AB", "off"}:
            out[k] = {s: n for s, n in v.items() if s in keep}
        elif k in ("labelled_in_AB", "AB_frames_without_reference") and "AB" not in keep:
            continue
        else:
            out[k] = v
    return {k: v for k, v in out.items()
            if not (k in ("labelled_in_AB", "AB_frames_without_reference") and "AB" not in keep)}


def run_triangulate(
    capture: str | Path,
    scan: str,
    stripes: str | Path,
    camera_json: str | Path,
    lasers_json: str | Path,
    handeye_json: str | Path,
    out: str | Path,
    *,
    threshold_px: float = 10.0,
    max_frame_gap: int | None = None,
    ambiguity_px: float = 3.0,
    predict: bool = True,
    end_trim_px: float = 8.0,
    smooth_px: int = 1,
    bridge_columns: int = 8,
    track_references: bool = True,
    sheet_curvature: bool = True,
    stats: str | Path | None = None,
) -> dict[str, Any]:
    """Label, triangulate and write the points of one scan; return the counts.

    Writes ``out`` (parquet, counts in its metadata under ``crossline``) and the same counts
    as JSON to ``stats`` (default: ``out`` with the suffix ``.json``). Centres within
    ``end_trim_px`` pixels (along the stripe) of the end of their trace are dropped; ``smooth_px`` > 1 smooths
    the centre line along each trace over that many columns (:mod:`crossline.scan.centreline`).
    Up to ``bridge_columns`` columns missing in a reference stripe between two of its centres
    are interpolated before AB centres are matched (:func:`crossline.scan.labels.bridge_gaps`);
    with ``track_references`` an AB frame's labelled stripes are the references of the next.
    With ``sheet_curvature`` each centre is moved by the bias that the sheet's thickness
    gives it on a curved surface (:mod:`crossline.scan.sheet_curvature`; a second pass over
    the written points). ``max_frame_gap=None`` allows one frame more than the scan's own laser pattern needs
    (:func:`crossline.scan.labels.reference_gap`): 3 for the paper's A, B, AB. ``smooth_px``
    defaults to 1 (every column on its own, as the paper); the workflow's config smooths
    over 5.
    """
    from crossline.io.capture import laser_pattern, open_capture

    t0 = time.perf_counter()
    cap = open_capture(capture)
    if scan not in cap.scans:
        raise StageError(f"capture {cap.root}: no scan {scan!r} (known: {sorted(cap.scans)})")
    sc = cap.scans[scan]
    rig_lasers = tuple(getattr(cap.rig, "lasers", ("A", "B")))
    cam, planes = _load_calibration(camera_json, lasers_json)
    _check_lasers(sc.lasers, scan, rig_lasers, planes, lasers_json)
    order = None
    states = set(map(str, sc.lasers))
    if planes.B is not None and "AB" in states and not {"A", "B"} <= states:
        try:  # AB frames without A or B frames to go by: the order of the cross tells
            order = CrossOrder.from_calibration(cam, planes)
        except ValueError as exc:
            log.warning("scan %s: AB frames without single-laser frames cannot be labelled (%s)",
                        scan, exc)
    if order is None:
        check_pattern(sc.lasers, scan)
    T_tool_cam = load_handeye(handeye_json)
    T_base_cam = sc.T_base_tool @ T_tool_cam  # each frame's camera pose, once for the scan
    try:
        smeta = read_stripes_meta(stripes)
    except OSError as exc:
        raise StageError(f"{stripes}: cannot read the stripes file ({exc.strerror or exc})") from exc
    except (pa.ArrowException, ValueError) as exc:  # not a parquet file at all
        raise StageError(f"{stripes}: not a stripes file ({exc})") from exc
    if not isinstance(smeta, dict):
        raise StageError(f"{stripes}: not a stripes file (its crossline metadata is not a JSON object)")
    if smeta.get("scan") != scan or smeta.get("frame_range") != [0, len(sc.frames)]:
        raise StageError(f"{stripes}: holds scan {smeta.get('scan')!r} frames {smeta.get('frame_range')}, "
                         f"expected all {len(sc.frames)} frames of scan {scan!r}")
    keep_freed_memory()  # each frame's (and row group's) arrays reuse the last one's pages
    pos_of = {int(f): i for i, f in enumerate(sc.frames)}
    by_number = np.argsort(sc.frames, kind="stable")
    sorted_frames = sc.frames[by_number]
    pat = laser_pattern(sc.lasers)
    if max_frame_gap is None:  # one dropped or repeated frame is tolerated
        max_frame_gap = reference_gap(pat["period"]) + 1
    dis = Disambiguator(threshold_px, max_frame_gap, ambiguity_px, predict, bridge_columns,
                        track_references, order)
    pf = pq.ParquetFile(stripes)
    _check_stripe_columns(stripes, pf.schema_arrow)
    next_pos = 0  # frames before this scan position have been given to the disambiguator
    n_points = 0
    trimmed = {"stripe_end": 0, "smoothing_window": 0}
    out = Path(out)

    def feed_until(pos: int) -> None:
        nonlocal next_pos
        empty = np.empty(0)
        while next_pos < pos:  # frames without any centre still move the pattern on
            dis.process(int(sc.frames[next_pos]), str(sc.lasers[next_pos]), empty, empty,
                        np.empty(0, np.uint8))
            next_pos += 1

    cells = CellSums()  # the points per cell of the base frame: the surface's shape
    with atomic_path(out) as tmp:
        # the sheet-curvature correction needs every point's neighbours: a second pass
        # named as atomic_path's own temporaries: a killed run's is cleared by the next one
        first = tmp.with_name(tmp.name.removesuffix(".tmp") + ".pass1.tmp") if sheet_curvature else tmp
        try:
            with pq.ParquetWriter(
                first, POINTS_SCHEMA, compression="zstd",
                use_dictionary=["frame", "laser", "lasers", "flags"], write_statistics=["frame"],
            ) as w:
                for g in range(pf.num_row_groups):
                    t = pf.read_row_group(g)
                    frame = t.column("frame").to_numpy()
                    u = t.column("u").to_numpy()
                    v = t.column("v").to_numpy()
                    flags = t.column("flags").to_numpy()
                    _check_stripe_rows(stripes, frame, u, v)
                    axis = t.column("axis").to_numpy()
                    # a steep stripe's centres (profiled along the rows) are followed down the rows
                    tu, tv = trace_space(u, v, axis)
                    try:
                        pos = np.fromiter((pos_of[f] for f in np.unique(frame).tolist()), np.int64)
                    except KeyError as exc:
                        raise StageError(f"{stripes}: frame {exc} is not a frame of scan {scan!r}") from exc
                    ufr = np.unique(frame)
                    starts = np.searchsorted(frame, ufr, side="left")
                    ends = np.searchsorted(frame, ufr, side="right")
                    label = np.full(frame.size, "", dtype="<U2")
                    dist = np.full(frame.size, np.nan)
                    for f, p, a, b in zip(ufr.tolist(), pos.tolist(), starts, ends, strict=True):
                        if p < next_pos:
                            raise StageError(f"{stripes}: frames out of order at frame {f}")
                        feed_until(p)
                        lab, dd = dis.process(f, str(sc.lasers[p]), tu[a:b], tv[a:b], flags[a:b],
                                              image=(u[a:b], v[a:b]))
                        label[a:b] = lab
                        dist[a:b] = dd
                        next_pos = p + 1
                    keep = label != ""
                    if not keep.any():
                        continue
                    idx = np.flatnonzero(keep)
                    prev = link_traces(frame[idx], label[idx], tu[idx], tv[idx])
                    trace, from_start, to_end = trace_position(prev, tu[idx], tv[idx])
                    # a trace that stops at the crossing of A and B (a merged run next to its end) has
                    # not reached the end of its stripe: that end is not trimmed
                    blob = np.flatnonzero((flags & MERGED) != 0)
                    start_open, end_open = blocked_ends(trace, frame[idx], tu[idx], tv[idx], frame[blob],
                                                        tu[blob], tv[blob])
                    from_start = np.where(start_open, np.inf, from_start)
                    to_end = np.where(end_open, np.inf, to_end)
                    inner = np.minimum(from_start, to_end) >= end_trim_px
                    # a trace of a few columns is no stripe, whatever stops it (a glint, a stray centre)
                    inner &= np.bincount(trace, minlength=trace.size)[trace] >= MIN_TRACE_COLUMNS
                    row_used, whole = smooth_along(trace, tu[idx], tv[idx], smooth_px)
                    trimmed["stripe_end"] += int((~inner).sum())
                    trimmed["smoothing_window"] += int((inner & ~whole).sum())
                    row_used, idx = row_used[inner & whole], idx[inner & whole]
                    if idx.size == 0:
                        continue
                    u_used, v_used = image_space(u[idx], v[idx], axis[idx], row_used)
                    uv = np.stack([u_used, v_used], axis=1)
                    lab = label[idx]
                    p_cam = triangulate(cam, planes, uv, lab)
                    # the scan position of each point
                    fpos = by_number[np.searchsorted(sorted_frames, frame[idx])]
                    p_base = transform_points(T_base_cam, p_cam, fpos)
                    sel = t.take(pa.array(idx))
                    cols = {
                        "frame": sel.column("frame"),
                        "laser": _LASER_NAMES.take(pa.array((lab == "B").astype(np.int8))),
                        "lasers": sel.column("lasers"),
                        "u": pa.array(u_used),
                        "v": pa.array(v_used),
                        "x_cam": pa.array(p_cam[:, 0]), "y_cam": pa.array(p_cam[:, 1]),
                        "z_cam": pa.array(p_cam[:, 2]),
                        "x": pa.array(p_base[:, 0]), "y": pa.array(p_base[:, 1]), "z": pa.array(p_base[:, 2]),
                        "strength": sel.column("strength"),
                        "width": sel.column("width"),
                        "ridge": sel.column("ridge"),
                        "flags": sel.column("flags"),
                        "ref_dist": pa.array(dist[idx].astype(np.float32)),
                        "width_n": sel.column("width_n"),
                        "axis": sel.column("axis"),
                    }
                    if sheet_curvature:
                        cells.add(p_base)
                    tbl = pa.table(cols, schema=POINTS_SCHEMA)
                    w.write_table(tbl, row_group_size=tbl.num_rows)
                    n_points += tbl.num_rows
                feed_until(len(sc.frames))
                counts = dict(dis.counts)
                counts["trimmed"] = dict(trimmed)  # labelled, then dropped: stripe ends and short traces
                meta = {
                    "scan": scan,
                    "extractor": smeta.get("extractor"),
                    "params": {"threshold_px": threshold_px, "max_frame_gap": max_frame_gap,
                               "ambiguity_px": ambiguity_px, "predict": bool(predict),
                               "end_trim_px": end_trim_px, "smooth_px": smooth_px,
                               "bridge_columns": bridge_columns, "track_references": bool(track_references)},
                    "points": n_points,
                    "frames": len(sc.frames),
                    "points_per_frame": n_points / max(len(sc.frames), 1),
                    "pattern": pat["period"],
                    "pattern_breaks": len(pat["breaks"]),
                    "counts": counts,
                    "stripes_counts": smeta.get("counts", {}),
                }
                if rig_lasers != ("A", "B"):  # the two-laser rig's files stay as they were
                    meta["lasers"] = list(rig_lasers)
                    meta["labelling"] = ("one-line rig: every centre is laser A's (no disambiguation)"
                                         if rig_lasers == ("A",) else "")
                    meta["counts"] = _only_lasers(meta["counts"], rig_lasers)
                if n_points == 0:  # raised inside the block: no file is left behind
                    raise StageError(f"scan {scan}: no stripe centre could be labelled A or B in {stripes} "
                                     f"(counts: {json.dumps(counts)})")
                w.add_key_value_metadata({_META_KEY: json.dumps(meta, sort_keys=True)})
            if sheet_curvature:
                # imported here: the correction triangulates again with this module's triangulate
                from crossline.scan.sheet_correction import correct_points_file

                meta["sheet_curvature"] = correct_points_file(
                    first, tmp, cam, planes, T_base_cam, by_number, sorted_frames, smeta,
                    cells,
                    lambda m: {_META_KEY: json.dumps(m, sort_keys=True)}, meta)
        finally:
            if first != tmp:
                first.unlink(missing_ok=True)
    write_json(Path(stats) if stats is not None else out.with_suffix(".json"), meta)
    log.info("scan %s: %d points from %d centres in %.2f s", scan, n_points, counts["centres_in"],
             time.perf_counter() - t0)
    return meta


def read_points_meta(path: str | Path) -> dict[str, Any]:
    """The parameters and counts stored in a points parquet's metadata."""
    md = pq.ParquetFile(path).metadata.metadata or {}
    if _META_KEY not in md:
        raise StageError(f"{path}: not a points file (no crossline metadata)")
    meta = json.loads(md[_META_KEY])
    if not isinstance(meta, dict):
        raise StageError(f"{path}: not a points file (its crossline metadata is not a JSON object)")
    return meta

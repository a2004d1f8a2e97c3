"""Stripe centres of laser frames: the paper's grey-centre (eq. 9-13), a speckle-aware Gaussian
fit, and Steger's detector.

All three work column by column, as the paper does: every image column ``u`` may hold
several stripe *segments* (an AB frame of the cross has two), each found as a run of pixels
above the threshold, and each gives one centre ``v`` (sub-pixel row). Pixel coordinates
inside the extractors are frame-local; :func:`run_extract_stripes` adds the scan window's
offset so that every stored centre is in full-sensor pixels.

Grey-centre (:func:`grey_centre`). Eq. 9 weights rows by intensity over the stripe region
``S``. Here ``S`` is the run above the threshold extended by ``pad`` pixels on each side (so
the stripe's tails are inside: a window cut at the threshold biases asymmetric stripes), and
the weights are the intensity minus the local background (the lower of the two means of the
two pixels just outside the window, so a neighbouring stripe on one side does not inflate
it). Nothing is anchored on the brightest pixel, so saturated (flat-topped) stripes are
centred on their middle. Two segments in one column never share pixels: each window stops
at the midpoint of the gap to its neighbour (flag ``CLOSE``). A run much wider than the
frame's typical stripe, or wider than ``max_width``, is two stripes merged (near the
crossing of A and B): it is flagged ``MERGED``, never split or averaged silently.

Gaussian fit (:func:`gaussian`). Laser speckle, not the sensor, limits a stripe centre: it
multiplies the stripe by a random field of contrast 0.1-0.3 (Dorsch, Häusler & Herrmann,
Appl. Opt. 33, 1994), while the sensor adds noise of a fraction of a DN. Under that noise the
intensity centroid is far from efficient (it leans on the bright core, whose errors are
largest). The fit models the profile as ``a exp(-(v - c)^2 / 2 s^2)`` over the run widened by
``pad`` px or half the run's length, whichever is more (a steep stripe's long run has long
tails along the column), never past the gap's midpoint to a neighbouring run less the
background pixels, on a background line fitted beyond both ends, and weights each pixel by the
inverse of its variance ``r^2 yhat^2 + sigma_n^2`` (relative noise ``r``, sensor noise
``sigma_n``), which is maximum likelihood for that noise; clipped pixels carry no weight.
Both noise levels are measured in the frame: ``sigma_n`` from the residuals of the
background lines, ``r`` from the relative residuals of the bright pixels of a first fit.
On the virtual rigs it finds the speckle contrast they render (0.15, 0.20) and stays within
5 % of the Cramér-Rao bound of the centre (``tests/test_stripes.py``). A column cuts a steep
stripe obliquely, and where the stripe is curved (a ball, a cylinder, the edge of a part) the
profile along the column is skewed towards the centre of curvature, and its fitted centre with
it: by about ``2.5 sigma_col^2 s^2 v'' / (1 + s^2)^2`` rows for slope ``s`` and curvature
``v''`` (0.3 px normal to the line on a ring of 100 px radius at slopes 1.5-3, tested), which
makes a ball small. So stripes steeper than ``ACROSS_SLOPE`` are fitted again *across* the
stripe (``across=True``): the profile is sampled bilinearly along the normal (each sample the
mean over the stripe length one column holds, so it sees the column's pixels), fitted with
the same weighted Gaussian, and the ridge carried along the line back to the column
(``v = c + t / n_y``, as Steger does).

Steger (:func:`steger`). Gaussian smoothing (``sigma``), Hessian by central differences of
the smoothed image at the candidate pixels only (the runs above the threshold: the band
around the stripes), the normal ``n`` as the eigenvector of the most negative eigenvalue,
and the sub-pixel ridge along ``n`` by one Newton step; the ridge point is carried along
the line to the pixel's column (``v = r + t / n_y``), and the pixel whose column crossing
lies inside it is the one kept. Each centre carries its normal, ridge strength
(``-lambda``) and a width from the Gaussian line model.

Columns of a centre table (dict of arrays, one entry per centre): ``u, v`` (px), ``strength``
(background-subtracted summed intensity, counts; Steger: smoothed intensity at the ridge),
``peak`` (brightest pixel, counts), ``width`` (run length above threshold along the column,
px), ``width_n`` (width across the stripe, px: grey-centre ``width * |n_y|``, Steger the
FWHM of the Gaussian model), ``nx, ny`` (unit normal, ``ny >= 0``), ``ridge`` (Steger's
ridge strength, NaN for grey-centre) and ``flags`` (bits ``MERGED``, ``CLOSE``, ``SATURATED``,
``EDGE``).

Modules (issue 21.3): this one is the stage, ``extract-stripes`` and ``gather-stripes`` (frames
streamed to a parquet file, chunks, the per-frame metadata), and re-exports the names its
importers use. The extractors live beside it: ``stripe_levels`` (a frame's levels and
threshold), ``stripe_runs`` (runs above the threshold, slopes, the centre table),
``stripe_kernels`` (compiled window kernels and the flag bits), ``stripe_grey``,
``stripe_gaussian`` and ``stripe_steger`` (the three extractors), ``stripe_frame`` (any angle,
local background, :func:`extract`) and ``stripe_channel`` (colour channel, data range).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from crossline.errors import CrosslineError, StageError
from crossline.io.atomic import atomic_path
from crossline.scan.frames import keep_freed_memory, map_frames
from crossline.scan.off_frames import OFF_MODES, OffFrames, read_order
from crossline.scan.stripe_channel import _data_range, scan_channel
from crossline.scan.stripe_dim import centre_heights, with_dim_stripes
from crossline.scan.stripe_frame import EXTRACTORS, _rows_of, any_angle, extract, with_local_background
from crossline.scan.stripe_gaussian import gaussian
from crossline.scan.stripe_grey import grey_centre
from crossline.scan.stripe_kernels import CLOSE, EDGE, FLAG_NAMES, MERGED, SATURATED
from crossline.scan.stripe_levels import (
    NOISE_K,
    frame_levels,
    full_scale,
    stripe_peaks,
)
from crossline.scan.stripe_runs import COLUMNS, empty_centres
from crossline.scan.stripe_steger import steger

__all__ = [
    "CLOSE",
    "COLUMNS",
    "EDGE",
    "EXTRACTORS",
    "FLAG_NAMES",
    "FRAMES_PER_GROUP",
    "MERGED",
    "SATURATED",
    "STRIPES_SCHEMA",
    "empty_centres",
    "extract",
    "frame_levels",
    "full_scale",
    "gather_stripes",
    "gaussian",
    "grey_centre",
    "read_stripes_meta",
    "run_extract_stripes",
    "scan_channel",
    "steger",
]

log = logging.getLogger(__name__)


FRAMES_PER_GROUP = 64  # parquet row group = frames [64k, 64k + 64) of the scan
_F32 = ("strength", "peak", "width", "width_n", "nx", "ny", "ridge")
STRIPES_SCHEMA = pa.schema(
    [
        ("frame", pa.int64()),
        ("lasers", pa.string()),
        ("u", pa.float64()),
        ("v", pa.float64()),
        *[(c, pa.float32()) for c in _F32],
        ("flags", pa.uint8()),
        ("axis", pa.uint8()),
    ]
)
_META_KEY = b"crossline"


def _table(frame: int, state: str, c: dict[str, np.ndarray], du: float, dv: float) -> pa.Table:
    n = c["u"].size
    cols = {
        "frame": pa.array(np.full(n, frame, np.int64)),
        "lasers": pa.repeat(pa.scalar(state, pa.string()), n),
        "u": pa.array(c["u"].astype(np.float64) + du),
        "v": pa.array(c["v"].astype(np.float64) + dv),
    }
    for name in _F32:
        cols[name] = pa.array(c[name].astype(np.float32))
    cols["flags"] = pa.array(c["flags"].astype(np.uint8))
    cols["axis"] = pa.array(c["axis"].astype(np.uint8) if "axis" in c else np.zeros(n, np.uint8))
    return pa.table(cols, schema=STRIPES_SCHEMA)


def _chunk_bounds(n_frames: int, chunk: tuple[int, int]) -> tuple[int, int]:
    i, n = chunk
    if n < 1 or not 0 <= i < n:
        raise StageError(f"chunk must be (i, n) with 0 <= i < n, got {chunk}")
    return i * n_frames // n, (i + 1) * n_frames // n


class _GroupedWriter:
    """Parquet writer whose row groups hold the frames ``[64k, 64k + 64)`` of a scan.

    The same rows give the same file whether they come from one run or from gathered
    chunks: a row group is a maximal run of rows whose ``frame // FRAMES_PER_GROUP`` is
    equal, whichever process wrote them.
    """

    def __init__(self, path: Path):
        # dictionary encoding only where values repeat: on float columns it costs 3x the time
        self.writer = pq.ParquetWriter(path, STRIPES_SCHEMA, compression="zstd",
                                       use_dictionary=["frame", "lasers", "flags"],
                                       write_statistics=["frame"])
        self.buf: list[pa.Table] = []
        self.group: int | None = None
        self.rows = 0

    def add(self, table: pa.Table) -> None:
        if table.num_rows == 0:
            return
        g = int(table.column("frame")[0].as_py()) // FRAMES_PER_GROUP
        if self.group is not None and g != self.group:
            self.flush()
        self.group = g
        self.buf.append(table)

    def flush(self) -> None:
        if self.buf:
            t = pa.concat_tables(self.buf).combine_chunks()
            self.writer.write_table(t, row_group_size=t.num_rows)
            self.rows += t.num_rows
        self.buf = []

    def close(self, meta: dict[str, Any]) -> None:
        self.flush()
        self.writer.add_key_value_metadata({_META_KEY: json.dumps(meta, sort_keys=True)})
        self.writer.close()


def _frame_work(extractor: str, params: dict[str, Any], data_max: float):
    """The per-frame function of the stage; it takes frames transposed, (width, height), and
    how many lasers the frame has on (a dim stripe beside a brighter one is looked for where
    that is more than one: :func:`crossline.scan.stripe_dim.with_dim_stripes`)."""
    kw = {"threshold": params["threshold"], "min_width": params["min_width"],
          "max_width": params["max_width"], "data_max": data_max}
    thr, mw = params["threshold"], params["max_width"]

    def work(i: int, imT: np.ndarray, lasers_on: int = 1) -> dict[str, Any]:
        lv = frame_levels(imT, thr, data_max)
        info: dict[str, Any] = {"levels": lv}

        def fn_at(level: float, record: bool):
            first = [record]

            def fn(a: np.ndarray, d: np.ndarray | None = None) -> dict[str, np.ndarray]:
                if extractor == "gaussian":
                    c, inf = gaussian(a, pad=params["fit_pad"], relative_noise=params["relative_noise"],
                                      across=params["fit_across"], return_info=True, transposed=True,
                                      level=level, detect=d, **kw)
                    if first[0]:  # the column pass's (not the rows'): the frame's noise
                        info["fit"], first[0] = inf, False
                    return c
                if extractor == "grey_centre":
                    return grey_centre(a, pad=params["pad"], transposed=True, level=level, detect=d, **kw)
                return steger(np.ascontiguousarray(cv2.transpose(a)), sigma=params["sigma"],
                              level=level, detect=_rows_of(d), **kw)  # Steger smooths the image itself
            return fn

        def at(a: np.ndarray, level: float, d: np.ndarray | None, record: bool = True):
            return any_angle(fn_at(level, record), a, level, mw, d)

        c, lv, top = with_local_background(at, imT, lv, thr, mw)
        info["levels"], info["local_background"] = lv, top is not None
        if not (c["u"].size and np.isfinite(lv["peak"])):
            return {**c, "_info": info}
        if lasers_on > 1:
            def again(level: float, fraction: float) -> dict[str, np.ndarray]:
                if top is not None:  # the runs are the background-free image's already
                    return at(imT, level, top, False)
                return with_local_background(lambda a, lev, d: at(a, lev, d, False), imT,
                                             {**lv, "level": level}, thr * fraction, mw)[0]

            n_first = c["u"].size
            c, dim_peak, ref = with_dim_stripes(c, lv, top, thr, again, imT.shape)
            info["dim_stripe_centres"] = c["u"].size - n_first
        else:
            dim_peak, ref = np.full(c["u"].size, np.nan), None
        mp = params.get("min_peak")
        if mp:
            peak = centre_heights(c, top)
            bright = peak >= lv["background"] + mp * (lv["peak"] - lv["background"])
            if not bright.all():  # held to its own stripe's peak (lower, where two differ)
                if ref is None:
                    ref = stripe_peaks(peak, c["nx"], c["ny"], lv["peak"])
                ref = np.where(np.isfinite(dim_peak), np.minimum(ref, dim_peak), ref)
                bright = peak >= lv["background"] + mp * (ref - lv["background"])
            if not bright.all():
                c = {k: x[bright] for k, x in c.items()}
        return {**c, "_info": info}

    return work


def run_extract_stripes(
    capture: str | Path,
    scan: str,
    out: str | Path,
    *,
    extractor: str = "grey_centre",
    threshold: float = 0.10,
    min_width: float = 2.0,
    max_width: float = 30.0,
    sigma: float = 2.0,
    chunk: tuple[int, int] = (0, 1),
    threads: int = 1,
    pad: int = 2,
    fit_pad: int = 6,
    relative_noise: float | None = None,
    fit_across: bool = True,
    decoder: str = "auto",
    min_peak: float = 0.17,
    off_frames: str = "subtract",
) -> dict[str, Any]:
    """Extract the stripe centres of one scan's frames (or one chunk of them) to parquet.

    Frames are read once and streamed through ``threads`` worker threads; centres are
    stored in full-sensor pixels with the frame's laser state. The parquet's schema
    metadata (key ``crossline``) holds the parameters and counts. Returns that metadata.
    ``extractor`` defaults to the paper's grey centre; the workflow's config uses the
    Gaussian fit. Where the scan has ``off`` frames, ``off_frames="subtract"`` takes the
    room's light they show out of the laser frames between them
    (:mod:`crossline.scan.off_frames`); the off frames' own centres are the raw frame's.
    """
    from crossline.io.capture import open_capture

    if extractor not in EXTRACTORS:
        raise StageError(f"unknown extractor {extractor!r}; expected one of {EXTRACTORS}")
    if off_frames not in OFF_MODES:
        raise StageError(f"unknown off_frames {off_frames!r}; expected one of {OFF_MODES}")
    if not 0 < threshold < 1:
        raise StageError(f"threshold is a fraction of the stripe's peak above the background, "
                         f"in (0, 1), got {threshold}")
    cap = open_capture(capture)
    if scan not in cap.scans:
        raise StageError(f"capture {cap.root}: no scan {scan!r} (known: {sorted(cap.scans)})")
    sc = cap.scans[scan]
    win = cap.rig.scan_window
    lo, hi = _chunk_bounds(len(sc.frames), chunk)
    all_states = np.asarray(sc.lasers).astype(str)
    lasers_on = [0 if s == "off" else len(s) for s in all_states]  # A, B, AB or off
    params = {"threshold": threshold, "min_width": min_width, "max_width": max_width, "min_peak": min_peak,
              "off_frames": off_frames}
    if extractor == "steger":
        params["sigma"] = sigma
    elif extractor == "gaussian":
        params["fit_pad"] = int(fit_pad)
        params["relative_noise"] = None if relative_noise is None else float(relative_noise)
        params["fit_across"] = bool(fit_across)
    else:
        params["pad"] = int(pad)
    meta: dict[str, Any] = {
        "scan": scan, "extractor": extractor, "params": params,
        "scan_window": [win.x, win.y, win.width, win.height],
        "frames_in_scan": len(sc.frames),
    }
    counts = {"frames": 0, "frames_without_stripe": 0, "frames_local_background": 0, "centres": 0,
              "frames_dim_stripe": 0, "centres_dim_stripe": 0,
              **{f"flag_{name}": 0 for name in FLAG_NAMES.values()}}
    room = None
    if off_frames == "subtract" and (all_states == "off").any():
        room = OffFrames(all_states, lo, hi, [str(f) for f in sc.frames], max_width)
        order = read_order(lo, hi, all_states)
        counts["frames_room_light_subtracted"] = counts["frames_room_light_kept"] = 0
    else:
        order = [(i, True) for i in range(lo, hi)]
    keep_freed_memory()  # every frame's arrays reuse the last frame's pages
    t0 = time.perf_counter()
    noise: list[tuple[int, float, float]] = []
    levels: list[tuple[int, float, float, float, float]] = []
    paths = [sc.frame_path(sc.frames[i]) for i, _ in order]
    sensor = cap.rig.sensor
    try:
        scan_paths = [sc.frame_path(f) for f in sc.frames]
        chosen = scan_channel(scan_paths, getattr(sensor, "channel", None), (win.height, win.width))
        channel = chosen["name"]
        rng_ = _data_range([sc.frame_path(f) for f in sc.frames], getattr(sensor, "data_bits", None),
                           (win.height, win.width), decoder, channel)
    except CrosslineError as exc:
        raise StageError(f"scan {scan}: {exc}") from exc
    meta["data_range"] = rng_
    meta["channel"] = chosen
    if chosen["source"].startswith("chosen"):
        log.info("scan %s: colour frames measured on the %s channel (%s)", scan, channel, chosen["source"])
    log.info("scan %s: data range 0..%d (%d bits, %s)", scan, rng_["max"], rng_["bits"], rng_["source"])
    data_max = float(rng_["max"])
    fit = _frame_work(extractor, params, data_max)
    transposed = True

    def work(j: int, img: np.ndarray) -> tuple[int, dict[str, Any], pa.Table, dict[str, int]] | None:
        # the table and the flag counts are made in the worker thread too: the loop below,
        # which the workers wait on, only writes
        i, extract_it = order[j]
        subtracted = None  # None: no off frames used; else whether the room's light was taken out
        if room is not None:
            if all_states[i] == "off":
                room.put(i, img)
            else:
                img, subtracted = room.subtract(i, img, data_max)
        if not extract_it:
            return None
        c = fit(j, img, lasers_on[i])
        flags = {name: int(np.count_nonzero(c["flags"] & bit)) for bit, name in FLAG_NAMES.items()}
        return i, c, _table(int(sc.frames[i]), str(all_states[i]), c, win.x, win.y), flags, subtracted

    def unreadable(j: int, _exc: BaseException) -> None:
        if room is not None:
            room.failed(order[j][0])

    def in_frame_order(results: Iterator) -> Iterator:
        # an off frame is read before the laser frames ahead of it: put them back in order
        held, nxt = {}, lo
        for r in results:
            if r is None:
                continue
            held[r[0]] = r
            while nxt in held:
                yield held.pop(nxt)
                nxt += 1

    with atomic_path(out) as tmp:
        writer = _GroupedWriter(tmp)
        it = map_frames(paths, work, shape=(win.height, win.width), threads=threads, decoder=decoder,
                        transposed=transposed, channel=channel, on_read_error=unreadable)
        try:
            for i, c, table, flags, subtracted in in_frame_order(it):
                counts["frames"] += 1
                if subtracted is not None:
                    counts["frames_room_light_subtracted" if subtracted else "frames_room_light_kept"] += 1
                nc = c["u"].size
                counts["frames_without_stripe"] += nc == 0
                counts["frames_local_background"] += bool(c["_info"]["local_background"])
                dim = int(c["_info"].get("dim_stripe_centres", 0))
                counts["frames_dim_stripe"] += dim > 0
                counts["centres_dim_stripe"] += dim
                counts["centres"] += nc
                for name, k in flags.items():
                    counts[f"flag_{name}"] += k
                info = c["_info"]
                lv = info["levels"]
                levels.append((int(sc.frames[i]), lv["background"], lv["noise"], lv["peak"], lv["level"]))
                if "fit" in info and nc:
                    noise.append((int(sc.frames[i]), info["fit"]["noise_dn"], info["fit"]["relative_noise"]))
                writer.add(table)
        except CrosslineError as exc:
            raise StageError(f"scan {scan}: {exc}") from exc
        if chunk[1] == 1 and counts["centres"] == 0:
            bg = np.median([r[1] for r in levels]) if levels else float("nan")
            nz = np.median([r[2] for r in levels]) if levels else float("nan")
            raise StageError(
                f"scan {scan}: no stripe found in any of its {counts['frames']} frames: no column "
                f"of a frame holds a pixel {NOISE_K:g} noise sigmas above the background "
                f"(background {bg:.1f}, noise {nz:.2f} counts, data range 0..{rng_['max']}); "
                f"are the lasers on, is the exposure right?"
            )
        meta["counts"] = counts
        meta["levels"] = _level_columns(levels)
        if extractor == "gaussian":  # what the fit found in each frame: sensor noise, speckle
            meta["noise"] = _noise_columns(noise)
        meta["chunk"] = list(chunk)
        meta["frame_range"] = [lo, hi]
        writer.close(meta)
    dt = time.perf_counter() - t0
    log.info("scan %s: %d frames, %d centres, %.1f frames/s (%s, %d threads); %d frames had room-lit "
             "surfaces above the threshold and were extracted less their local background; in %d "
             "frames a stripe much dimmer than the other was found again at its own level (%d "
             "centres added)", scan, counts["frames"], counts["centres"], counts["frames"] / max(dt, 1e-9),
             extractor, threads, counts["frames_local_background"], counts["frames_dim_stripe"],
             counts["centres_dim_stripe"])
    if room is not None:
        log.info("scan %s: the room's light of its off frames subtracted from %d laser frames, not "
                 "from %d (it moved between their two off frames, or they have one only); %d off "
                 "frames of neighbouring chunks read for it", scan, counts["frames_room_light_subtracted"],
                 counts["frames_room_light_kept"], sum(not e for _, e in order))
    return meta


def _level_columns(rows: list[tuple[int, float, float, float, float]]) -> dict[str, list]:
    """Per-frame intensity levels (background, noise, stripe peak, threshold) as JSON columns."""
    def r(x: float) -> float | None:
        return round(float(x), 3) if np.isfinite(x) else None

    return {"frame": [x[0] for x in rows], "background": [r(x[1]) for x in rows],
            "noise": [r(x[2]) for x in rows], "peak": [r(x[3]) for x in rows],
            "threshold": [r(x[4]) for x in rows]}


def _noise_columns(rows: list[tuple[int, float, float]]) -> dict[str, list]:
    """Per-frame noise estimates of the gaussian extractor as JSON columns."""
    return {"frame": [r[0] for r in rows],
            "background_noise_dn": [round(float(r[1]), 5) for r in rows],
            "relative_noise": [round(float(r[2]), 5) for r in rows]}


def read_stripes_meta(path: str | Path) -> dict[str, Any]:
    """The parameters and counts stored in a stripes parquet's schema metadata."""
    try:
        md = pq.ParquetFile(path).metadata.metadata or {}
    except Exception as exc:  # pyarrow raises several types for broken files
        raise StageError(f"{path}: cannot be read as parquet ({exc})") from exc
    if _META_KEY not in md:
        raise StageError(f"{path}: not a stripes file (no crossline metadata)")
    try:
        meta = json.loads(md[_META_KEY])
    except ValueError as exc:
        raise StageError(f"{path}: its crossline metadata is not JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise StageError(f"{path}: its crossline metadata is a {type(meta).__name__}, expected an object")
    return meta


def gather_stripes(chunks: Iterable[str | Path], out: str | Path) -> dict[str, Any]:
    """Join chunk files of one scan into the table an unsplit run writes (same bytes)."""
    chunks = [Path(c) for c in chunks]
    if not chunks:
        raise StageError("gather-stripes: no chunk files given")
    metas = [read_stripes_meta(c) for c in chunks]
    for c, m in zip(chunks, metas, strict=True):
        fr, counts = m.get("frame_range"), m.get("counts")
        if not (isinstance(fr, list) and len(fr) == 2 and all(type(x) is int for x in fr)
                and isinstance(counts, dict) and all(type(v) is int for v in counts.values())
                and type(m.get("frames_in_scan")) is int):
            raise StageError(f"{c}: not a stripe chunk of extract-stripes (its metadata lacks whole "
                             "numbers frame_range [start, stop], frames_in_scan and counts)")
    order = sorted(range(len(chunks)), key=lambda k: metas[k]["frame_range"][0])
    chunks = [chunks[k] for k in order]
    metas = [metas[k] for k in order]
    first = metas[0]
    for c, m in zip(chunks, metas, strict=True):
        for key in ("scan", "extractor", "params", "scan_window", "frames_in_scan", "data_range"):
            if m.get(key) != first.get(key):
                raise StageError(f"{c}: {key} {m[key]!r} differs from {chunks[0]}'s {first[key]!r}")
    pos = 0
    for c, m in zip(chunks, metas, strict=True):
        if m["frame_range"][0] != pos:
            raise StageError(f"{c}: covers frames {m['frame_range']}, expected to start at {pos} "
                             f"(a chunk is missing or repeated)")
        pos = m["frame_range"][1]
    if pos != first["frames_in_scan"]:
        raise StageError(f"chunks cover {pos} of the scan's {first['frames_in_scan']} frames")
    counts: dict[str, int] = {}
    for m in metas:
        for k, v in m["counts"].items():
            counts[k] = counts.get(k, 0) + int(v)
    meta = {k: first[k] for k in ("scan", "extractor", "params", "scan_window", "frames_in_scan")}
    meta["counts"] = counts
    for key in ("data_range", "channel"):
        if key in first:
            meta[key] = first[key]
    for key in ("noise", "levels"):
        if key in first:
            meta[key] = {c: [x for m in metas for x in m[key][c]] for c in first[key]}
    meta["chunk"] = [0, 1]
    meta["frame_range"] = [0, pos]
    if counts["centres"] == 0:
        raise StageError(f"scan {first['scan']}: no stripe found in any of its {counts['frames']} frames")
    with atomic_path(out) as tmp:
        writer = _GroupedWriter(tmp)
        for c in chunks:
            pf = pq.ParquetFile(c)
            for g in range(pf.num_row_groups):
                t = pf.read_row_group(g).replace_schema_metadata(None).cast(STRIPES_SCHEMA)
                writer.add(t)
        writer.close(meta)
    return meta

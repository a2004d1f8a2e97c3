"""A scan's data as the report reads it: the points, the fused cloud and the frames.

``ScanData`` holds what the report knows about one scan; ``_load_scan`` fills it from the
capture's ``frames.csv``, the triangulated points (``points/<scan>.parquet`` and its side
file) and the fused cloud (``<scan>.ply``, else, where there is none, the points themselves),
noting every file it read for the provenance; ``points_per_frame`` counts the points of each
frame by laser state; ``_read_json`` reads a JSON input, None when it is missing or broken.
Split from ``crossline.report.accuracy`` (issue 21.3), which re-exports the names its importers
use.

What the report would measure wrong it refuses (StageError naming the files, issue 23.2): a
fused cloud that cannot be read (its figures would be of the unfused points, as if all were
well), and a points file or arm draws of another scan (:func:`_same_scan_points`,
:func:`_same_scan_arm`). What it only counts or draws with, it reads leniently: a points file
or a side file that cannot be read, and arm draws that cannot be read, are named in the log
and their figures left out (the arm draws' under the uncertainty's ``incomplete``).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from crossline.errors import StageError
from crossline.io.columns import frame_counts

__all__ = ["ScanData", "points_per_frame"]

# the report stage's logger, as before the split: its records keep their name
log = logging.getLogger("crossline.report.accuracy")


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable (%s); its section is left out", path, exc)
        return None
    return data if isinstance(data, dict) else None


# what the report reads of the stages' side files (keys absent are fine): a type, or a dict of
# what it reads inside; NUMBER takes None (a non-finite figure as the stages write it)
NUMBER = "number"
POINTS_STATS = {"extractor": str, "params": {"smooth_px": NUMBER},
                "counts": {"labelled_by_order": {"frames": NUMBER, "by_previous_frames": NUMBER,
                                                 "by_order": NUMBER}}}
FUSE_STATS = {**{k: NUMBER for k in ("n_input", "n_outliers", "n_after_outlier_removal", "n_output")},
              "parameters": dict,
              "refine": {"skipped": str, **{k: NUMBER for k in (
                  "crossings", "used", "frames", "frames_with_crossings", "gap_rms_before_mm",
                  "gap_rms_after_mm", "ab_offset_mm", "correction_rms_mm", "correction_max_mm")}}}


def _stats_problem(data: Any, spec: dict, where: str = "") -> str | None:
    """Why ``data`` does not hold what ``spec`` says the report reads, or None."""
    if not isinstance(data, dict):
        return f"{where or 'the file'} is {type(data).__name__}, expected a JSON object"
    for key, want in spec.items():
        if key not in data:
            continue
        v, at = data[key], f"{where}.{key}" if where else key
        if isinstance(want, dict):
            why = _stats_problem(v, want, at)
            if why is not None:
                return why
        elif want == NUMBER:
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float)):
                return f"'{at}' = {v!r:.60} is not a number"
        elif not isinstance(v, want):
            return f"'{at}' = {v!r:.60} is not a JSON {'object' if want is dict else 'text'}"
    return None


def _read_stats(path: Path, spec: dict) -> dict | None:
    """A stage's side file (JSON) as the report reads it, None (with a warning naming the file
    and the key) when it is missing, broken or holds something else where the report reads."""
    data = _read_json(path)
    why = None if data is None else _stats_problem(data, spec)
    if why is not None:
        log.warning("%s: %s; its figures are left out", path, why)
        return None
    return data


@dataclass
class ScanData:
    """What the report knows about one scan (arrays for plots included)."""

    name: str
    artefact: str
    nominal: dict[str, float]
    states: np.ndarray | None = None  # laser state per frame, in frame order
    frame_ids: np.ndarray | None = None
    # the triangulated points' distinct frames and their counts (crossline.io.columns.
    # frame_counts), and their count per laser code (0, 1 = A, 2 = B): no per-point arrays
    point_frames: tuple[np.ndarray, np.ndarray] | None = None
    point_lasers: np.ndarray | None = None
    cloud: dict[str, np.ndarray] | None = None  # points, normals, laser (codes), frame
    cloud_source: str = ""
    fuse_stats: dict | None = None
    points_path: Path | None = None
    points_info: dict | None = None
    mesh: str | None = None  # a freeform's nominal mesh, relative to the capture
    T_base_nominal: np.ndarray | None = None  # its placement as rig.yaml gives it (a datum)
    plots: dict[str, Any] = field(default_factory=dict)
    arm: Any = None  # the fuse stage's ArmDraws (crossline.io.arm_draws), or None
    arm_error: str | None = None  # why there are none


def points_per_frame(
    frame_ids: np.ndarray, states: np.ndarray, point_frames: np.ndarray,
    counts_of: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Points per frame, by laser state, and the gain of the cross-line over a single line.

    The gain is the mean number of points per frame over all frames of the scan (every
    frame costs the same time) divided by the mean per single-laser frame (A or B): the
    paper's 4/3 for the pattern A, B, AB when each stripe gives the same number of points.
    """
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    states = np.asarray(states).astype(str)
    order = np.argsort(frame_ids, kind="stable")
    frame_ids, states = frame_ids[order], states[order]
    # per distinct frame of the points, then onto the table's frames: no per-point temporaries
    # (``counts_of``: :func:`frame_counts` of the points' frames, made when they were read)
    seen, n_seen = counts_of if counts_of is not None else frame_counts(point_frames)
    counts = np.zeros(len(frame_ids), dtype=np.int64)
    known = np.zeros(len(seen), dtype=bool)
    if len(frame_ids) and len(seen):
        pos = np.clip(np.searchsorted(frame_ids, seen), 0, len(frame_ids) - 1)
        known = frame_ids[pos] == seen
        np.add.at(counts, pos[known], n_seen[known])
    by_state = {}
    for s in ("A", "B", "AB", "off"):
        m = states == s
        if m.any():
            by_state[s] = {"frames": int(m.sum()), "points": int(counts[m].sum()),
                           "points_per_frame": float(counts[m].mean())}
    single = (states == "A") | (states == "B")
    n = len(frame_ids)
    out: dict[str, Any] = {
        "frames": n,
        "points": int(counts.sum()),
        "points_outside_frames": int(n_seen[~known].sum()),
        "points_per_frame": float(counts.sum() / n) if n else None,
        "by_state": by_state,
        "points_per_single_laser_frame": float(counts[single].mean()) if single.any() else None,
    }
    ppf, ps = out["points_per_frame"], out["points_per_single_laser_frame"]
    out["gain_over_single_line"] = ppf / ps if ppf is not None and ps else None
    out["_counts"] = counts  # for the plot; removed before JSON
    return out


FLANGE_TOLERANCE_MM = 1e-6  # arm draws' flange origins are frames.csv's positions, copied


def _same_scan_points(name: str, points: Path, frames: Path, n_frames: int | None) -> None:
    """Raise a StageError naming ``points`` and ``frames`` (scan ``name``'s frames.csv, of
    ``n_frames`` rows) where the points file's metadata says it holds another scan's points, or
    the points of a frames table of another length (as fuse refuses them). A file without
    the metadata (of another tool, or broken: its reading says so) has nothing to compare."""
    from crossline.scan.triangulate import read_points_meta

    try:
        meta = read_points_meta(points)
    except Exception:  # pyarrow raises several types for broken files
        return
    scan, n = meta.get("scan"), meta.get("frames")
    if isinstance(scan, str) and scan != name:
        raise StageError(f"{points}: holds the points of scan {scan!r} (its metadata), not of scan "
                         f"{name!r}, whose frames table is {frames}: the points file of another "
                         "scan; triangulate the scan again")
    if isinstance(n, int) and not isinstance(n, bool) and n_frames is not None and n != n_frames:
        raise StageError(f"{frames}: {n_frames} frames, but {points} was triangulated from the {n} "
                         f"frames of scan {scan!r}: not that scan's frames table (or not its points "
                         "file); triangulate the scan again")


def _same_scan_arm(arm_path: Path, arm: Any, frames: Path, cloud: dict | None,
                   cloud_name: str) -> None:
    """Raise a StageError naming ``arm_path`` and the file it disagrees with where the arm
    draws are not the scan's: a frame of the draws that is not a row of ``frames`` (the scan's
    frames.csv), flange origins that are not that table's flange positions (draws centred on the
    flange, as fuse writes them with a frames table), or a frame of the cloud (``cloud_name``)
    without draws."""
    from crossline.io.capture import read_frames_table
    table = read_frames_table(frames)
    order = np.argsort(table.frames, kind="stable")
    ids = table.frames[order]
    k = np.clip(np.searchsorted(ids, arm.frames), 0, max(len(ids) - 1, 0))
    foreign = arm.frames if len(ids) == 0 else arm.frames[ids[k] != arm.frames]
    if len(foreign):
        raise StageError(f"{arm_path}: frame(s) {foreign[:5].tolist()} of its draws ({len(foreign)} "
                         f"of {len(arm.frames)}) are not rows of {frames}: the arm draws of another "
                         "scan (or of an older frames table); fuse the scan again")
    if arm.centre == "flange":
        flange = table.T_base_tool[order][k, :3, 3]
        off = np.linalg.norm(arm.origins - flange, axis=1)
        bad = np.flatnonzero(off > FLANGE_TOLERANCE_MM)
        if len(bad):
            i = bad[0]
            raise StageError(
                f"{arm_path}: the flange positions of its draws are not those of {frames} (frame "
                f"{arm.frames[i]}: {np.round(arm.origins[i], 3).tolist()} mm in the draws, "
                f"{np.round(flange[i], 3).tolist()} mm in the table; {len(bad)} of "
                f"{len(arm.frames)} frames differ, by up to {off.max():.3g} mm): the arm draws of "
                "another scan; fuse the scan again")
    if cloud is not None and "frame" in cloud and len(cloud["frame"]):
        seen, _ = frame_counts(cloud["frame"])
        lacking = np.setdiff1d(seen, arm.frames)
        if len(lacking):
            raise StageError(f"{arm_path}: no draws for frame(s) {lacking[:5].tolist()} of "
                             f"{cloud_name} ({len(lacking)} of its {len(seen)} frames): not the "
                             "arm draws of the fuse that made it; fuse the scan again")


def _load_scan(
    name: str, spec: Any, root: Path, interim: Path, processed: Path, files: list
) -> ScanData:
    import pandas as pd

    from crossline.fuse import read_ply
    from crossline.io.columns import read_columns

    sd = ScanData(name, spec.artefact, dict(spec.nominal), mesh=getattr(spec, "mesh", None),
                  T_base_nominal=getattr(spec, "T_base_nominal", None))
    if sd.mesh and (root / sd.mesh).is_file():
        files.append(("capture", sd.mesh, root / sd.mesh))
    fcsv = root / "scans" / name / "frames.csv"
    if fcsv.is_file():
        files.append(("capture", f"scans/{name}/frames.csv", fcsv))
        try:
            fr = pd.read_csv(fcsv, usecols=["frame", "lasers"], dtype={"lasers": str},
                             keep_default_na=False)
            sd.frame_ids = fr["frame"].to_numpy(np.int64)
            sd.states = fr["lasers"].str.strip().to_numpy(str)
        except (ValueError, KeyError) as exc:
            log.warning("%s: unreadable (%s)", fcsv, exc)
    pq = interim / "points" / f"{name}.parquet"
    if pq.is_file():
        files.append(("interim", f"points/{name}.parquet", pq))
        _same_scan_points(name, pq, fcsv, None if sd.frame_ids is None else len(sd.frame_ids))
        try:
            cols = read_columns(pq, ["frame", "laser"])
            sd.point_frames = frame_counts(cols.pop("frame"))
            sd.point_lasers = np.bincount(cols.pop("laser"), minlength=3)
        except Exception as exc:  # pyarrow raises several types for broken files
            log.warning("%s: unreadable (%s)", pq, exc)
        else:
            sd.points_path = pq  # the other readers of the points (depths, labels, viewpoints)
    side = interim / "points" / f"{name}.json"
    if side.is_file():
        files.append(("interim", f"points/{name}.json", side))
        sd.points_info = _read_stats(side, POINTS_STATS)
    ply = processed / f"{name}.ply"
    if ply.is_file():
        files.append(("processed", f"{name}.ply", ply))
        try:
            # the report reads the normals' mean only (the up vector): 12 B a point less
            sd.cloud = read_ply(ply, normals=False)
        except (ValueError, KeyError, OSError) as exc:
            # not the points in its stead: their figures (unfused, unrefined) would stand in the
            # report as the cloud's, as if all were well
            why = str(exc).removeprefix(f"{ply}: ")
            raise StageError(f"{ply}: the fused cloud of scan {name!r} cannot be read ({why}); the "
                             "report does not measure a damaged cloud: delete it and run the "
                             "workflow again (its fuse stage makes it anew)") from None
        sd.cloud_source = f"{name}.ply"
    if sd.cloud is None and pq.is_file():
        try:
            cols = read_columns(pq, ["x", "y", "z", "laser", "frame"])
            sd.cloud = {"points": np.column_stack([cols.pop(k) for k in ("x", "y", "z")]).astype(
                np.float64, copy=False), "laser": cols["laser"],
                "frame": cols["frame"].astype(np.int64, copy=False)}
            sd.cloud_source = f"points/{name}.parquet (no fused cloud)"
        except Exception as exc:
            log.warning("%s: no usable points (%s)", pq, exc)
    for cand in (processed / f"{name}.fuse.json", processed / f"{name}.json"):
        if cand.is_file():
            files.append(("processed", cand.name, cand))
            sd.fuse_stats = _read_stats(cand, FUSE_STATS)
            break
    arm = processed / f"{name}.arm.npz"
    if arm.is_file():
        from crossline.errors import CrosslineError
        from crossline.io.arm_draws import read_arm_draws

        files.append(("processed", arm.name, arm))
        try:
            sd.arm = read_arm_draws(arm)
        except CrosslineError as exc:
            sd.arm_error = str(exc)
            log.warning("%s", exc)
        else:
            if len(sd.arm.draws) == 0:
                sd.arm, sd.arm_error = None, f"{arm.name} holds no draws (fuse.arm_draws: 0)"
            elif fcsv.is_file():
                _same_scan_arm(arm, sd.arm, fcsv, sd.cloud,
                               str(ply) if sd.cloud_source == f"{name}.ply" else str(pq))
    else:
        sd.arm_error = f"no {arm.name} (the fuse stage's draws of the arm's pose errors)"
    return sd

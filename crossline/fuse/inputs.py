"""The fuse stage's inputs: a points parquet's columns, and the scan's frames table.

``read_points_columns`` reads the columns fuse needs row group by row group into arrays
(with each frame's camera centre from the camera-frame columns, :class:`FrameMoments`);
``_read_frames`` reads the frame times and flange positions of a scan's frames.csv, and
``_same_scan`` refuses a frames table of another scan. Split from the fuse stage's module
(issue 21.3; now :mod:`crossline.fuse.cloud`); the package ``crossline.fuse`` re-exports these
names.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from crossline.errors import StageError
from crossline.fuse.camera_centres import FrameMoments
from crossline.io.columns import column_type_problems

__all__ = ["read_points_columns"]

_POINT_COLUMNS = ("frame", "laser", "x", "y", "z", "x_cam", "y_cam", "z_cam", "width")


def read_points_columns(path: Path) -> dict[str, Any]:
    """The columns fuse needs from a points parquet, row group by row group into arrays.

    Returns ``xyz`` (N, 3) float64 base frame, ``laser`` (N,) uint8 codes (1 = A, 2 = B,
    0 = other), ``frame`` (N,) int32 (int64 where a frame number needs it) and ``width`` (N,)
    float32 (where the file has it) of the points with finite x, y, z (and x_cam, y_cam,
    z_cam where it has those); ``non_finite`` counts the others. A file without frame, laser,
    x, y or z is refused, and one whose column read is not of its kind
    (:func:`crossline.io.columns.column_type_problems`: frame whole numbers, laser texts, the
    rest numbers; a number stored as text). Where the file has x_cam, y_cam, z_cam,
    ``cameras`` = (frames, camera centres) from them (:class:`FrameMoments`) instead of the
    points themselves. Strings never become Python objects: a long scan's DataFrame would
    hold several hundred bytes a point.
    """
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    try:
        f = pq.ParquetFile(path)
        names = set(f.schema_arrow.names)
    except Exception as exc:  # pyarrow raises several types for broken files
        raise StageError(f"{path}: cannot be read as parquet ({exc})") from exc
    missing = [c for c in ("frame", "laser", "x", "y", "z") if c not in names]
    if missing:
        stripes = {"u", "v"} <= names and "x" not in names
        what = ("a stripes file (pixel centres u, v), not a points file: triangulate turns it into "
                "points" if stripes else "expected frame, laser, x, y, z, ...")
        raise StageError(f"{path}: missing column(s) {missing}; {what}")
    wrong = column_type_problems(f.schema_arrow, _POINT_COLUMNS)
    if wrong:  # a number stored as text is not cast: the file is not what triangulate wrote
        raise StageError(f"{path}: not a points file of triangulate: {'; '.join(wrong)}")
    n = f.metadata.num_rows
    if n == 0:
        raise StageError(f"{path}: has no points; nothing to fuse")
    cam = all(c in names for c in ("x_cam", "y_cam", "z_cam"))
    # frames as int32 while they fit (4 B a point less for the whole stage)
    out: dict[str, Any] = {"xyz": np.empty((n, 3)), "laser": np.zeros(n, np.uint8),
                           "frame": np.zeros(n, np.int32 if n < 2**31 else np.int64)}
    moments = FrameMoments() if cam else None
    if "width" in names:
        out["width"] = np.empty(n, np.float32)
    k = 0
    try:
        for g in range(f.num_row_groups):
            t = f.read_row_group(g, columns=[c for c in _POINT_COLUMNS if c in names])
            xyz = np.column_stack([t[c].to_numpy() for c in ("x", "y", "z")]).astype(np.float64)
            ok = np.isfinite(xyz).all(1)
            if moments is not None:  # a point is in both frames or in neither
                pc_cam = np.column_stack([t[c].to_numpy() for c in ("x_cam", "y_cam", "z_cam")])
                ok &= np.isfinite(pc_cam.astype(np.float64)).all(1)
            m = int(ok.sum())
            out["xyz"][k:k + m] = xyz[ok]
            if "laser" in names:
                lab = t["laser"].cast("string")
                codes = (np.asarray(pc.equal(lab, "A").fill_null(False)).astype(np.uint8)
                         + 2 * np.asarray(pc.equal(lab, "B").fill_null(False)).astype(np.uint8))
                out["laser"][k:k + m] = codes[ok]
            if "frame" in names:
                fv = t["frame"].to_numpy()[ok]
                if out["frame"].dtype == np.int32 and fv.size and (
                        int(fv.max()) >= 2**31 or int(fv.min()) < -2**31):
                    out["frame"] = out["frame"].astype(np.int64)
                out["frame"][k:k + m] = fv
            if moments is not None:
                moments.add(out["frame"][k:k + m], pc_cam[ok], xyz[ok])
            if "width" in names:
                out["width"][k:k + m] = t["width"].to_numpy()[ok]
            k += m
    except StageError:
        raise
    except Exception as exc:
        raise StageError(f"{path}: cannot be read as parquet ({exc})") from exc
    if k == 0:
        raise StageError(f"{path}: none of its {n} points has finite x, y, z; nothing to fuse")
    for key in ("xyz", "laser", "frame", "width"):
        if key in out and k < n:
            out[key] = out[key][:k]
    out["non_finite"] = n - k
    if moments is not None:
        out["cameras"] = moments.centres()
    return out


def _same_scan(points: Path, frames: Path, n_frames: int) -> None:
    """Raise a StageError when ``frames`` (a frames.csv of ``n_frames`` rows) is not the table of
    the scan ``points`` were triangulated from (as the points file's metadata says)."""
    from crossline.scan.triangulate import read_points_meta

    try:
        meta = read_points_meta(points)
    except (StageError, ValueError):  # a points file of another tool: nothing to compare with
        return
    scan, n = meta.get("scan"), meta.get("frames")
    if frames.parent.parent.name == "scans" and scan is not None and frames.parent.name != scan:
        raise StageError(f"{frames}: the frames table of scan {frames.parent.name!r}, but {points} "
                         f"holds the points of scan {scan!r} (give --frames scans/{scan}/frames.csv)")
    if isinstance(n, int) and n != n_frames:
        raise StageError(f"{frames}: {n_frames} frames, but {points} was triangulated from the {n} "
                         f"frames of scan {scan!r}: not that scan's frames table")


def _frames_in_table(points: Path, frames: Path, point_frames: np.ndarray,
                     table_frames: np.ndarray) -> None:
    """Raise a StageError naming ``frames`` when a frame of the points is not one of its rows."""
    from crossline.io.columns import frame_counts

    if len(point_frames) == 0:
        return
    seen, _ = frame_counts(point_frames)
    missing = np.setdiff1d(seen, np.asarray(table_frames, dtype=np.int64))
    if len(missing):
        raise StageError(f"{frames}: frame(s) {missing[:5].tolist()} of {points.name} "
                         f"({len(missing)} in all) are not rows of this frames table: it is "
                         "not the table of the scan these points were triangulated from")


def _read_frames(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame numbers, times (s) and reported flange positions (mm) of a scan's frames.csv."""
    from crossline.io.capture import read_frames_table

    path = Path(path)
    if not path.is_file():
        raise StageError(f"{path}: frames table not found (the scan's frames.csv)")
    t = read_frames_table(path)  # the capture's own checks: each faulty row named
    # the rows' times increase down the file; the pose refinement's prior correlates the arm's
    # error over the time between frames in frame order, so they must increase with the numbers
    order = np.argsort(t.frames, kind="stable")
    back = np.flatnonzero(np.diff(t.time_s[order]) <= 0)
    if len(back):
        a, b = order[back[0]], order[back[0] + 1]
        raise StageError(
            f"{path}: frame {t.frames[b]} was taken at {t.time_s[b]:g} s, before frame {t.frames[a]} "
            f"at {t.time_s[a]:g} s ({len(back)} such pair(s) of consecutive frame numbers): a scan's "
            "frames are numbered in the order they were taken, their times increasing with the numbers")
    return t.frames, t.time_s, t.T_base_tool[:, :3, 3]

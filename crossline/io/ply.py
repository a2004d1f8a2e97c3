"""The fused cloud's files: binary little-endian PLY (read and written) and binary STL.

Split from :mod:`crossline.fuse` (issue 21.3). The PLY holds float64 coordinates (``x y z``),
then ``nx ny nz`` as float32, ``laser`` as uchar (1 = A, 2 = B) and ``frame`` as int32; Open3D
and other readers read it as an ordinary point cloud with normals. It is written here rather
than by Open3D so that its bytes depend only on the points (no timestamp, no library version),
and read and written a block of rows at a time, so that a long scan's file is never held
whole in memory.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from crossline.io.atomic import atomic_path

if TYPE_CHECKING:
    from crossline.fuse import FusedCloud

__all__ = ["read_ply", "write_ply", "write_stl"]


_PLY_FIELDS = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f4"), ("ny", "<f4"),
               ("nz", "<f4"), ("laser", "u1"), ("frame", "<i4")]
_PLY_TYPES = {"<f8": "double", "<f4": "float", "u1": "uchar", "<i4": "int"}
_PLY_DTYPES = {"double": "<f8", "float64": "<f8", "float": "<f4", "float32": "<f4",
               "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1", "int": "<i4",
               "int32": "<i4", "uint": "<u4", "uint32": "<u4", "short": "<i2", "int16": "<i2",
               "ushort": "<u2", "uint16": "<u2"}
_PLY_BLOCK = 1 << 20  # vertex rows written at a time


def write_ply(path: str | Path, cloud: FusedCloud) -> None:
    """Write the cloud as binary little-endian PLY, atomically; same cloud, same bytes."""
    n = len(cloud.points)
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment crossline fused cloud: base frame, mm",
        "comment laser: 1 = A, 2 = B, 0 = unknown; frame: first frame of the point",
        f"element vertex {n}",
        *(f"property {_PLY_TYPES[t]} {n}" for n, t in _PLY_FIELDS),
        "end_header",
    ]
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        # a block of rows at a time: the whole vertex table would be another 41 B a point
        for a in range(0, max(n, 1), _PLY_BLOCK):
            rows = np.empty(min(_PLY_BLOCK, n - a), dtype=_PLY_FIELDS)
            for i, k in enumerate(("x", "y", "z")):
                rows[k] = cloud.points[a:a + len(rows), i]
            for i, k in enumerate(("nx", "ny", "nz")):
                rows[k] = cloud.normals[a:a + len(rows), i]
            rows["laser"] = cloud.laser[a:a + len(rows)]
            rows["frame"] = cloud.frame[a:a + len(rows)]
            f.write(rows.tobytes())


def read_ply(path: str | Path, *, normals: bool = True) -> dict[str, np.ndarray]:
    """Vertex properties of a binary little-endian PLY (such as ``write_ply``'s) by name.

    Returns ``{"points": (N, 3)}`` plus ``"normals"``, ``"laser"``, ``"frame"`` and any other
    property present (as 1-D arrays). Raises ValueError naming the file for other PLY flavours,
    a file that does not hold what its header declares, and non-finite coordinates or normals.
    With ``normals=False`` the normals are checked but not kept: ``"normal_mean"`` (3,) stands
    for them (a long scan's report needs no more, and they are 12 B a point).
    """
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(1 << 16)  # the header: a few hundred bytes
        end = head.find(b"end_header\n")
        if not head.startswith(b"ply\n") or end < 0:
            raise ValueError(f"{path}: not a PLY file")
        lines = head[:end].decode("ascii", "replace").splitlines()
        if "format binary_little_endian 1.0" not in lines:
            raise ValueError(f"{path}: only binary little-endian PLY is read here")
        fields: list[tuple[str, str]] = []
        n = 0
        element = None
        later = False  # an element after the vertices (faces): the file holds more than them
        for ln in lines:
            parts = ln.split()
            if parts[:1] == ["element"]:
                element = parts[1] if len(parts) > 1 else ""
                later = later or (element != "vertex" and bool(fields))
                if element == "vertex":
                    if len(parts) != 3 or not parts[2].isdigit():
                        raise ValueError(f"{path}: header line {ln!r}: expected 'element vertex <count>'")
                    n = int(parts[2])
                elif fields:
                    break  # vertices come first; later elements (faces) are not read
            elif parts[:1] == ["property"] and element == "vertex":
                if len(parts) > 1 and parts[1] == "list":
                    raise ValueError(f"{path}: list properties on vertices are not supported")
                if len(parts) != 3 or parts[1] not in _PLY_DTYPES:
                    raise ValueError(f"{path}: header line {ln!r}: expected 'property <type> <name>' "
                                     f"with a type among {sorted(_PLY_DTYPES)}")
                fields.append((parts[2], _PLY_DTYPES[parts[1]]))
        missing = [k for k in ("x", "y", "z") if k not in [f for f, _ in fields]]
        if missing:
            raise ValueError(f"{path}: the vertices have no {', '.join(missing)} property")
        start = end + len(b"end_header\n")
        dt = np.dtype(fields)
        size = path.stat().st_size - start
        held = size // dt.itemsize
        if held < n:
            raise ValueError(f"{path}: truncated: the header declares {n} vertices of {dt.itemsize} "
                             f"bytes, the file holds {held} of them")
        if not later and size != n * dt.itemsize:
            raise ValueError(f"{path}: the header declares {n} vertices of {dt.itemsize} bytes "
                             f"({n * dt.itemsize} bytes), the file holds {size} bytes after it: "
                             f"not the file its header describes")
        names = [f for f, _ in fields]
        has_normals = all(k in names for k in ("nx", "ny", "nz"))
        keep_normals = has_normals and normals
        out: dict[str, np.ndarray] = {"points": np.empty((n, 3))}
        if keep_normals:  # as the file stores them (float32 as fuse writes them): 12 B a point less
            out["normals"] = np.empty((n, 3), dtype=np.result_type(dt["nx"], np.float32))
        total = np.zeros(3)
        rest = [k for k in names if k not in ("x", "y", "z", "nx", "ny", "nz")]
        for k in rest:
            out[k] = np.empty(n, dtype=dt[k])
        # a block of rows at a time: the whole file in memory would be another 41 B a point
        f.seek(start)
        for a in range(0, n, _PLY_BLOCK):
            rows = np.fromfile(f, dtype=dt, count=min(_PLY_BLOCK, n - a))
            b = a + len(rows)
            for i, k in enumerate(("x", "y", "z")):
                out["points"][a:b, i] = rows[k]
            if keep_normals:
                for i, k in enumerate(("nx", "ny", "nz")):
                    out["normals"][a:b, i] = rows[k]
            elif has_normals:
                blk = np.column_stack([rows[k] for k in ("nx", "ny", "nz")]).astype(np.float64)
                bad = np.flatnonzero(~np.isfinite(blk).all(axis=1))
                if len(bad):
                    raise ValueError(f"{path}: vertex {a + bad[0]} (of {n}) has non-finite normal "
                                     f"{blk[bad[0]].tolist()}; a fused cloud holds finite values "
                                     "only")
                total += blk.sum(axis=0)
            for k in rest:
                out[k][a:b] = rows[k]
        if has_normals and not normals:
            out["normal_mean"] = total / max(n, 1)
    for key, what in (("points", "coordinates"), ("normals", "normal")):
        bad = np.flatnonzero(~np.isfinite(out[key]).all(axis=1)) if key in out else []
        if len(bad):  # the fuse stage writes finite values only: a damaged or foreign file
            raise ValueError(f"{path}: vertex {bad[0]} (of {n}) has non-finite {what} "
                             f"{out[key][bad[0]].tolist()} ({len(bad)} such vertices); a fused "
                             f"cloud holds finite values only")
    return out


def write_stl(path: str | Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Write a triangle mesh as binary STL (float32, mm), atomically and byte-reproducibly."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(triangles, dtype=np.int64)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    nrm = np.cross(b - a, c - a)
    ln = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.divide(nrm, ln, out=np.zeros_like(nrm), where=ln > 0)
    rec = np.zeros(len(F), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rec["n"] = nrm
    rec["v"] = np.stack([a, b, c], axis=1)
    head = b"crossline mesh, base frame, mm".ljust(80, b" ")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(head)
        f.write(np.uint32(len(F)).tobytes())
        f.write(rec.tobytes())

"""Write fused clouds in the formats inspection software exchanges: ASTM E57.

E57 (ASTM E2807) is the vendor-neutral format of 3-D imaging data that CloudCompare,
PolyWorks, Geomagic Control X and the scanner vendors' own tools read. It is written with
libE57Format, the standard's reference implementation, through the bindings that the
``pye57`` package ships (``pye57.libe57``). pye57's own writer is not used: it stores
coordinates in single precision and gives every file a random GUID, so the same cloud would
never give the same bytes; here coordinates are doubles and the GUIDs are derived from the
content, so the export is as reproducible as every other artefact.

E57 coordinates are metres by the standard; crossline's millimetres are converted on the
way out (and back in :func:`read_e57`). Normals go into the E57 surface-normals extension
(``nor:normalX`` ...), which CloudCompare reads.
"""

from __future__ import annotations

import hashlib
import uuid
from pathlib import Path

import numpy as np

from crossline.errors import StageError
from crossline.io.atomic import atomic_path

__all__ = ["read_e57", "run_export_cloud", "write_e57"]

MM_PER_M = 1000.0
_NOR_URI = "http://www.libe57.org/E57_NOR_surface_normals.txt"
_CHUNK = 1 << 20


def _libe57():
    try:
        from pye57 import libe57
    except ImportError as exc:  # pragma: no cover - pye57 is a dependency
        raise StageError("E57 export needs the pye57 package (pip install pye57)") from exc
    return libe57


def _guid(*parts: bytes) -> str:
    h = hashlib.sha256(b"".join(parts)).digest()
    return f"{{{uuid.UUID(bytes=h[:16], version=5)}}}"


def _buffers(e, imf, arrays: dict[str, np.ndarray], capacity: int):
    """libE57's buffer list over numpy arrays (converted and scaled to doubles)."""
    out = e.VectorSourceDestBuffer()
    for k, a in arrays.items():
        out.append(e.SourceDestBuffer(imf, k, a, capacity, True, True))
    return out


def write_e57(path: str | Path, points_mm: np.ndarray, normals: np.ndarray | None = None,
              name: str = "scan", description: str = "crossline fused cloud") -> None:
    """Write an (N, 3) cloud in mm (and its unit normals) as one E57 scan, atomically."""
    P = np.ascontiguousarray(points_mm, dtype=np.float64) / MM_PER_M
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise StageError(f"{path}: E57 export needs an (N, 3) cloud with N > 0, got {P.shape}")
    N = None if normals is None else np.ascontiguousarray(normals, dtype=np.float64)
    if N is not None and N.shape != P.shape:
        raise StageError(f"{path}: normals {N.shape} do not match the points {P.shape}")
    e = _libe57()
    content = P.tobytes() + (N.tobytes() if N is not None else b"")
    with atomic_path(path) as tmp:
        imf = e.ImageFile(str(tmp), "w")
        try:
            imf.extensionsAdd("", e.E57_V1_0_URI)
            if N is not None:
                imf.extensionsAdd("nor", _NOR_URI)
            root = imf.root()
            root.set("formatName", e.StringNode(imf, "ASTM E57 3D Imaging Data File"))
            root.set("guid", e.StringNode(imf, _guid(b"file", content)))
            root.set("versionMajor", e.IntegerNode(imf, e.E57_FORMAT_MAJOR))
            root.set("versionMinor", e.IntegerNode(imf, e.E57_FORMAT_MINOR))
            root.set("coordinateMetadata", e.StringNode(imf, ""))
            data3d = e.VectorNode(imf, True)
            root.set("data3D", data3d)
            root.set("images2D", e.VectorNode(imf, True))
            scan = e.StructureNode(imf)
            scan.set("guid", e.StringNode(imf, _guid(b"scan", name.encode(), content)))
            scan.set("name", e.StringNode(imf, name))
            scan.set("description", e.StringNode(imf, description))
            lo, hi = P.min(axis=0), P.max(axis=0)
            bounds = e.StructureNode(imf)
            for i, ax in enumerate("xyz"):
                bounds.set(f"{ax}Minimum", e.FloatNode(imf, float(lo[i])))
                bounds.set(f"{ax}Maximum", e.FloatNode(imf, float(hi[i])))
            scan.set("cartesianBounds", bounds)
            proto = e.StructureNode(imf)
            fields = {}
            for i, ax in enumerate("XYZ"):
                a, b = float(lo[i]), float(hi[i])
                proto.set(f"cartesian{ax}", e.FloatNode(imf, a, e.E57_DOUBLE, a, b))
                fields[f"cartesian{ax}"] = P[:, i]
            if N is not None:
                for i, ax in enumerate("XYZ"):
                    proto.set(f"nor:normal{ax}", e.FloatNode(imf, 0.0, e.E57_SINGLE, -1.0, 1.0))
                    fields[f"nor:normal{ax}"] = N[:, i]
            points = e.CompressedVectorNode(imf, proto, e.VectorNode(imf, True))
            scan.set("points", points)
            data3d.append(scan)
            n = len(P)
            cap = min(_CHUNK, n)
            bufs = {k: np.empty(cap, np.float64) for k in fields}
            writer = points.writer(_buffers(e, imf, bufs, cap))
            for start in range(0, n, cap):
                m = min(cap, n - start)
                for k, v in fields.items():
                    bufs[k][:m] = v[start:start + m]
                writer.write(m)
            writer.close()
        finally:
            imf.close()


def read_e57(path: str | Path) -> dict[str, np.ndarray]:
    """The first scan of an E57 file: ``points`` (N, 3) in mm and, where present, ``normals``."""
    e = _libe57()
    imf = e.ImageFile(str(path), "r")
    try:
        scan = e.StructureNode(e.VectorNode(imf.root().get("data3D")).get(0))
        points = e.CompressedVectorNode(scan.get("points"))
        proto = e.StructureNode(points.prototype())
        names = [f"cartesian{a}" for a in "XYZ"]
        # the normals extension's names are well formed only where the file declares its prefix
        # (a file written without normals, by another program, may not)
        nor = any(imf.extensionsPrefix(i) == "nor" for i in range(imf.extensionsCount()))
        if nor and proto.isDefined("nor:normalX"):
            names += [f"nor:normal{a}" for a in "XYZ"]
        n = points.childCount()
        bufs = {k: np.empty(n, np.float64) for k in names}
        reader = points.reader(_buffers(e, imf, bufs, n))
        got = reader.read()
        reader.close()
    finally:
        imf.close()
    out = {"points": np.column_stack([bufs[f"cartesian{a}"][:got] for a in "XYZ"]) * MM_PER_M}
    if "nor:normalX" in bufs:
        out["normals"] = np.column_stack([bufs[f"nor:normal{a}"][:got] for a in "XYZ"])
    return out


def run_export_cloud(ply: str | Path, out: str | Path) -> int:
    """The export stage: a fused cloud's PLY (crossline's own) written as E57; returns N."""
    from crossline.fuse import read_ply

    ply, out = Path(ply), Path(out)
    if not ply.is_file():
        raise StageError(f"{ply}: fused cloud not found (run fuse first)")
    try:
        cloud = read_ply(ply)
    except (OSError, ValueError) as exc:
        raise StageError(f"{ply}: cannot be read as a fused cloud ({exc})") from exc
    if len(cloud["points"]) == 0:
        raise StageError(f"{ply}: the cloud has no points; nothing to export")
    if out.suffix.lower() != ".e57":
        raise StageError(f"{out}: only E57 (.e57) is written; PLY is the fused cloud itself")
    write_e57(out, cloud["points"], cloud.get("normals"), name=ply.stem,
              description=f"crossline fused cloud of scan {ply.stem}, base frame")
    return len(cloud["points"])

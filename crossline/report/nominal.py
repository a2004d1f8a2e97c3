"""Compare a scanned cloud with its nominal (CAD) shape: align, signed deviation, regions, map.

A freeform scan may name a nominal mesh (STL, PLY or OBJ, in mm, in the part's own CAD
frame). The fused cloud is in the arm's base frame, so the comparison runs in three steps:

1. ``align_to_nominal``: the rigid transform ``T_nominal_cloud``. Coarse from a datum the
   user gives or from RANSAC on FPFH features; fine by iterating Open3D's point-to-plane
   step with a Tukey kernel on the *exact* closest points of the mesh (not on samples of
   it), the kernel's scale following the residuals' robust sigma, so that a local defect
   and points off the part (table, fixture) do not pull the fit.
2. ``signed_deviation``: distance of every point to the mesh, positive outside.
3. ``deviation_summary`` / ``deviation_colours`` / ``deviation_map_figure``: statistics,
   the out-of-tolerance *regions* (connected clusters, not neighbouring points of one
   defect), a colour map and its PLY.

Precision: Open3D's ``RaycastingScene`` is float32, whose spacing is ~4 nm at 50 mm and
~60 nm at 1 m from the origin; its closest points lose a few bits more. So the scene is
built in coordinates centred on the mesh, and each distance is recomputed in float64 on the
triangle the scene found (``crossline.report.metrics.point_triangle_closest``): exact to
~1e-12 mm where that triangle is the closest one, and off by about one float32 spacing at
the part's own size (nanometres) where rounding picked a neighbour instead.

Everything here takes and returns arrays; only ``load_nominal`` and ``write_coloured_ply``
touch files.

The code is split by idea (issue 21.3): ``nominal_surface`` (the mesh's ray-casting scene,
closest points and signed distance), ``nominal_align`` (coarse and fine alignment, the
alignment's ambiguity), ``nominal_regions`` (statistics and out-of-tolerance regions),
``nominal_map`` (colours, the coloured PLY, the deviation map figure). This module keeps
reading the mesh, its support plane and ``signed_deviation``, and re-exports the names its
importers use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from crossline.errors import CrosslineError
from crossline.report.nominal_align import WEAK_MODE_RATIO as WEAK_MODE_RATIO
from crossline.report.nominal_align import align_to_nominal, weakest_mode_ratio
from crossline.report.nominal_map import deviation_colours, deviation_map_figure, write_coloured_ply
from crossline.report.nominal_regions import deviation_summary
from crossline.report.nominal_surface import _Surface

__all__ = [
    "align_to_nominal",
    "deviation_colours",
    "deviation_map_figure",
    "deviation_summary",
    "load_nominal",
    "signed_deviation",
    "support_plane",
    "weakest_mode_ratio",
    "write_coloured_ply",
]

MESH_SUFFIXES = (".stl", ".ply", ".obj")


# ----------------------------------------------------------------------------- mesh


def load_nominal(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 mm and triangles (F, 3) int64 of an STL, PLY or OBJ mesh."""
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise CrosslineError(f"{path}: nominal mesh must be STL, PLY or OBJ, not '{path.suffix}'")
    if not path.is_file():
        raise CrosslineError(f"{path}: nominal mesh not found")
    # Open3D only warns on a file it cannot parse and returns an empty mesh: the checks
    # below turn that into an error that names the file
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise CrosslineError(
            f"{path}: no triangles could be read (expected a triangle mesh in STL, PLY or OBJ)"
        )
    V = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.isfinite(V).all():
        bad = int(np.flatnonzero(~np.isfinite(V).all(1))[0])
        raise CrosslineError(f"{path}: vertex {bad} is not finite ({V[bad].tolist()})")
    F = np.asarray(mesh.triangles, dtype=np.int64)
    if F.min() < 0 or F.max() >= len(V):
        raise CrosslineError(f"{path}: triangle indices outside 0..{len(V) - 1}")
    # STL stores three vertices per triangle: merge the exact duplicates so that edges are
    # shared and a closed part is recognised as closed (its sign then comes from parity)
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        raise CrosslineError(f"{path}: every triangle is degenerate (zero area)")
    return (np.asarray(mesh.vertices, dtype=np.float64).copy(),
            np.asarray(mesh.triangles, dtype=np.int64).copy())


def support_plane(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The plane ``(n, d)`` of a mesh's open boundary, if it is one plane: the face a part
    stands on and its drawing leaves open (``n`` points into the part). None for a closed
    mesh or a boundary that is not flat (to 1e-4 of the part's size)."""
    from crossline.geometry import fit_plane

    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(triangles, dtype=np.int64)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    rim = np.unique(uniq[counts == 1])
    if len(rim) < 3:
        return None
    n, d = fit_plane(V[rim])
    size = float(np.linalg.norm(np.ptp(V, axis=0)))
    if np.abs(V[rim] @ n + d).max() > 1e-4 * size:
        return None
    if float(V.mean(axis=0) @ n + d) < 0:
        n, d = -n, -d
    return n, float(d)


# ----------------------------------------------------------------------------- deviation


def signed_deviation(
    points_nominal_frame: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
    directions: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Signed distance (N,) in mm of points (N, 3) to the nominal mesh, positive outside (excess).

    Closed meshes (every edge shared by two triangles) take the sign from the parity of ray
    crossings (``RaycastingScene.compute_occupancy``, three rays), as
    ``compute_signed_distance`` does; meshes that are not closed take it from the side of
    the closest triangle, i.e. positive where its counter-clockwise normal points. The
    distance is Open3D's closest point, recomputed in float64 on that triangle. Points that
    are not finite get NaN. With ``directions``, also the gradient (N, 3) of the signed
    distance at each point: the unit vector from its closest point towards it, signed so that
    moving along it increases the deviation (the triangle's normal where the point lies on the
    surface), which is how the deviation follows a small move of the point.
    """
    p = np.asarray(points_nominal_frame, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(p), np.nan)
    grad = np.full((len(p), 3), np.nan)
    ok = np.isfinite(p).all(1)
    if ok.any():
        d, q, n = _Surface(vertices, triangles).signed(p[ok])
        out[ok] = d
        if directions:
            with np.errstate(invalid="ignore", divide="ignore"):
                g = (p[ok] - q) / d[:, None]
            on = np.abs(d) < 1e-9
            g[on] = n[on]
            grad[ok] = g
    return (out, grad) if directions else out

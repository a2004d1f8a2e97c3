"""Synthetic cross-line scans with exact geometry, for the fuse, metrology and report tests.

Not a renderer: no images. Each frame's laser sheets (planes in the camera frame) are
intersected analytically with a scene of rectangles and spheres (or an Open3D mesh), seen
from a camera moving over it; the points come out in the camera and the base frames, as the
triangulation stage writes them, with the laser that made them. Optional Gaussian noise.
A capture folder (rig.yaml, frames.csv, truth.json) and the calibration JSONs the report
reads are written beside them, so that the report can run without the other stages.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from crossline.geometry import (
    invert_transform,
    make_transform,
    rotvec_to_matrix,
    transform_points,
    transform_to_pose,
)
from crossline.io.atomic import write_json, write_parquet

K_PAPER = [[5145.362, 0.0, 1517.375], [0.0, 5153.664, 1023.363], [0.0, 0.0, 1.0]]
DIST_PAPER = [-0.09903, 0.195427, -0.000065974, -0.0000978477, 0.41673]
X_PAPER = [[-0.42684, 0.66270, -0.61532, 4.1373], [-0.904314, -0.3163, 0.286604, 21.393],
           [-0.004728, 0.678785, 0.73432, 112.962], [0, 0, 0, 1]]


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


# the two sheets cross at (0, 0, 150) mm on the optical axis; each lies at 68° to the axis
LASER_ORIGIN = {"A": np.array([60.0, 0.0, 0.0]), "B": np.array([0.0, 60.0, 0.0])}
LASER_NORMAL = {"A": _unit([1.0, 0.0, 0.4]), "B": _unit([0.0, 1.0, 0.4])}


def laser_plane(L: str) -> tuple[np.ndarray, float]:
    """True plane (normal, d) of laser L in the camera frame."""
    n = LASER_NORMAL[L]
    return n, float(-n @ LASER_ORIGIN[L])


@dataclass
class Rect:
    """A rectangle: corner o, edge vectors a and b."""

    o: np.ndarray
    a: np.ndarray
    b: np.ndarray

    def hit(self, org: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        n = np.cross(self.a, self.b)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.o - org) @ n) / (dirs @ n)
        p = org + t[:, None] * dirs
        q = p - self.o
        u = q @ self.a / (self.a @ self.a)
        v = q @ self.b / (self.b @ self.b)
        ok = (t > 1e-9) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
        return np.where(ok, t, np.inf)


@dataclass
class Ball:
    """A sphere (only its upper part above z_min is real; the rest is the stem/plate's)."""

    c: np.ndarray
    r: float

    def hit(self, org: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        oc = org - self.c
        b = dirs @ oc
        disc = b * b - (oc @ oc - self.r**2)
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        return np.where((disc > 0) & (t > 1e-9), t, np.inf)


def box(lo, hi) -> list[Rect]:
    """The 5 visible faces (top and sides) of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    dx, dy, dz = hi - lo
    ex, ey, ez = np.eye(3)
    return [Rect(np.array([lo[0], lo[1], hi[2]]), ex * dx, ey * dy),
            Rect(lo.copy(), ex * dx, ez * dz), Rect(np.array([lo[0], hi[1], lo[2]]), ex * dx, ez * dz),
            Rect(lo.copy(), ey * dy, ez * dz), Rect(np.array([hi[0], lo[1], lo[2]]), ey * dy, ez * dz)]


def scene(kind: str, *, T_world: np.ndarray | None = None):
    """Primitives of an artefact on a plate (scene frame: plate at z = 0, up +z) and its truth."""
    plate = Rect(np.array([-45.0, -35.0, 0.0]), np.array([90.0, 0, 0]), np.array([0, 70.0, 0]))
    if kind == "gauge_block":
        prims = [plate, *box([-17.5, -4.5, 0.0], [17.5, 4.5, 20.0])]
        truth = {"height": 20.0, "plate_plane_base": [0, 0, 1, 0.0], "top_plane_base": [0, 0, 1, -20.0]}
    elif kind == "plane":
        prims = [plate]
        truth = {"plane_base": [0, 0, 1, 0.0]}
    elif kind == "sphere":
        c = np.array([0.0, 0.0, 22.5])
        prims = [plate, Ball(c, 12.5)]
        truth = {"diameter": 25.0, "center_base": c.tolist()}
    else:
        raise ValueError(kind)
    return prims, truth


def cast(prims, org: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Nearest hit distance of rays (inf where nothing is hit)."""
    t = np.full(len(dirs), np.inf)
    for p in prims:
        t = np.minimum(t, p.hit(org, dirs))
    return t


def scan_points(prims, *, frames: int = 120, pattern=("A", "B", "AB"), rays: int = 500,
                noise: float = 0.0, seed: int = 0, height: float = 165.0, travel=(-25.0, 25.0),
                T_scene: np.ndarray | None = None, mesh=None):
    """Points of a scan: DataFrame (frame, laser, u, v, x_cam.., x..) and per-frame T_base_cam.

    The camera looks straight down from ``height`` above the plate and moves along the
    diagonal of x and y.
    ``T_scene`` places the scene (and so the whole scan) anywhere in the base frame.
    """
    rng = np.random.default_rng(seed)
    T_scene = np.eye(4) if T_scene is None else T_scene
    R_down = rotvec_to_matrix([np.pi, 0.0, 0.0])
    out = []
    Ts = []
    xs = np.linspace(travel[0], travel[1], frames)
    for k in range(frames):
        # along the diagonal: both stripes sweep the surface (neither runs along the motion)
        T_scene_cam = make_transform(R_down, [xs[k] * 0.7071, xs[k] * 0.7071, height])
        T_base_cam = T_scene @ T_scene_cam
        Ts.append(T_base_cam)
        state = pattern[k % len(pattern)]
        lasers = ["A", "B"] if state == "AB" else [state] if state in ("A", "B") else []
        for L in lasers:
            org_c = LASER_ORIGIN[L]
            s = np.linspace(-40.0, 40.0, rays)
            tgt = np.zeros((rays, 3))
            tgt[:, 2] = 150.0
            if L == "A":
                tgt[:, 1] = s
            else:
                tgt[:, 0] = s
            d_c = tgt - org_c
            d_c /= np.linalg.norm(d_c, axis=1, keepdims=True)
            org_s = transform_points(T_scene_cam, org_c[None])[0]
            d_s = d_c @ T_scene_cam[:3, :3].T
            if mesh is not None:
                t = _mesh_cast(mesh, org_s, d_s)
            else:
                t = cast(prims, org_s, d_s)
            ok = np.isfinite(t)
            p_s = org_s + t[ok, None] * d_s[ok]
            # visible from the camera? (nothing nearer along the camera ray)
            cam_s = T_scene_cam[:3, 3]
            v = p_s - cam_s
            dist = np.linalg.norm(v, axis=1)
            v /= dist[:, None]
            tv = _mesh_cast(mesh, cam_s, v) if mesh is not None else cast(prims, cam_s, v)
            vis = tv > dist - 1e-6
            p_s = p_s[vis]
            p_c = transform_points(invert_transform(T_scene_cam), p_s)
            if noise:
                p_c = p_c + rng.normal(scale=noise, size=p_c.shape)
            p_b = transform_points(T_base_cam, p_c)
            out.append(pd.DataFrame({
                "frame": np.full(len(p_c), k, dtype=np.int64), "laser": L,
                "u": 0.0, "v": 0.0,
                "x_cam": p_c[:, 0], "y_cam": p_c[:, 1], "z_cam": p_c[:, 2],
                "x": p_b[:, 0], "y": p_b[:, 1], "z": p_b[:, 2]}))
    df = pd.concat(out, ignore_index=True)
    states = [pattern[k % len(pattern)] for k in range(frames)]
    return df, np.array(Ts), states


_SCENES: dict = {}


def _mesh_cast(mesh, org, dirs):
    import open3d as o3d

    if _SCENES.get("mesh") is not mesh:  # one scene per mesh, built once per scan
        _SCENES["mesh"] = mesh
        _SCENES["scene"] = o3d.t.geometry.RaycastingScene()
        _SCENES["scene"].add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    scene_ = _SCENES["scene"]
    r = np.column_stack([np.repeat(org[None], len(dirs), 0), dirs]).astype(np.float32)
    return scene_.cast_rays(o3d.core.Tensor(r))["t_hit"].numpy().astype(np.float64)


def bump_mesh(n: int = 120, size: float = 80.0):
    """A smooth freeform part: a bump on a slope, as a triangle grid (legacy Open3D mesh)."""
    import open3d as o3d

    g = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(g, g)
    Z = 6.0 * np.exp(-(X**2 + 0.5 * Y**2) / 150.0) + 0.05 * X
    V = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F))
    return m


def _plane_to_base(plane, T):
    n = np.asarray(plane[:3], float)
    d = float(plane[3])
    nb = T[:3, :3] @ n
    return [*nb.tolist(), d - float(nb @ T[:3, 3])]


def make_capture(root: Path, interim: Path, *, noise: float = 0.004, frames: int = 90,
                 rays: int = 300, seed: int = 0, capture_date: str | None = "2024-05-17",
                 scans=("gauge", "plate", "ball", "part"), truth: bool = True,
                 calib_error: float = 1.0, stray_mm: float = 3.0) -> dict:
    """Write a synthetic capture (rig.yaml, frames.csv, truth.json), its calibration JSONs
    and points parquets. ``calib_error`` scales the small errors put into the calibrations;
    the part's scan gets a patch of points ``stray_mm`` off its surface. Returns
    ``{"planted_off_part": n}``."""
    info = {"planted_off_part": 0}
    rng = np.random.default_rng(seed)
    root, interim = Path(root), Path(interim)
    T_scene = make_transform(rotvec_to_matrix([0.02, -0.03, 0.4]), [400.0, -120.0, 35.0])
    X = np.asarray(X_PAPER, dtype=np.float64)
    from crossline.geometry import orthonormalize

    X[:3, :3] = orthonormalize(X[:3, :3])
    kinds = {"gauge": "gauge_block", "plate": "plane", "ball": "sphere", "part": "freeform"}
    rig_scans = {"gauge": {"artefact": "gauge_block", "height": 20.0},
                 "plate": {"artefact": "plane"}, "ball": {"artefact": "sphere", "diameter": 25.0},
                 "part": {"artefact": "freeform"}}
    lines = ["format: crossline-capture/1", "sensor: {width: 3072, height: 2048, bit_depth: 8}",
             "scan_window: {x: 207, y: 624, width: 2658, height: 800}", "frame_rate: 80",
             "board: {pattern: symmetric, cols: 15, rows: 11, spacing: 3.75, diameter: 1.875, "
             "circles: dark}"]
    if capture_date:
        lines.append(f"capture_date: '{capture_date}'")
    lines.append("scans:")
    for s in scans:
        spec = rig_scans[s]
        lines.append(f"  {s}: {json.dumps(spec)}")
    root.mkdir(parents=True, exist_ok=True)
    (root / "rig.yaml").write_text("\n".join(lines) + "\n")
    tr_scans = {}
    for i, s in enumerate(scans):
        kind = kinds[s]
        mesh = None
        if kind == "freeform":
            mesh = bump_mesh()
            prims, t = [], {"mesh": "truth/part.ply"}
            import open3d as o3d

            (root / "truth").mkdir(exist_ok=True)
            mb = o3d.geometry.TriangleMesh(mesh)
            mb.transform(T_scene)
            o3d.io.write_triangle_mesh(str(root / "truth" / "part.ply"), mb)
        else:
            prims, t = scene(kind)
        df, Ts, states = scan_points(prims, frames=frames, rays=rays, noise=noise, seed=seed + i,
                                     T_scene=T_scene, mesh=mesh, height=165.0 if kind != "freeform"
                                     else 160.0)
        if kind == "freeform" and stray_mm:
            # a dense patch 3 mm off the part (something else under the stripes): the
            # validation must count it apart, not let it into the deviations
            xyz = df[["x", "y", "z"]].to_numpy()
            centre = xyz[len(xyz) // 2]
            patch = df[np.linalg.norm(xyz - centre, axis=1) < 4.0].copy()  # a copy of the
            # surface within 4 mm of a point, lifted: as dense as the scan, so fusion keeps it
            p = patch[["x", "y", "z"]].to_numpy() + T_scene[:3, 2] * stray_mm
            f = patch["frame"].to_numpy()
            pc = np.einsum("nij,nj->ni", invert_transform(Ts)[f, :3, :3], p) + invert_transform(Ts)[f, :3, 3]
            patch[["x", "y", "z"]] = p
            patch[["x_cam", "y_cam", "z_cam"]] = pc
            df = pd.concat([df, patch], ignore_index=True)
            info["planted_off_part"] = len(patch)
        # truth in the base frame
        for key in ("plate_plane_base", "top_plane_base", "plane_base"):
            if key in t:
                t[key] = _plane_to_base(t[key], T_scene)
        if "center_base" in t:
            t["center_base"] = transform_points(T_scene, np.asarray([t["center_base"]]))[0].tolist()
        tr_scans[s] = t
        d = root / "scans" / s
        d.mkdir(parents=True, exist_ok=True)
        T_base_tool = Ts @ invert_transform(X)
        pos, q = transform_to_pose(T_base_tool)
        fr = pd.DataFrame({"frame": np.arange(len(Ts)), "time_s": np.arange(len(Ts)) / 80.0,
                           "lasers": states, "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                           "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3]})
        fr.to_csv(d / "frames.csv", index=False, float_format="%.9f")
        write_parquet(interim / "points" / f"{s}.parquet", df)
    if truth:
        write_json(root / "truth.json", {
            "camera": {"K": K_PAPER, "dist": DIST_PAPER, "image_size": [3072, 2048]},
            "lasers": {L: {"normal": laser_plane(L)[0].tolist(), "d": laser_plane(L)[1]}
                       for L in ("A", "B")},
            "T_tool_cam": X.tolist(), "T_base_board": np.eye(4).tolist(), "scans": tr_scans})
    # calibrations, each a little off
    e = calib_error
    K = np.array(K_PAPER) + np.array([[0.8, 0, 0.5], [0, -0.6, -0.4], [0, 0, 0]]) * e
    views = [{"image": f"view_{i:02d}.png", "used": i != 7, "reason": None if i != 7 else
              "RMS 0.41 px is over 3 × the median", "rms_px": float(0.05 + 0.02 * rng.random())
              if i != 7 else 0.41} for i in range(15)]
    # the camera stage's layout: residuals and board pose per used view, and the board
    from crossline.board import Board

    board = Board("symmetric", 15, 11, 3.75, 1.875, "dark")
    poses, residuals = {}, {}
    for v in views:
        if v["used"]:
            R = rotvec_to_matrix(rng.normal(scale=0.1, size=3))
            c = np.array([26.25, 18.75, 0.0])  # the board's centre, in view
            poses[v["image"]] = make_transform(R, np.array([0.0, 0.0, 150.0]) - R @ c
                                               + rng.normal(scale=3, size=3))
            residuals[v["image"]] = rng.normal(scale=0.05, size=(165, 2))
    write_json(interim / "calibration" / "camera.json", {
        "K": K.tolist(), "dist": (np.array(DIST_PAPER) * (1 + 0.002 * e)).tolist(),
        "image_size": [3072, 2048], "rms_px": 0.061, "views": views, "residuals": residuals,
        "T_cam_board": poses, "board": board.to_dict(),
        "bias_correction": {"enabled": True, "iterations": 2}})
    las = {}
    for j, L in enumerate(("A", "B")):
        n, d = laser_plane(L)
        n2 = _unit(n + e * np.array([2e-5, -1e-5, 1.5e-5]) * (1 + j))
        las[L] = {"normal": n2.tolist(), "d": d + e * 0.003 * (1 - 2 * j), "rms_mm": 0.004 + 0.001 * j,
                  "n_points": 5000, "poses": [{"pose": f"p{i}", "rms_mm": 0.004 + 0.001 * i,
                                               "n": 800} for i in range(3)]}
    write_json(interim / "calibration" / "lasers.json", las)
    methods = {}
    for j, name in enumerate(("chou_kamel", "tsai", "park", "refined")):
        dT = make_transform(rotvec_to_matrix(e * np.array([1e-4, -2e-4, 1e-4]) / (1 + j)),
                            e * np.array([0.01, -0.02, 0.015]) / (1 + j))
        methods[name] = {"T_tool_cam": (X @ dT).tolist(), "rotation_residual_deg_rms": 0.01 / (1 + j),
                         "translation_residual_mm_rms": 0.02 / (1 + j),
                         "board_consistency_mm": 0.03 / (1 + j)}
    methods["andreff"] = {"error": "degenerate motion"}
    write_json(interim / "calibration" / "handeye.json", {
        "T_tool_cam": methods["refined"]["T_tool_cam"], "method": "refined", "methods": methods,
        "pairs": {"total": 10, "used": 9, "rejected": 1, "angle_tolerance_deg": 0.05},
        "reprojection_rms_px": 0.07})
    return info

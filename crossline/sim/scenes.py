"""The artefacts on the table (base frame) and the calibration board, as analytic scenes.

* gauge: a surface plate (box) on the table, slightly out of level, and a gauge block of
  ``height`` standing on it (a zirconia-ceramic block: diffuse, so modelled as Lambertian;
  specular reflection is not modelled). Truth: the plate's top plane and the block's top plane.
* plate: a large white plate (box) on the table, tilted by a degree or so. Truth: its top plane.
* ball: a sphere of ``diameter`` on a cylindrical stem standing on the table. Truth: centre.
* ball_bar: two balls of ``diameter`` whose centres are ``length`` apart along the bar's
  direction (its yaw on the table, an optional inclination), each on its own vertical stem
  standing on the table (ISO 10360-8 sphere-spacing error). Truth: both centres.
* part: a freeform like an earbud case (``FreeformPart``), a leaning superellipsoid of
  degree 4 cut by the table: rounded, doubly curved, with steep (near-vertical) flanks.
  Truth: a triangle mesh of its surface (``crossline.sim.part``).
"""

from __future__ import annotations

import numpy as np

from crossline.geometry import rotvec_to_matrix
from crossline.sim.presets import BoardSpec, RigPreset, ScanSpec
from crossline.sim.scene import Box, Cylinder, Dent, FreeformPart, HalfSpace, Scene, Sphere
from crossline.sim.texture import board_texture

__all__ = ["board_box", "board_scene_free", "board_scene_table", "scan_scene"]


def _rot(rx_deg=0.0, ry_deg=0.0, rz_deg=0.0) -> np.ndarray:
    return (rotvec_to_matrix(np.radians([0, 0, rz_deg])) @ rotvec_to_matrix(np.radians([0, ry_deg, 0]))
            @ rotvec_to_matrix(np.radians([rx_deg, 0, 0])))


def board_box(spec: BoardSpec) -> Box:
    """The board's plate as a box in board coordinates (face 4, z = 0, carries the pattern)."""
    xmin, ymin, xmax, ymax = spec.plate_rect()
    th = spec.thickness_mm
    centre = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, th / 2])
    half = np.array([(xmax - xmin) / 2, (ymax - ymin) / 2, th / 2])
    return Box(centre, np.eye(3), half, spec.edge_albedo, "board", hidden=(5,),
               textures={4: board_texture(spec, centre)})


def board_scene_free(spec: BoardSpec, background_mm: float = 40.0) -> Scene:
    """The board (board frame) with a dark background plane ``background_mm`` behind it."""
    bg = HalfSpace(np.array([0.0, 0.0, background_mm + spec.thickness_mm]),
                   np.array([0.0, 0.0, -1.0]), spec.background_albedo, "background")
    return Scene([board_box(spec), bg], up=np.array([0.0, 0.0, -1.0]))


def board_scene_table(preset: RigPreset) -> Scene:
    """The hand-eye board lying on the table at T_base_board, in the base frame."""
    box = board_box(preset.board).transformed(preset.T_base_board)
    table = HalfSpace(np.array([0.0, 0.0, preset.table_z_mm]), np.array([0.0, 0.0, 1.0]),
                      preset.table_albedo, "table")
    return Scene([box, table])


def _plane(n: np.ndarray, p: np.ndarray) -> list[float]:
    n = n / np.linalg.norm(n)
    return [*n.tolist(), float(-n @ p)]


def scan_scene(preset: RigPreset, spec: ScanSpec) -> tuple[Scene, dict, np.ndarray]:
    """The scene of a scan (base frame), its truth entries, and the aim point (base)."""
    p = spec.params
    z0 = preset.table_z_mm
    table = HalfSpace(np.array([0.0, 0.0, z0]), np.array([0.0, 0.0, 1.0]), preset.table_albedo,
                      "table")
    prims = [table]
    truth: dict = {}
    if spec.artefact == "gauge_block":
        L, W, H = p["plate_size"]
        R = _rot(*p.get("plate_tilt_deg", (0.0, 0.0)), 0.0)
        top_centre = np.array([p["centre"][0], p["centre"][1], z0 + H])
        plate = Box(top_centre - R[:, 2] * H / 2, R, np.array([L, W, H]) / 2, p["plate_albedo"],
                    "surface_plate", hidden=(4,))
        Rb = R @ _rot(0, 0, p["yaw_deg"])
        bl, bw = p["size"]
        hgt = p["height"]
        block = Box(top_centre + Rb[:, 2] * hgt / 2, Rb, np.array([bl, bw, hgt]) / 2,
                    p["block_albedo"], "gauge_block", hidden=(4,))
        prims += [plate, block]
        n = R[:, 2]
        truth = {
            "height": float(hgt),
            "plate_plane_base": _plane(n, top_centre),
            "top_plane_base": _plane(n, top_centre + n * hgt),
            "block": {"centre_base": (top_centre + n * hgt / 2).tolist(), "axes_base": Rb.T.tolist(),
                      "size": [bl, bw, hgt]},
        }
        aim = top_centre + n * hgt
    elif spec.artefact == "plane":
        L, W, H = p["size"]
        R = _rot(*p.get("tilt_deg", (0.0, 0.0)), p.get("yaw_deg", 0.0))
        top_centre = np.array([p["centre"][0], p["centre"][1], z0 + H])
        plate = Box(top_centre - R[:, 2] * H / 2, R, np.array([L, W, H]) / 2, p["albedo"],
                    "plate", hidden=(4,))
        prims.append(plate)
        truth = {"plane_base": _plane(R[:, 2], top_centre), "size": [L, W, H]}
        aim = top_centre
    elif spec.artefact == "sphere":
        r = p["diameter"] / 2
        c = np.array([p["centre"][0], p["centre"][1], z0 + p["centre_height"]])
        prims.append(Sphere(c, r, p["albedo"], "ball"))
        prims.append(Cylinder(np.array([c[0], c[1], z0]), np.array([0.0, 0.0, 1.0]), p["stem_radius"],
                              p["centre_height"], p["stem_albedo"], "stem"))
        truth = {"diameter": float(p["diameter"]), "center_base": c.tolist(),
                 "stem": {"radius": p["stem_radius"], "top_base": c.tolist()}}
        aim = c + np.array([0.0, 0.0, r])
    elif spec.artefact == "ball_bar":
        prims += ball_bar_prims(preset, spec)
        r = p["diameter"] / 2
        c1, c2 = ball_bar_centres(preset, spec)
        u = (c2 - c1) / np.linalg.norm(c2 - c1)
        truth = {"diameter": float(p["diameter"]), "length": float(p["length"]),
                 "centers_base": [c1.tolist(), c2.tolist()], "direction_base": u.tolist(),
                 "yaw_deg": float(p["yaw_deg"]), "incline_deg": float(p.get("incline_deg", 0.0)),
                 "stems": [{"radius": p["stem_radius"], "top_base": c.tolist()} for c in (c1, c2)]}
        aim = (c1 + c2) / 2 + np.array([0.0, 0.0, r])  # between the balls, on top
    elif spec.artefact == "freeform":
        part = freeform_part(preset, spec)
        prims.append(part)
        a, b, cz = p["semi_axes"]
        truth = {"design": {"kind": "superellipsoid, degree 4, leaning, cut by the table",
                            "semi_axes": [a, b, cz], "lean": p.get("lean", 0.0),
                            "centre_base": part.c.tolist(), "M": part.M.tolist(),
                            "surface": "||M (p - centre)||_4 = 1 with (M (p - centre))_z >= 0"}}
        if part.dent is not None:
            T = nominal_frame(preset, spec)
            at = part.dent.centre
            truth["dent"] = {
                "profile": "inward along the design normal by depth * exp(-r^2 / (2 sigma^2)), "
                           "r the distance to the centre",
                "depth_mm": part.dent.depth_mm, "sigma_mm": part.dent.sigma_mm,
                "centre_base": at.tolist(),
                "centre_nominal": (T[:3, :3].T @ (at - T[:3, 3])).tolist(),
            }
        aim = part.c + part.Minv @ np.array([0.0, 0.0, 0.75])
    else:
        raise ValueError(f"unknown artefact {spec.artefact!r}")
    return Scene(prims), truth, aim


def ball_bar_centres(preset: RigPreset, spec: ScanSpec) -> tuple[np.ndarray, np.ndarray]:
    """The two ball centres of a ball bar (base frame): ``length`` apart along the bar, its
    middle over ``centre``, the first (lower) ball's centre ``centre_height`` above the table."""
    p = spec.params
    yaw, inc = np.radians(p["yaw_deg"]), np.radians(p.get("incline_deg", 0.0))
    u = np.array([np.cos(yaw) * np.cos(inc), np.sin(yaw) * np.cos(inc), np.sin(inc)])
    half = p["length"] / 2
    mid = np.array([p["centre"][0], p["centre"][1],
                    preset.table_z_mm + p["centre_height"] + half * np.sin(inc)])
    return mid - half * u, mid + half * u


def ball_bar_prims(preset: RigPreset, spec: ScanSpec) -> list:
    """The balls and stems of a ball bar (base frame): ``ball_1``, ``stem_1``, ``ball_2``, ``stem_2``."""
    p = spec.params
    z0 = preset.table_z_mm
    prims: list = []
    for k, c in enumerate(ball_bar_centres(preset, spec), start=1):
        prims.append(Sphere(c, p["diameter"] / 2, p["albedo"], f"ball_{k}"))
        prims.append(Cylinder(np.array([c[0], c[1], z0]), np.array([0.0, 0.0, 1.0]), p["stem_radius"],
                              float(c[2] - z0), p["stem_albedo"], f"stem_{k}"))
    return prims


def nominal_frame(preset: RigPreset, spec: ScanSpec) -> np.ndarray:
    """T_base_part of a freeform: its drawing's frame, origin at the middle of its footprint
    on the table, z up, x along the part's long semi-axis (the frame its nominal mesh is in)."""
    p = spec.params
    T = np.eye(4)
    T[:3, :3] = _rot(0, 0, p.get("yaw_deg", 0.0))
    T[:3, 3] = [p["centre"][0], p["centre"][1], preset.table_z_mm]
    return T


def freeform_part(preset: RigPreset, spec: ScanSpec) -> FreeformPart:
    """The freeform part of a scan spec (base frame)."""
    p = spec.params
    a, b, c = p["semi_axes"]
    R = _rot(0, 0, p.get("yaw_deg", 0.0))
    S = np.array([[1.0, 0.0, -p.get("lean", 0.0)], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    M = np.diag([1 / a, 1 / b, 1 / c]) @ S @ R.T
    centre = np.array([p["centre"][0], p["centre"][1], preset.table_z_mm])
    dent = None
    if p.get("dent"):
        # params "dent": depth_mm, sigma_mm and "at", the plan position (x, y) on the unit
        # superellipsoid; the dent's centre is the surface point above it
        dx, dy = p["dent"]["at"]
        X = np.array([dx, dy, (1.0 - dx**4 - dy**4) ** 0.25])
        dent = Dent(centre + np.linalg.solve(M, X), float(p["dent"]["depth_mm"]),
                    float(p["dent"]["sigma_mm"]))
    return FreeformPart(centre, M, p["albedo"], "part", dent)

"""A tiny analytic scan capture for the scan-stage tests (independent of crossline.sim).

A flat plate in the base frame, a camera with distortion on an arm sweeping over it, two
laser planes crossing in an X; frames are rendered analytically (Gaussian stripe profile
across the true projected line, Poisson-like noise) in a small scan window, with the true
centre of each stripe per column returned for scoring.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import yaml

from crossline.camera import Camera
from crossline.geometry import make_transform, matrix_to_quat, rotvec_to_matrix
from crossline.io.images import write_png
from crossline.laser import LaserPlane, LaserPlanes

SENSOR = (640, 480)
WINDOW = (40, 150, 560, 180)  # x, y, width, height
K = np.array([[900.0, 0.0, 322.0], [0.0, 900.0, 238.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.08, 0.05, 2e-4, -1e-4, 0.0])
T_TOOL_CAM = make_transform(rotvec_to_matrix(np.array([0.01, -0.02, 0.005])), np.array([5.0, -3.0, 40.0]))
# the plate, tilted 8 degrees about base x so that the stripes move as the camera sweeps along y
PLATE = np.array([0.0, np.sin(np.radians(8.0)), np.cos(np.radians(8.0)), 0.0])


def camera() -> Camera:
    """The analytic rig's camera."""
    return Camera(K, DIST, SENSOR)


def planes() -> LaserPlanes:
    """Two planes crossing in an X in the image, through the optical axis at ~150 mm."""
    # plane A contains the direction (1, 0.35, 0) in the image, tilted about it
    out = {}
    for name, slope in (("A", 0.25), ("B", -0.22)):
        line_dir = np.array([1.0, slope, 0.0])
        emitter = np.array([0.0, 60.0 if name == "A" else -60.0, 0.0])
        target = np.array([0.0, 0.0, 150.0])
        n = np.cross(target - emitter, line_dir)
        n /= np.linalg.norm(n)
        d = -float(n @ emitter)
        out[name] = LaserPlane(n, d)
    return LaserPlanes(out["A"], out["B"])


def T_base_tool(i: int, n: int) -> np.ndarray:
    """Arm pose of frame i: the camera 150 mm above the plate, sweeping along y."""
    # T_base_cam = looking down (-z in base), moving along base y
    R_base_cam = rotvec_to_matrix(np.array([np.pi, 0.0, 0.0]))
    t = np.array([1.0, -6.0 + 12.0 * i / max(n - 1, 1), 150.0])
    T_base_cam = make_transform(R_base_cam, t)
    return T_base_cam @ np.linalg.inv(T_TOOL_CAM)


def true_centres(T_btool: np.ndarray, cam: Camera, pl: LaserPlanes, laser: str) -> np.ndarray:
    """True stripe row v (full-sensor) per full-sensor column of the window, NaN off-line."""
    T_cam_base = np.linalg.inv(T_btool @ T_TOOL_CAM)
    # plate plane in the camera frame
    n_b, d_b = PLATE[:3], PLATE[3]
    R, t = T_cam_base[:3, :3], T_cam_base[:3, 3]
    n_c = R @ n_b
    d_c = d_b - n_c @ t
    lp = pl[laser]
    # intersection line of the plate and the laser plane, sampled, projected
    direc = np.cross(n_c, lp.normal)
    A = np.array([n_c, lp.normal, direc])
    p0 = np.linalg.solve(A, np.array([-d_c, -lp.d, 0.0]))
    s = np.linspace(-200, 200, 40001)
    pts = p0 + s[:, None] * direc / np.linalg.norm(direc)
    pts = pts[pts[:, 2] > 1]
    uv = cam.project(pts)
    o = np.argsort(uv[:, 0])
    x0, _y0, w, _h = WINDOW
    cols = np.arange(x0, x0 + w, dtype=float)
    return np.interp(cols, uv[o, 0], uv[o, 1], left=np.nan, right=np.nan)


def render(vs: list[np.ndarray], rng: np.random.Generator, sigma: float = 1.3, peak: float = 180.0,
           bit_depth: int = 8, ambient: np.ndarray | None = None,
           peaks: list[float] | None = None) -> np.ndarray:
    """A frame of the window with Gaussian stripes centred on rows ``vs`` (full-sensor), of
    heights ``peaks`` (default ``peak`` each), on the room's light ``ambient`` (counts, the
    window's shape) where given."""
    _x0, y0, w, h = WINDOW
    rows = np.arange(y0, y0 + h, dtype=float)[:, None]
    img = np.full((h, w), 5.0) + (0.0 if ambient is None else ambient)
    for v, pk in zip(vs, peaks or [peak] * len(vs), strict=True):
        slope = np.gradient(v)
        cosf = 1.0 / np.sqrt(1.0 + slope**2)
        # pixel-integrated Gaussian across the line (normal distance)
        sub = np.linspace(-0.45, 0.45, 7)
        acc = np.zeros((h, w))
        for dv in sub:
            dn = (rows + dv - v[None, :]) * cosf[None, :]
            acc += np.exp(-0.5 * (dn / sigma) ** 2)
        img += pk * np.nan_to_num(acc / sub.size)
    img = img + rng.normal(0.0, 1.0, img.shape) * np.sqrt(img * 0.5 + 1.0)
    full = 255 if bit_depth == 8 else 65535
    scale = 1 if bit_depth == 8 else 257
    return np.clip(np.round(img * scale), 0, full).astype(np.uint8 if bit_depth == 8 else np.uint16)


def make_capture(root: Path, n_frames: int = 24, pattern=("A", "B", "AB"), seed: int = 0,
                 states: list[str] | None = None, bit_depth: int = 8, ambient=None,
                 laser_peaks: dict[str, float] | None = None, sigma: float = 1.3) -> dict:
    """Write the analytic capture under ``root``; return the truth (centres per frame, rig).
    ``ambient(i)`` gives frame i's room light (counts, the window's shape), if given;
    ``laser_peaks`` each laser's stripe height (default 180 counts), ``sigma`` their width (px)."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    x0, y0, w, h = WINDOW
    rig = {
        "format": "crossline-capture/1",
        "sensor": {"width": SENSOR[0], "height": SENSOR[1], "bit_depth": bit_depth},
        "scan_window": {"x": x0, "y": y0, "width": w, "height": h},
        "frame_rate": 80,
        "board": {"pattern": "symmetric", "cols": 5, "rows": 4, "spacing": 3.75, "diameter": 1.875,
                  "circles": "dark"},
        "scans": {"plate": {"artefact": "plane"}},
    }
    (root / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    dummy = np.zeros((4, 4), np.uint8)
    for sub, names in (("camera", ["v0.png"]), ("laser_A", ["p0_board.png", "p0_laser.png",
                                                            "p1_board.png", "p1_laser.png"]),
                       ("laser_B", ["p0_board.png", "p0_laser.png", "p1_board.png", "p1_laser.png"]),
                       ("handeye", ["pose_00.png"])):
        for name in names:
            write_png(root / "calibration" / sub / name, dummy)
    (root / "calibration" / "handeye" / "poses.csv").write_text(
        "image,x,y,z,qw,qx,qy,qz\npose_00.png,0,0,0,1,0,0,0\n")
    cam, pl = camera(), planes()
    states = list(states) if states is not None else [pattern[i % len(pattern)] for i in range(n_frames)]
    fdir = root / "scans" / "plate" / "frames"
    fdir.mkdir(parents=True, exist_ok=True)
    truth = {"frames": [], "states": states, "T_base_tool": [], "v": {}}
    with open(root / "scans" / "plate" / "frames.csv", "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(["frame", "time_s", "lasers", "x", "y", "z", "qw", "qx", "qy", "qz"])
        for i, st in enumerate(states):
            T = T_base_tool(i, len(states))
            vA = true_centres(T, cam, pl, "A")
            vB = true_centres(T, cam, pl, "B")
            on = {"A": ["A"], "B": ["B"], "AB": ["A", "B"], "off": []}[st]
            lit = [{"A": vA, "B": vB}[k] for k in on]
            pk = [(laser_peaks or {}).get(k, 180.0) for k in on]
            amb = None if ambient is None else ambient(i)
            write_png(fdir / f"{i:06d}.png", render(lit, rng, sigma=sigma, bit_depth=bit_depth, ambient=amb,
                                                    peaks=pk))
            q = matrix_to_quat(T[:3, :3])
            wr.writerow([i, f"{i / 80:.6f}", st, *(f"{x:.9f}" for x in T[:3, 3]),
                         *(f"{x:.12f}" for x in q)])
            truth["frames"].append(i)
            truth["T_base_tool"].append(T)
            truth["v"][i] = {"A": vA, "B": vB}
    truth["cols"] = np.arange(x0, x0 + w, dtype=float)
    return truth


def write_calibration(root: Path) -> tuple[Path, Path, Path]:
    """camera.json, lasers.json and handeye.json of the true rig under ``root``."""
    from crossline.io.atomic import write_json

    root.mkdir(parents=True, exist_ok=True)
    camera().save(root / "camera.json")
    planes().save(root / "lasers.json")
    write_json(root / "handeye.json", {"T_tool_cam": T_TOOL_CAM.tolist(), "method": "truth"})
    return root / "camera.json", root / "lasers.json", root / "handeye.json"

"""Random virtual rigs: a whole rig drawn from a seed, as a real engineer could have built it.

``random_rig(seed)`` returns a ``RigPreset`` like ``PRESETS["paper"]``; the same seed gives
the same rig (and, through ``simulate``, the same bytes). The draw is built in the order an
engineer designs a rig, each choice constrained by the ones before:

1. **Sensor**: one of the common machine-vision formats of 1-12 MP (``SENSORS``; ``small``:
   those up to 2.3 MP, for tests), its pixel pitch, full well, read noise, black level, PRNU,
   PSF, f-number; the ADC's data bits (8, 10, 12 or 16, written in the low bits of 16-bit
   PNGs above 8).
2. **Field and lens**: working distance D (70-400 mm, log-uniform) and the field across the
   sensor width (40-150 mm) give the focal length; full field angles of 10-70 deg.
   Distortion: barrel (2 rigs in 3) or pincushion, 0.2-5 % at the image corner, split over
   k1, k2, k3 (kept monotonic to 1.3x the corner radius), small tangential terms, a principal
   point within 2 % of the centre.
3. **Artefacts**: sized to the field: a ball of a standard diameter of 25-40 % of the field,
   a gauge block of a standard height of 15-30 % of it, the freeform scaled from the paper's;
   their heights set the measuring range R.
4. **Lasers**: stripe orientation in the image uniform over 0-180 deg, the second stripe
   turned 50-130 deg from the first (an X, a '+', a turned '+', a stripe near vertical);
   each plane meets the viewing ray at its stripe's crossing of the sensor middle (offset by
   up to 12 % of the sensor height) at a triangulation angle of 20-45 deg, its emitter on
   either side; sheet thickness from a stripe 1/e^2 width of 3-12 px at D (PSF included);
   wavelength 405-660 nm, M^2, fan angle the smallest standard one that covers the field,
   speckle contrast 0.05-0.3 (grain from wavelength, f-number and pitch), exposure 20-100 %
   of full well on white (the second laser within +-20 % of the first).
5. **Scan window**: 80-100 % of the sensor width, 30-100 % of its height, around the stripes
   in the middle of the measuring range, grown until both stripes cross it over the whole
   measuring range; the frame rate rises as the window's rows fall.
6. **Board**: symmetric or asymmetric circle grid (dark or light circles) or chessboard,
   spacing a standard value that makes its extent 40-65 % of the frame's height at the near
   calibration depth, circles of at least 14 px (squares 18 px); every camera, laser and
   hand-eye view of the full and quick calibration must fit (else the board is redrawn).
7. **Mount, arm and room**: hand-eye matrix (any rotation, flange offset 0-60 mm sideways,
   40-180 mm along), board and artefacts on the table 300-650 mm from the base, arm precision
   0.005-0.06 mm, ambient light 0.5-20 % of full well at scan exposure, board views at
   20-95 %, and a laser pattern: A,B,AB; A,B,AB,AB; A,B,AB,AB,AB; A,B,AB,off; or all AB.
   Scans sweep at right angles to the stripes' bisector (the image is rolled accordingly).

A draw that breaks a constraint is drawn again from the next sub-seed; the number of tries
and every drawn quantity are recorded in ``RigPreset.draw`` (truth.json ``rig_draw``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from crossline.board import Board
from crossline.camera import Camera
from crossline.errors import CrosslineError
from crossline.geometry import make_transform, rotvec_to_matrix
from crossline.optics import grain_px
from crossline.sim.presets import (
    ArmNoiseSpec,
    BoardSpec,
    CalibrationSpec,
    LaserSpec,
    RigPreset,
    ScanSpec,
    SensorSpec,
    laser_through,
)

__all__ = ["RANDOM_PRESETS", "SENSORS", "random_rig", "stripe_segment"]

RANDOM_PRESETS = ("random", "random-small")

# (width, height, pixel pitch um) of common machine-vision sensor formats
SENSORS = (
    (1024, 1024, 5.5),   # 1.0 MP
    (1280, 1024, 4.8),   # 1.3 MP
    (1440, 1080, 3.45),  # 1.6 MP
    (1920, 1200, 5.86),  # 2.3 MP
    (2048, 1536, 3.45),  # 3.1 MP
    (2448, 2048, 3.45),  # 5.0 MP
    (2592, 1944, 2.2),   # 5.0 MP
    (3072, 2048, 2.4),   # 6.3 MP
    (4096, 2160, 3.45),  # 8.8 MP
    (4000, 3000, 3.45),  # 12.0 MP
)
SMALL_MP = 2.4  # random-small draws sensors up to this size
BALLS_MM = (10.0, 12.7, 15.0, 20.0, 25.0, 30.0, 38.1, 50.0)
GAUGES_MM = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 40.0, 50.0)
SPACINGS_MM = (0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 3.75, 4.0, 5.0, 6.0, 7.5, 8.0, 10.0,
               12.0, 15.0, 20.0, 25.0, 30.0)
FAN_HALF_DEG = (5.0, 10.0, 15.0, 22.5, 30.0, 37.5, 45.0)
WAVELENGTHS_NM = (405.0, 450.0, 520.0, 635.0, 660.0)
PATTERNS = (("A", "B", "AB"), ("A", "B", "AB", "AB"), ("A", "B", "AB", "AB", "AB"),
            ("A", "B", "AB", "off"), ("AB",))
PATTERN_WEIGHTS = (0.35, 0.25, 0.15, 0.15, 0.10)
MAX_TRIES = 200


class _Redraw(Exception):
    """A drawn quantity breaks a constraint: draw again."""


def _nearest(values, x: float) -> float:
    v = np.asarray(values, dtype=np.float64)
    return float(v[np.argmin(np.abs(np.log(v / x)))])


def _logu(rng, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def stripe_segment(cam: Camera, laser: LaserSpec, z: float,
                   window: tuple[int, int, int, int] | None = None, n: int = 801) -> np.ndarray:
    """Pixels (M, 2) of a laser's stripe on the fronto-parallel plane at depth ``z`` (mm),
    inside its fan and inside ``window`` (default: the sensor)."""
    nrm = np.asarray(laser.normal, dtype=np.float64)
    nxy = float(np.hypot(nrm[0], nrm[1]))
    c = -laser.d - nrm[2] * z
    p0 = np.array([c * nrm[0] / nxy**2, c * nrm[1] / nxy**2, z])
    along = np.array([-nrm[1], nrm[0], 0.0]) / nxy
    w, h = cam.image_size
    half = 1.5 * z * max(w / cam.fx, h / cam.fy)
    P = p0 + np.linspace(-half, half, n)[:, None] * along
    e = np.asarray(laser.emitter)
    fc = np.asarray(laser.fan_centre)
    side = np.cross(nrm, fc)
    phi = np.arctan2((P - e) @ side, (P - e) @ fc)
    P = P[np.abs(phi) <= np.radians(laser.fan_half_angle_deg)]
    uv = cam.project(P)
    x0, y0, ww, hh = window if window is not None else (0, 0, w, h)
    ok = (uv[:, 0] >= x0) & (uv[:, 0] <= x0 + ww - 1) & (uv[:, 1] >= y0) & (uv[:, 1] <= y0 + hh - 1)
    return uv[ok]


def _length(seg: np.ndarray) -> float:
    return float(np.linalg.norm(seg[-1] - seg[0])) if len(seg) > 1 else 0.0


def _distortion(rng, r_corner: float) -> tuple[float, float, float, float, float]:
    """(k1, k2, p1, p2, k3) with 0.2-5 % radial distortion at the corner, monotonic to 1.3x."""
    sign = -1.0 if rng.uniform() < 2 / 3 else 1.0  # barrel (k1 < 0) in two rigs of three
    delta = sign * _logu(rng, 0.002, 0.05)
    a = rng.uniform(0.6, 1.3)
    b = rng.uniform(-0.4, 0.4) * abs(a)
    c = (1.0 - a - b) if rng.uniform() < 0.5 else rng.uniform(-0.2, 0.2)
    r2 = r_corner**2
    k1, k2, k3 = delta * a / r2, delta * b / r2**2, delta * c / r2**3
    r = np.linspace(0.0, 1.3 * r_corner, 200)
    deriv = 1.0 + 3 * k1 * r**2 + 5 * k2 * r**4 + 7 * k3 * r**6
    if deriv.min() < 0.5:
        raise _Redraw("distortion not monotonic")
    p1, p2 = rng.normal(0.0, 3e-4, 2)
    return float(k1), float(k2), float(p1), float(p2), float(k3)


def _sensor(rng, small: bool) -> dict:
    choices = [s for s in SENSORS if not small or s[0] * s[1] <= SMALL_MP * 1e6]
    w, h, pitch = choices[int(rng.integers(len(choices)))]
    data_bits = int(rng.choice([8, 10, 12, 16]))
    return dict(
        width=w, height=h, pixel_pitch_um=pitch, data_bits=data_bits,
        bit_depth=8 if data_bits == 8 else 16,
        full_well_e=round(_logu(rng, 4000.0, 30000.0), 0),
        read_noise_e=round(rng.uniform(2.0, 12.0), 2),
        black_level_dn=round(rng.uniform(0.0, 10.0), 2),
        prnu=round(rng.uniform(0.002, 0.01), 4),
        psf_sigma_px=round(rng.uniform(0.4, 0.75), 3),
        f_number=round(rng.uniform(2.8, 11.0), 1),
    )


def _laser(rng, cam: Camera, D: float, theta: float, alpha: float, offset_px: float,
           width_px: float, psf: float, wavelength: float, peak: float, pitch: float,
           f_number: float, field_mm: float) -> LaserSpec:
    """A laser whose stripe runs at image angle ``theta`` through the sensor middle (offset
    across the stripe) at depth D, its plane at ``alpha`` to the viewing ray there."""
    t = np.array([np.cos(theta), np.sin(theta)])
    q = np.array([cam.cx, cam.cy]) + offset_px * np.array([-t[1], t[0]])
    xy = cam.undistort(q[None])[0]
    P = D * np.array([xy[0], xy[1], 1.0])
    L = np.array([t[0] / cam.fx, t[1] / cam.fy, 0.0])
    L /= np.linalg.norm(L)
    r = P / np.linalg.norm(P)
    m = r - (r @ L) * L
    m /= np.linalg.norm(m)
    k = np.cross(L, m)
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    sb = np.sin(alpha) / (m @ r)
    n = side * np.sqrt(1.0 - sb * sb) * k + sb * m
    d = -float(n @ P)
    # the emitter: the plane's point nearest a point beside the camera's centre
    z_e = rng.uniform(-15.0, 15.0)
    e0 = np.array([0.0, 0.0, z_e])
    e = e0 - (n @ e0 + d) * n
    s0 = float(np.linalg.norm(P - e))
    # sheet thickness from the stripe's 1/e^2 width in the image (PSF taken out)
    sig = np.sqrt(max((width_px / 4.0) ** 2 - psf**2, 0.09))
    cos_a = np.sqrt(max(1.0 - (n @ r) ** 2, 1e-6))
    w0 = 2.0 * sig * cos_a * D / cam.fx
    need = np.degrees(np.arctan(0.6 * field_mm * 1.45 / s0))
    fan = next((f for f in FAN_HALF_DEG if f >= need), FAN_HALF_DEG[-1])
    grain = float(np.clip(grain_px(wavelength, f_number, pitch), 0.3, 1.5))
    return laser_through(
        e, P, L, wavelength_nm=wavelength, waist_mm=float(w0), m2=round(rng.uniform(1.05, 1.5), 3),
        fan_half_angle_deg=fan, fan_rolloff=round(rng.uniform(0.05, 0.3), 3),
        peak_electrons=float(peak), speckle_contrast=round(rng.uniform(0.05, 0.3), 3),
        speckle_grain_px=round(grain, 3),
    )


def _window(rng, cam: Camera, lasers: dict, depths: tuple[float, float, float]):
    """Scan window (x, y, w, h): the stripes' rows in the middle of the measuring range,
    grown until each stripe crosses it at every depth."""
    W, H = cam.image_size
    w = int(W * rng.uniform(0.8, 1.0)) // 16 * 16
    x0 = int((W - w) * rng.uniform(0.0, 1.0)) // 2 * 2
    segs = [stripe_segment(cam, las, depths[1], (x0, 0, w, H)) for las in lasers.values()]
    if any(len(s) < 2 for s in segs):
        raise _Redraw("stripe outside the sensor")
    pts = np.concatenate(segs)
    vc = float(np.median(pts[:, 1]))
    h = max(int(H * rng.uniform(0.3, 1.0)) // 16 * 16, 128)
    while True:
        h = min(h, H)
        y0 = int(np.clip(vc - h / 2, 0, H - h)) // 2 * 2
        win = (x0, y0, w, h)
        ok = True
        for las in lasers.values():
            for z in depths:
                if _length(stripe_segment(cam, las, z, win)) < 0.8 * min(w, h):
                    ok = False
        if ok:
            return win
        if h == H:
            raise _Redraw("a stripe leaves the full-height window within the measuring range")
        h = int(h * 1.15) // 16 * 16 + 16


def _board(rng, cam: Camera, z_near: float, D: float) -> BoardSpec:
    pattern = ("symmetric", "asymmetric", "chessboard")[int(rng.integers(3))]
    circles = "dark" if rng.uniform() < 0.5 else "light"
    H = cam.image_size[1]
    frame_h = z_near * H / cam.fy  # mm across the frame's height at the near depth
    target = rng.uniform(0.4, 0.65) * frame_h
    mm_px = D / cam.fx
    if pattern == "asymmetric":
        rows = int(rng.integers(7, 14))
        cols = int(rng.integers(4, 9))
        span_x = 2 * cols - 1  # spacings along x: (2 (cols - 1) + 1)
    elif pattern == "symmetric":
        cols = int(rng.integers(6, 16))
        rows = int(rng.integers(5, min(cols - 1, 11) + 1))  # never square: 90 deg would be ambiguous
        span_x = cols - 1
    else:
        cols = int(rng.integers(6, 15))
        rows = int(rng.integers(5, min(cols - 1, 10) + 1))
        span_x = cols + 1  # the outer squares beyond the inner corners
    spacing = _nearest(SPACINGS_MM, target / span_x)
    if pattern == "chessboard":
        if spacing / mm_px < 18.0:
            raise _Redraw("chessboard squares too small in the image")
        board = Board("chessboard", cols, rows, spacing)
    else:
        frac = rng.uniform(0.4, 0.6) if pattern == "symmetric" else rng.uniform(0.5, 0.75)
        diameter = round(frac * spacing, 3)
        if diameter / mm_px < 14.0:
            raise _Redraw("circles too small in the image")
        board = Board(pattern, cols, rows, spacing, diameter, circles)
    light, dark = rng.uniform(0.7, 0.9), rng.uniform(0.03, 0.15)
    margin = round(max(2.0, spacing * rng.uniform(0.8, 1.5)), 2)
    return BoardSpec(board, light_albedo=round(light, 3), dark_albedo=round(dark, 3),
                     margin_mm=margin, thickness_mm=round(rng.uniform(2.0, 6.0), 1),
                     edge_albedo=round(rng.uniform(0.3, 0.7), 3),
                     background_albedo=round(rng.uniform(0.1, 0.6), 3))


def _on_table(rng, radius: tuple[float, float], taken: list) -> tuple[float, float]:
    """A point on the table at a radius from the base, clear of the other artefacts."""
    for _ in range(100):
        r, a = rng.uniform(*radius), rng.uniform(-np.pi, np.pi)
        p = (r * np.cos(a), r * np.sin(a))
        if all(np.hypot(p[0] - q[0], p[1] - q[1]) > 260.0 for q in taken):
            taken.append(p)
            return float(p[0]), float(p[1])
    raise _Redraw("no room on the table")


def _scans(rng, D: float, field: float, sweep_deg: float, sizes: dict, taken: list) -> tuple:
    """The four scans, each sweeping along the image direction ``sweep_deg``."""
    ball, gauge, part = sizes["ball"], sizes["gauge"], sizes["part"]

    def traj(distance, extent, tilt_hi=12.0):
        return dict(distance_mm=round(distance, 3), tilt_deg=round(rng.uniform(0.0, tilt_hi), 2),
                    tilt_azimuth_deg=round(rng.uniform(-180, 180), 1),
                    heading_deg=round(rng.uniform(-180, 180), 1),
                    sweep_mm=round(1.1 * extent + 0.3 * field, 2),
                    wobble_deg=round(rng.uniform(0.5, 2.0), 2), roll_deg=-sweep_deg)

    bl = max(1.6 * gauge, 0.45 * field)
    g = ScanSpec(
        "gauge", "gauge_block",
        params=dict(height=gauge, size=(round(bl, 2), round(max(0.3 * bl, 6.0), 2)),
                    block_albedo=round(rng.uniform(0.5, 0.8), 3),
                    plate_albedo=round(rng.uniform(0.35, 0.7), 3),
                    plate_size=(round(3 * field + 100, 1), round(2 * field + 80, 1), 50.0),
                    centre=_on_table(rng, (300.0, 650.0), taken),
                    yaw_deg=round(rng.uniform(-180, 180), 1),
                    plate_tilt_deg=tuple(round(x, 4) for x in rng.uniform(-0.03, 0.03, 2))),
        **traj(D - 0.3 * gauge, bl))
    p = ScanSpec(
        "plate", "plane",
        params=dict(size=(round(2.5 * field + 60, 1), round(2 * field + 40, 1), 8.0),
                    albedo=round(rng.uniform(0.6, 0.9), 3),
                    centre=_on_table(rng, (300.0, 650.0), taken),
                    yaw_deg=round(rng.uniform(-180, 180), 1),
                    tilt_deg=tuple(round(x, 3) for x in rng.uniform(-1.5, 1.5, 2))),
        **traj(D + rng.uniform(-0.1, 0.3) * gauge, field, tilt_hi=15.0))
    b = ScanSpec(
        "ball", "sphere",
        params=dict(diameter=ball, centre=_on_table(rng, (300.0, 650.0), taken),
                    centre_height=round(ball / 2 + max(5.0, 0.6 * ball), 2),
                    stem_radius=round(0.18 * ball, 2), albedo=round(rng.uniform(0.5, 0.8), 3),
                    stem_albedo=round(rng.uniform(0.3, 0.5), 3)),
        **traj(D - 0.15 * ball, ball))
    a, bb, c = part
    f = ScanSpec(
        "part", "freeform",
        params=dict(semi_axes=part, lean=round(rng.uniform(-0.1, 0.1), 3),
                    centre=_on_table(rng, (300.0, 650.0), taken),
                    yaw_deg=round(rng.uniform(-180, 180), 1), albedo=round(rng.uniform(0.5, 0.8), 3)),
        **traj(D - 0.1 * c, 2 * max(a, bb), tilt_hi=22.0))
    return g, p, b, f


def _draw(seed: int, attempt: int, small: bool) -> RigPreset:
    rng = np.random.default_rng([int(seed), 424242, int(attempt)])
    from crossline.sim import views as views_mod

    s = _sensor(rng, small)
    W, H = s["width"], s["height"]
    D = _logu(rng, 70.0, 400.0)
    field = rng.uniform(40.0, 150.0)  # mm across the sensor width at D
    fx = W * D / field
    half_angle = np.degrees(np.arctan(0.5 * np.hypot(W, H) / fx))
    if not 5.0 <= half_angle <= 35.0:
        raise _Redraw("field angle out of range")
    fy = fx * (1.0 + rng.normal(0.0, 5e-4))
    cx = (W - 1) / 2 + rng.normal(0.0, 0.01) * W
    cy = (H - 1) / 2 + rng.normal(0.0, 0.01) * H
    r_corner = 0.5 * np.hypot(W, H) / fx
    dist = _distortion(rng, r_corner)
    K = ((round(fx, 3), 0.0, round(cx, 3)), (0.0, round(fy, 3), round(cy, 3)), (0.0, 0.0, 1.0))
    cam = Camera(np.array(K), np.array(dist), (W, H))

    # artefacts (sized to the field) and the measuring range they need
    ball = _nearest(BALLS_MM, rng.uniform(0.25, 0.4) * field)
    gauge = _nearest(GAUGES_MM, rng.uniform(0.15, 0.3) * field)
    ps = field / 72.0 * rng.uniform(0.8, 1.2)
    part = (round(25.0 * ps, 2), round(20.0 * ps, 2), round(25.0 * ps * rng.uniform(0.7, 1.0), 2))
    R = max(gauge, ball / 2, 0.75 * part[2])
    depths = (D - 0.3 * R, D + 0.35 * R, D + 1.1 * R)

    # lasers
    theta_a = rng.uniform(0.0, np.pi)
    theta_b = theta_a + np.radians(rng.uniform(50.0, 130.0)) * (1 if rng.uniform() < 0.5 else -1)
    width_px = rng.uniform(3.0, 12.0)
    psf = min(s["psf_sigma_px"], 0.8 * width_px / 4.0)
    s["psf_sigma_px"] = round(psf, 3)
    exposure = rng.uniform(0.2, 1.0)
    wavelength = float(rng.choice(WAVELENGTHS_NM))
    lasers, alphas = {}, {}
    for name, theta in (("A", theta_a), ("B", theta_b)):
        alpha = np.radians(rng.uniform(20.0, 45.0))
        alphas[name] = float(np.degrees(alpha))
        peak = exposure * s["full_well_e"] / 0.8 * (1.0 if name == "A" else rng.uniform(0.8, 1.2))
        lasers[name] = _laser(rng, cam, D, theta, alpha, rng.uniform(-0.12, 0.12) * H, width_px,
                              psf, wavelength, peak, s["pixel_pitch_um"], s["f_number"], field)
    window = _window(rng, cam, lasers, depths)
    fps = round(min(500.0, rng.uniform(40.0, 120.0) * H / window[3]), 1)

    # sweep across both stripes: the image direction farthest from both
    cands = [(theta_a + theta_b) / 2, (theta_a + theta_b) / 2 + np.pi / 2]
    score = [min(abs(np.sin(c - theta_a)), abs(np.sin(c - theta_b))) for c in cands]
    sweep_img = cands[int(np.argmax(score))]
    sweep_deg = float(np.degrees(sweep_img))

    # calibration
    cal_depths = (D - 0.2 * R, D + 1.3 * R)
    cal = CalibrationSpec(
        camera_views=18, laser_poses=4, handeye_views=12, depth_range_mm=cal_depths,
        laser_depths_mm=tuple(float(x) for x in np.linspace(D - 0.2 * R, D + 1.2 * R, 4)),
        handeye_distance_mm=float(D + 0.2 * R))
    quick = replace(cal, camera_views=8, laser_poses=3, handeye_views=8,
                    laser_depths_mm=tuple(float(x) for x in np.linspace(D - 0.2 * R, D + 1.2 * R, 3)))
    board = _board(rng, cam, cal_depths[0], D)

    taken: list = []
    bx, by = _on_table(rng, (300.0, 650.0), taken)
    table_z = round(rng.uniform(-20.0, 20.0), 2)
    T_base_board = make_transform(
        rotvec_to_matrix(np.array([0.0, 0.0, np.radians(rng.uniform(-180, 180))]))
        @ rotvec_to_matrix(np.array([np.pi, 0.0, 0.0])),
        np.array([bx, by, table_z + board.thickness_mm]))
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    lateral = rng.uniform(0.0, 60.0) * np.array([np.cos(a := rng.uniform(-np.pi, np.pi)), np.sin(a)])
    T_tool_cam = make_transform(rotvec_to_matrix(axis * rng.uniform(0.0, np.pi)),
                                np.array([lateral[0], lateral[1], rng.uniform(40.0, 180.0)]))
    precision = _logu(rng, 0.005, 0.06)
    arm = ArmNoiseSpec(precision_mm=round(precision, 5), smooth_fraction=round(rng.uniform(0.7, 0.95), 3),
                       corr_time_s=round(_logu(rng, 0.1, 1.0), 3),
                       rot_sigma_rad=float(precision * 1e-3 * rng.uniform(0.5, 2.0)))
    scans = _scans(rng, D, field, sweep_deg, {"ball": ball, "gauge": gauge, "part": part}, taken)
    pattern = PATTERNS[int(rng.choice(len(PATTERNS), p=PATTERN_WEIGHTS))]
    ambient_scan = _logu(rng, 0.005, 0.2) * s["full_well_e"]
    board_exposure = rng.uniform(0.2, 0.95)
    ambient_board = board_exposure * s["full_well_e"] / board.light_albedo

    sensor = SensorSpec(width=W, height=H, K=K, dist=dist, scan_window=window, frame_rate=fps,
                        bit_depth=s["bit_depth"], data_bits=s["data_bits"],
                        full_well_e=s["full_well_e"], read_noise_e=s["read_noise_e"],
                        black_level_dn=s["black_level_dn"], prnu=s["prnu"],
                        psf_sigma_px=s["psf_sigma_px"], pixel_pitch_um=s["pixel_pitch_um"],
                        f_number=s["f_number"])
    off_axis = [float(np.degrees(min(t % (np.pi / 2), np.pi / 2 - t % (np.pi / 2))))
                for t in (theta_a, theta_b)]  # each stripe's angle from the nearest image axis
    kind = "+" if max(off_axis) < 10.0 else "X" if min(off_axis) > 25.0 else "turned +"
    draw = {
        "seed": int(seed), "attempt": int(attempt), "small": bool(small),
        "megapixels": round(W * H / 1e6, 2), "pixel_pitch_um": s["pixel_pitch_um"],
        "data_bits": s["data_bits"], "working_distance_mm": D, "field_mm": field,
        "focal_length_mm": fx * s["pixel_pitch_um"] * 1e-3, "half_field_angle_deg": half_angle,
        "corner_distortion": _corner_distortion(dist, r_corner),
        "measuring_range_mm": R, "window_depths_mm": list(depths),
        "stripe_angle_deg": {"A": float(np.degrees(theta_a) % 180.0),
                             "B": float(np.degrees(theta_b) % 180.0)},
        "cross": kind,
        "triangulation_deg": alphas, "stripe_width_px": width_px, "exposure": exposure,
        "board_exposure": board_exposure, "ambient_scan_fraction": ambient_scan / s["full_well_e"],
        "sweep_image_angle_deg": float(np.degrees(sweep_img) % 180.0),
    }
    rig = RigPreset(
        name="random-small" if small else "random",
        description=(f"random rig {seed}: {W}x{H} {s['data_bits']}-bit camera, "
                     f"f {draw['focal_length_mm']:.1f} mm at {D:.0f} mm, "
                     f"{draw['corner_distortion'] * 100:+.1f} % distortion, "
                     f"{kind} cross at {draw['stripe_angle_deg']['A']:.0f}/"
                     f"{draw['stripe_angle_deg']['B']:.0f} deg, {board.board.pattern} board"),
        capture_date="2025-01-01",
        sensor=sensor, lasers=lasers, board=board, T_tool_cam=T_tool_cam,
        T_base_board=T_base_board, arm=arm, scans=scans, calibration=cal, table_z_mm=table_z,
        table_albedo=round(rng.uniform(0.15, 0.5), 3), ambient_board_e=float(ambient_board),
        ambient_scan_e=float(ambient_scan), pattern=pattern, quick_frames=24,
        quick_calibration=quick, draw=draw,
    )
    # every calibration view of the full and the quick capture must fit the frame
    try:
        for c in (cal, quick):
            views_mod.camera_views(cam, board, c, c.camera_views)
            for i, las in enumerate(lasers.values()):
                views_mod.laser_views(cam, board, las, c.laser_depths_mm, c.laser_poses, phase=0.7 * i)
            views_mod.handeye_views(cam, rig, c.handeye_views, c.handeye_distance_mm)
    except CrosslineError as exc:
        raise _Redraw(str(exc)) from None
    return rig


def _corner_distortion(dist, r_corner: float) -> float:
    k1, k2, _, _, k3 = dist
    r2 = r_corner**2
    return float(k1 * r2 + k2 * r2**2 + k3 * r2**3)


def random_rig(seed: int, small: bool = False) -> RigPreset:
    """The rig drawn from ``seed`` (``small``: sensors up to 2.3 MP); the same seed, the same rig."""
    reasons: list[str] = []
    for attempt in range(MAX_TRIES):
        try:
            return _draw(seed, attempt, small)
        except _Redraw as exc:
            reasons.append(str(exc))
    raise CrosslineError(f"random rig {seed}: no rig met the constraints in {MAX_TRIES} draws "
                         f"(last: {reasons[-1]})")

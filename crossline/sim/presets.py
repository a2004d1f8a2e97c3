"""Virtual rigs: every number the simulator uses, with where it comes from.

``PRESETS["paper"]`` is the rig of the paper (camera, distortion, laser planes, hand-eye
matrix, board, 80 frames/s, an arm of 0.02 mm precision); ``PRESETS["compact"]`` is a
different rig (another camera with stronger barrel distortion and an off-centre principal
point, a 100 mm working distance, other laser planes and wavelength, an asymmetric grid of
light circles, another hand-eye matrix, a less precise arm) so that nothing downstream can be
tuned to one rig. ``crossline.sim.random_rig`` draws any number of others from a seed.

Radiometry is expressed in electrons collected by one pixel during one exposure:

* ``LaserSpec.peak_electrons`` is the peak of the stripe (sheet centre) on a white Lambertian
  surface (albedo 1) at normal incidence, at the sheet's focus distance, in the middle of the
  fan, before vignetting, pixel integration, PSF and speckle. Everything else follows from
  the physics (albedo, incidence cosine, 1/s fan spreading, sheet widening w0/w(s)).
* ``SensorSpec`` converts electrons to digital numbers (DN): shot noise, read noise, full
  well, conversion gain (full well maps to the top DN), black level, quantisation.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field, replace

import numpy as np

from crossline.board import Board
from crossline.geometry import make_transform, orthonormalize, rotvec_to_matrix

__all__ = [
    "PRESETS",
    "ArmNoiseSpec",
    "BoardSpec",
    "CalibrationSpec",
    "LaserSpec",
    "RigPreset",
    "ScanSpec",
    "SensorSpec",
    "ball_bar_scans",
    "laser_from_abcd",
]


@dataclass(frozen=True)
class SensorSpec:
    """Camera sensor and lens: size, window, intrinsics and the electrons-to-DN chain."""

    width: int
    height: int
    K: tuple[tuple[float, ...], ...]
    dist: tuple[float, ...]
    scan_window: tuple[int, int, int, int]  # x, y, width, height
    frame_rate: float
    bit_depth: int = 8
    full_well_e: float = 10500.0  # electrons at saturation
    read_noise_e: float = 6.0  # electrons rms, Gaussian
    black_level_dn: float = 4.0  # offset at 8 bit (scaled by 257 at 16 bit)
    prnu: float = 0.004  # photo-response non-uniformity, relative rms, fixed per pixel
    psf_sigma_px: float = 0.6  # Gaussian PSF (lens + pixel crosstalk), px
    pixel_pitch_um: float = 2.4  # for the record (speckle grain, f-number)
    f_number: float = 8.0
    data_bits: int | None = None  # the ADC's bits inside the container (None: bit_depth)

    def gain_e_per_dn(self, bit_depth: int | None = None) -> float:
        """Conversion gain: full well reaches the top code above the black level."""
        bits = self.bit_depth if bit_depth is None else bit_depth
        top = 2**bits - 1
        return self.full_well_e / (top - self.black_dn(bits))

    def black_dn(self, bit_depth: int | None = None) -> float:
        """Black level (DN) at a bit depth (``black_level_dn`` is at 8 bit: x 257 at 16)."""
        bits = self.bit_depth if bit_depth is None else bit_depth
        return self.black_level_dn * ((2**bits - 1) / 255.0)


@dataclass(frozen=True)
class LaserSpec:
    """One line laser: its plane in the camera frame, emitter, sheet and radiometry."""

    normal: tuple[float, float, float]  # unit normal in cam
    d: float  # n . p + d = 0, mm
    emitter: tuple[float, float, float]  # on the plane, cam frame, mm
    fan_centre: tuple[float, float, float]  # unit direction of the fan's middle ray, in the plane
    wavelength_nm: float = 405.0
    waist_mm: float = 0.08  # 1/e^2 half-thickness of the sheet at its focus (w0)
    m2: float = 1.2  # beam quality of the thin (fast) axis
    focus_mm: float = 155.0  # distance from the emitter to the sheet's waist (s0)
    fan_half_angle_deg: float = 30.0
    fan_rolloff: float = 0.15  # irradiance falls by this fraction at the fan edge (Powell lens)
    peak_electrons: float = 11500.0  # see module docstring
    speckle_contrast: float = 0.15
    speckle_grain_px: float = 0.55  # sigma of the Gaussian that correlates the speckle field

    @property
    def rayleigh_mm(self) -> float:
        """Rayleigh range z_R = pi w0^2 / (M^2 lambda) of the sheet's thickness, mm."""
        return float(np.pi * self.waist_mm**2 / (self.m2 * self.wavelength_nm * 1e-6))


def laser_from_abcd(abcd: tuple[float, float, float, float], **kw) -> LaserSpec:
    """A laser on the plane ``[A B C D]`` (normalised) with its emitter beside the camera.

    The emitter is the point of the plane on z = 0 (the camera's principal plane) nearest the
    optical axis; the fan's middle ray points from it to where the plane meets the optical
    axis, and the sheet is focused there unless ``focus_mm`` is given.
    """
    v = np.asarray(abcd, dtype=np.float64)
    n, d = v[:3] / np.linalg.norm(v[:3]), v[3] / np.linalg.norm(v[:3])
    nxy = n[:2] @ n[:2]
    e = np.array([-d * n[0] / nxy, -d * n[1] / nxy, 0.0])
    axis_pt = np.array([0.0, 0.0, -d / n[2]])
    c = axis_pt - e
    s0 = float(np.linalg.norm(c))
    kw.setdefault("focus_mm", s0)
    return LaserSpec(tuple(n), float(d), tuple(e), tuple(c / s0), **kw)


def laser_through(emitter, target, line_dir, **kw) -> LaserSpec:
    """A laser whose plane holds the emitter, a target point and a direction (cam frame)."""
    e = np.asarray(emitter, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    n = np.cross(t - e, np.asarray(line_dir, dtype=np.float64))
    n /= np.linalg.norm(n)
    d = -float(n @ e)
    if d > 0:
        n, d = -n, -d
    c = (t - e) / np.linalg.norm(t - e)
    kw.setdefault("focus_mm", float(np.linalg.norm(t - e)))
    return LaserSpec(tuple(n), d, tuple(e), tuple(c), **kw)


@dataclass(frozen=True)
class BoardSpec:
    """The calibration board: pattern, its printed albedos and the plate it is printed on."""

    board: Board
    light_albedo: float = 0.80  # white ceramic
    dark_albedo: float = 0.07  # printed black
    margin_mm: float = 4.0  # plate edge beyond the outermost circle edge
    thickness_mm: float = 4.0
    edge_albedo: float = 0.6  # the plate's side faces
    background_albedo: float = 0.25  # table / background behind the board

    def plate_rect(self) -> tuple[float, float, float, float]:
        """Plate outline in board coordinates: xmin, ymin, xmax, ymax (mm)."""
        b = self.board
        ex, ey = b.extent()
        r = 0.0 if b.pattern == "chessboard" else b.diameter / 2
        pad = r + self.margin_mm + (b.spacing if b.pattern == "chessboard" else 0.0)
        return (-pad, -pad, ex + pad, ey + pad)


@dataclass(frozen=True)
class ArmNoiseSpec:
    """Error of the reported flange pose T_base_tool (see crossline.sim.arm)."""

    precision_mm: float = 0.02  # the arm's stated precision, read as 2 sigma of the 3-D error
    smooth_fraction: float = 0.9  # share of the per-axis sigma that is time-correlated
    corr_time_s: float = 0.3  # correlation time of the smooth part
    rot_sigma_rad: float = 2e-5  # per axis, total

    @property
    def sigma_axis_mm(self) -> float:
        """Per-axis sigma: 2 sigma of the 3-D error (sqrt(3) sigma) is the stated precision."""
        return self.precision_mm / (2.0 * np.sqrt(3.0))

    @property
    def sigma_smooth_mm(self) -> float:
        """Per-axis sigma of the smooth (configuration-dependent) part."""
        return self.sigma_axis_mm * self.smooth_fraction

    @property
    def sigma_white_mm(self) -> float:
        """Per-axis sigma of the white (encoder jitter) part."""
        return self.sigma_axis_mm * np.sqrt(1.0 - self.smooth_fraction**2)

    @property
    def rot_sigma_smooth(self) -> float:
        """Per-axis rotation sigma of the smooth part, rad."""
        return self.rot_sigma_rad * self.smooth_fraction

    @property
    def rot_sigma_white(self) -> float:
        """Per-axis rotation sigma of the white part, rad."""
        return self.rot_sigma_rad * np.sqrt(1.0 - self.smooth_fraction**2)


@dataclass(frozen=True)
class ScanSpec:
    """One scan: the artefact on the table and how the arm sweeps the scanner over it."""

    name: str
    artefact: str  # gauge_block | plane | sphere | freeform | ball_bar (rig.yaml)
    params: dict = field(default_factory=dict)  # artefact geometry (mm) and albedos
    distance_mm: float = 140.0  # camera to the aim point along the optical axis
    tilt_deg: float = 0.0  # optical axis away from straight down
    tilt_azimuth_deg: float = 0.0  # direction of the tilt in the table plane
    heading_deg: float = 0.0  # image x axis direction on the table (the sweep direction)
    sweep_incline_deg: float = 0.0  # the sweep rises at this angle along its heading
    sweep_mm: float = 75.0  # length of the sweep
    sweep_offset_mm: tuple[float, float] = (0.0, 0.0)  # aim point shift: along, across sweep
    wobble_deg: float = 1.5  # slow hand rotation amplitude over the sweep
    frames: int = 300
    roll_deg: float = 0.0  # camera roll about its axis: the sweep runs at -roll in the image
    # frames of a quick capture over the whole sweep (None: the rig's quick_frames over the
    # sweep's middle at full speed, which would miss both balls of a ball bar)
    quick_frames: int | None = None


@dataclass(frozen=True)
class CalibrationSpec:
    """How many calibration views and at which distances (camera to board centre, mm)."""

    camera_views: int = 18
    laser_poses: int = 4
    handeye_views: int = 12
    depth_range_mm: tuple[float, float] = (130.0, 175.0)
    laser_depths_mm: tuple[float, ...] = (135.0, 148.0, 161.0, 174.0)
    handeye_distance_mm: float = 145.0
    max_tilt_deg: float = 40.0


@dataclass(frozen=True)
class RigPreset:
    """A complete virtual rig."""

    name: str
    description: str
    capture_date: str
    sensor: SensorSpec
    lasers: dict[str, LaserSpec]
    board: BoardSpec
    T_tool_cam: np.ndarray
    T_base_board: np.ndarray
    arm: ArmNoiseSpec
    scans: tuple[ScanSpec, ...]
    calibration: CalibrationSpec
    table_z_mm: float = 0.0
    table_albedo: float = 0.3
    ambient_board_e: float = 10500.0  # electrons on a white surface facing the light, board views
    ambient_scan_e: float = 450.0  # the same at scan exposure (faint room light)
    pattern: tuple[str, ...] = ("A", "B", "AB")
    quick_frames: int = 24
    quick_calibration: CalibrationSpec = CalibrationSpec(
        camera_views=8, laser_poses=3, handeye_views=8,
        laser_depths_mm=(136.0, 155.0, 172.0),
    )
    draw: dict | None = None  # a random rig's drawn quantities (crossline.sim.random_rig)


def _T(rotvec_deg=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    return make_transform(rotvec_to_matrix(np.radians(rotvec_deg)), np.asarray(t, dtype=np.float64))


def _board_on_table(x: float, y: float, yaw_deg: float, z_top: float) -> np.ndarray:
    """T_base_board of a board lying face up on the table (board z points down, into it)."""
    R = rotvec_to_matrix(np.radians([0.0, 0.0, yaw_deg])) @ rotvec_to_matrix(np.array([np.pi, 0, 0]))
    return make_transform(R, np.array([x, y, z_top]))


# ----------------------------------------------------------------------------- paper

_X_PAPER = np.array(
    [
        [-0.42684, 0.66270, -0.61532, 4.1373],
        [-0.904314, -0.3163, 0.286604, 21.393],
        [-0.004728, 0.678785, 0.73432, 112.962],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
_X_PAPER[:3, :3] = orthonormalize(_X_PAPER[:3, :3])

_PAPER_SCANS = (
    ScanSpec(
        "gauge", "gauge_block",
        params=dict(height=20.0, size=(35.0, 9.0), block_albedo=0.65, plate_albedo=0.5,
                    plate_size=(300.0, 200.0, 60.0), centre=(520.0, 40.0), yaw_deg=15.0,
                    plate_tilt_deg=(0.02, -0.015)),
        distance_mm=137.0, tilt_deg=6.0, tilt_azimuth_deg=100.0, heading_deg=15.0,
        sweep_mm=78.0, sweep_offset_mm=(0.0, 0.0),
    ),
    ScanSpec(
        "plate", "plane",
        params=dict(size=(200.0, 150.0, 8.0), albedo=0.85, centre=(480.0, -90.0), yaw_deg=-20.0,
                    tilt_deg=(1.2, -0.8)),
        distance_mm=146.0, tilt_deg=12.0, tilt_azimuth_deg=30.0, heading_deg=-25.0, sweep_mm=80.0,
    ),
    ScanSpec(
        "ball", "sphere",
        params=dict(diameter=25.0, centre=(560.0, -40.0), centre_height=30.0, stem_radius=5.0,
                    albedo=0.7, stem_albedo=0.4),
        distance_mm=136.0, tilt_deg=8.0, tilt_azimuth_deg=200.0, heading_deg=40.0, sweep_mm=70.0,
    ),
    ScanSpec(
        "part", "freeform",
        params=dict(semi_axes=(25.0, 20.0, 25.0), lean=0.08, centre=(600.0, 60.0), yaw_deg=25.0,
                    albedo=0.75),
        distance_mm=137.0, tilt_deg=20.0, tilt_azimuth_deg=-60.0, heading_deg=25.0, sweep_mm=82.0,
        sweep_offset_mm=(0.0, 3.0),
    ),
)

PAPER = RigPreset(
    name="paper",
    description=(
        "The paper's rig: 3072x2048 camera with its intrinsics and distortion, lasers A and B on "
        "its calibrated planes (405 nm), 15x11 circle grid of 3.75 mm, its hand-eye matrix X, "
        "an arm of 0.02 mm precision, 80 frames/s"
    ),
    capture_date="2024-05-14",
    sensor=SensorSpec(
        width=3072, height=2048,
        K=((5145.362, 0.0, 1517.375), (0.0, 5153.664, 1023.363), (0.0, 0.0, 1.0)),
        dist=(-0.09903, 0.195427, -0.000065974, -0.0000978477, 0.41673),
        scan_window=(207, 624, 2658, 800), frame_rate=80.0,
    ),
    lasers={
        "A": laser_from_abcd((-0.659905, -0.551732, 0.51, -68.7215)),
        "B": laser_from_abcd((0.76417, -0.543156, 0.34787, -49.616)),
    },
    board=BoardSpec(Board("symmetric", 15, 11, 3.75, 1.875, "dark")),
    T_tool_cam=_X_PAPER,
    T_base_board=_board_on_table(430.0, -150.0, 18.0, 4.0),
    arm=ArmNoiseSpec(),
    scans=_PAPER_SCANS,
    calibration=CalibrationSpec(),
)

# ----------------------------------------------------------------------------- compact

_COMPACT_SCANS = (
    ScanSpec(
        "gauge", "gauge_block",
        params=dict(height=20.0, size=(30.0, 9.0), block_albedo=0.6, plate_albedo=0.45,
                    plate_size=(250.0, 200.0, 50.0), centre=(-380.0, 250.0), yaw_deg=-30.0,
                    plate_tilt_deg=(-0.01, 0.03)),
        distance_mm=92.0, tilt_deg=8.0, tilt_azimuth_deg=10.0, heading_deg=-30.0, sweep_mm=62.0,
        frames=300,
    ),
    ScanSpec(
        "plate", "plane",
        params=dict(size=(180.0, 140.0, 6.0), albedo=0.8, centre=(-300.0, 330.0), yaw_deg=10.0,
                    tilt_deg=(-0.6, 1.5)),
        distance_mm=100.0, tilt_deg=15.0, tilt_azimuth_deg=-120.0, heading_deg=70.0, sweep_mm=60.0,
        frames=300,
    ),
    ScanSpec(
        "ball", "sphere",
        params=dict(diameter=25.0, centre=(-420.0, 380.0), centre_height=25.0, stem_radius=4.0,
                    albedo=0.65, stem_albedo=0.35),
        distance_mm=92.0, tilt_deg=10.0, tilt_azimuth_deg=45.0, heading_deg=-10.0, sweep_mm=55.0,
        frames=300,
    ),
    ScanSpec(
        "part", "freeform",
        params=dict(semi_axes=(24.0, 19.0, 22.0), lean=-0.06, centre=(-350.0, 450.0), yaw_deg=-40.0,
                    albedo=0.7),
        distance_mm=92.0, tilt_deg=22.0, tilt_azimuth_deg=150.0, heading_deg=-40.0, sweep_mm=66.0,
        frames=300,
    ),
)

COMPACT = RigPreset(
    name="compact",
    description=(
        "A compact rig unlike the paper's: 2448x2048 camera with a short lens (fx ~3500 px), "
        "strong barrel distortion and an off-centre principal point, 450 nm lasers crossing at "
        "~100 mm, an asymmetric grid of light circles on a dark board, another hand-eye matrix, "
        "a 0.03 mm arm, 100 frames/s"
    ),
    capture_date="2024-09-02",
    sensor=SensorSpec(
        width=2448, height=2048,
        K=((3498.5, 0.0, 1262.3), (0.0, 3501.2, 1008.7), (0.0, 0.0, 1.0)),
        dist=(-0.2134, 0.1387, 0.00041, -0.00032, -0.0472),
        scan_window=(124, 640, 2200, 720), frame_rate=100.0,
        full_well_e=6500.0, read_noise_e=4.0, black_level_dn=6.0, prnu=0.006, psf_sigma_px=0.7,
        pixel_pitch_um=3.45, f_number=5.6,
    ),
    lasers={
        "A": laser_through((-52.0, 18.0, 2.0), (0.0, 0.0, 100.0), (0.5, 0.866, 0.0),
                           wavelength_nm=450.0, waist_mm=0.06, m2=1.3, fan_half_angle_deg=35.0,
                           peak_electrons=7400.0, speckle_contrast=0.2, speckle_grain_px=0.5),
        # B's emitter sits across its own line from the camera (as A's does), so both planes
        # meet the viewing rays at ~25-29 degrees (a usable triangulation angle) and cross at 90
        "B": laser_through((26.0, 45.0, 2.0), (2.0, 0.0, 104.0), (0.7071, -0.7071, 0.0),
                           wavelength_nm=450.0, waist_mm=0.06, m2=1.3, fan_half_angle_deg=35.0,
                           peak_electrons=7400.0, speckle_contrast=0.2, speckle_grain_px=0.5),
    },
    board=BoardSpec(
        Board("asymmetric", 7, 13, 2.5, 1.5, "light"),
        light_albedo=0.85, dark_albedo=0.1, margin_mm=3.0, thickness_mm=3.0,
        background_albedo=0.45,
    ),
    T_tool_cam=_T((25.0, -40.0, 150.0), (-28.0, 42.0, 78.0)),
    T_base_board=_board_on_table(-320.0, 220.0, -35.0, -2.0),
    arm=ArmNoiseSpec(precision_mm=0.03, smooth_fraction=0.85, corr_time_s=0.5, rot_sigma_rad=3e-5),
    scans=_COMPACT_SCANS,
    calibration=CalibrationSpec(
        # 24 hand-eye views, not 10: its arm is 0.03 mm, and X averages over the views
        camera_views=16, laser_poses=3, handeye_views=24, depth_range_mm=(85.0, 118.0),
        laser_depths_mm=(86.0, 100.0, 114.0), handeye_distance_mm=100.0,
    ),
    table_z_mm=-5.0,
    table_albedo=0.35,
    ambient_board_e=5600.0,
    ambient_scan_e=380.0,
    quick_calibration=CalibrationSpec(
        camera_views=8, laser_poses=3, handeye_views=8, depth_range_mm=(85.0, 118.0),
        laser_depths_mm=(86.0, 100.0, 114.0), handeye_distance_mm=100.0,
    ),
)

PRESETS: dict[str, RigPreset] = {"paper": PAPER, "compact": COMPACT}


# ----------------------------------------------------------------------------- ball bar

BAR_TURNS_DEG = (0.0, 60.0, 120.0)  # the bar's three yaws, from the ball scan's heading
BAR_INCLINES_DEG = (0.0, 0.0, 15.0)  # and inclinations (the first ball the lower)


def _bar_length(diameter: float) -> float:
    """A ball bar's calibrated centre distance for balls of ``diameter``: a nominal of about
    2.2 diameters in steps of 5 mm (1 mm if that leaves 2-2.4 diameters), off it by a few
    micrometres as its certificate states (fixed per diameter: one bar per ball size)."""
    nominal = 5.0 * round(2.2 * diameter / 5.0)
    if not 2.0 * diameter <= nominal <= 2.4 * diameter:
        nominal = float(round(2.2 * diameter))
    off_um = zlib.crc32(f"ball bar {diameter:.4f}".encode()) % 161 / 10.0 - 8.0  # -8..+8 um
    return round(nominal + off_um * 1e-3, 4)


def ball_bar_scans(rig: RigPreset) -> tuple[ScanSpec, ...]:
    """Three scans of a ball bar (ISO 10360-8 sphere-spacing error), from the rig's ball scan.

    Two balls of the ball scan's diameter, stems and albedos, each on its own vertical stem,
    centres a calibrated length L apart (``_bar_length``), the bar's middle over the ball's
    place on the table: level along the ball scan's heading, turned by 60 deg, and turned by
    120 deg and inclined by 15 deg (its lower ball at the ball's height). Each sweep runs
    along the bar (heading = the bar's yaw, the camera rolled as for the ball, so the stripes
    cross the bar as they cross the ball; rising with an inclined bar, as a hand-guided arm
    follows it, so that both balls stay in the measuring range) over L + 1.6 D, at the ball
    scan's distance and tilt (its azimuth fixed on the table: the bar's turns change the view
    of it); a quick capture sweeps all of it, in as many frames per ball diameter of sweep as
    the quick ball scan has.
    """
    ball = next((sp for sp in rig.scans if sp.artefact == "sphere"), None)
    if ball is None:
        raise ValueError(f"rig {rig.name} has no sphere scan to take the ball bar's balls from")
    p = ball.params
    D = float(p["diameter"])
    L = _bar_length(D)
    sweep = round(L + 1.6 * D, 2)
    quick = math.ceil(rig.quick_frames * sweep / D)
    out = []
    for k, (turn, incline) in enumerate(zip(BAR_TURNS_DEG, BAR_INCLINES_DEG, strict=True)):
        yaw = round((ball.heading_deg + turn + 180.0) % 360.0 - 180.0, 2)
        params = dict(diameter=D, length=L, centre=tuple(p["centre"]), yaw_deg=yaw,
                      incline_deg=incline, centre_height=p["centre_height"],
                      stem_radius=p["stem_radius"], albedo=p["albedo"], stem_albedo=p["stem_albedo"])
        out.append(replace(
            ball, name=f"bar_{k + 1}", artefact="ball_bar", params=params, heading_deg=yaw,
            sweep_incline_deg=incline, sweep_mm=sweep, sweep_offset_mm=(0.0, 0.0), quick_frames=quick))
    return tuple(out)

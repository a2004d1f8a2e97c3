"""Laser-plane calibration: stripe points on the board plane, robust plane fit, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crossline.board import Board
from crossline.calibrate.lasers import ambient_model, edge_clearance, robust_plane, stripe_points
from crossline.calibrate.synthetic import look_at, render_view, sample_rays
from crossline.camera import Camera
from crossline.errors import CalibrationError
from crossline.geometry import angle_between, invert_transform
from crossline.io.images import read_image

CAM = Camera(np.array([[2400.0, 0, 512.0], [0, 2400.0, 384.0], [0, 0, 1]]),
             np.array([-0.1, 0.15, 2e-4, -1e-4, 0.0]), (1024, 768))
BOARD = Board("symmetric", 9, 7, 4.0, 2.0, "dark")
# a plane crossing the optical axis at ~120 mm, tilted like the paper's laser A
N_TRUE = np.array([-0.66, -0.55, 0.51]) / np.linalg.norm([-0.66, -0.55, 0.51])
D_TRUE = -float(N_TRUE @ np.array([0.0, 0.0, 120.0]))


@pytest.fixture(scope="module")
def rays() -> np.ndarray:
    """Sub-pixel rays of CAM, computed once."""
    return sample_rays(CAM, 3)


def _pose(distance: float, tilt_deg: float, az: float) -> np.ndarray:
    ex, ey = BOARD.extent()
    c = np.array([ex / 2, ey / 2, 0.0])
    t = np.radians(tilt_deg)
    eye = c + distance * np.array([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), -np.cos(t)])
    return invert_transform(look_at(eye, c))


def _pair(T: np.ndarray, rays: np.ndarray, seed: int, laser: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Lasers-off image (board exposure) and laser image (10x shorter exposure, stripe on)."""
    rng = np.random.default_rng(seed)
    board = render_view(CAM, BOARD, T, rays=rays, light=200, dark=25, table=60, noise=1.0, rng=rng)
    kw = dict(laser_plane=(N_TRUE, D_TRUE), laser_sigma_mm=0.05, laser_peak=170.0) if laser else {}
    on = render_view(CAM, BOARD, T, rays=rays, light=20, dark=2.5, table=6, ambient=3.0, noise=1.0,
                     rng=rng, **kw)
    return board, on


@pytest.mark.slow
def test_plane_from_rendered_poses(rays: np.ndarray) -> None:
    """Three board poses: stripe points on the true plane; the fitted plane matches it.

    The stripe crosses dark circles; centres are kept only clear of circle rims.
    """
    pts, classes = [], []
    for k, (z, tilt, az) in enumerate([(105.0, 15.0, 0.3), (120.0, 25.0, 2.0), (135.0, 10.0, 4.0)]):
        b, on = _pair(_pose(z, tilt, az), rays, k)
        s = stripe_points(CAM, BOARD, b, on, name=f"laser_A/pose_{k:02d}_laser.png")
        r = s.points @ N_TRUE + D_TRUE
        assert len(s.points) > 100
        assert np.sqrt(np.mean(r**2)) < 0.003  # mm; a pixel is ~0.05 mm here
        assert abs(np.mean(r)) < 0.001
        pts.append(s.points)
        classes.append(2 * k + s.on_other)
    # as the stage fits: each pose and albedo class with its own noise (the centres inside
    # the dark circles, where the stripe is 8x weaker against the same additive noise)
    n, d, inliers = robust_plane(np.concatenate(pts), groups=np.concatenate(classes) // 2,
                                 noise_groups=np.concatenate(classes))
    if n @ N_TRUE < 0:
        n, d = -n, -d
    assert np.degrees(angle_between(n, N_TRUE)) < 0.005
    assert abs(d - D_TRUE) < 0.002
    assert inliers.mean() > 0.95


@pytest.mark.slow
def test_light_circles_on_a_dark_board(tmp_path) -> None:
    """The paper rig rendered with light circles on a dark board (its table is lit brighter than
    the board's plate, and the saturated rims ring in the laser-minus-board difference): the
    stripe is measured on the plate, on the true plane. Both once lost it under a threshold set
    by the stripe on the table or by the rings ("no laser stripe on the board")."""
    import json

    from tests.conftest import render_cached

    cap = render_cached("paper", seed=0, board=Board.parse("symmetric:15x11:3.75:1.875:light"),
                        scans=["plate"], frames=1)
    truth = json.loads((cap / "truth.json").read_text())
    cam = Camera(np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"]),
                 tuple(truth["camera"]["image_size"]))
    board = Board.parse("symmetric:15x11:3.75:1.875:light")
    for laser in ("A", "B"):
        n_t, d_t = np.array(truth["lasers"][laser]["normal"]), truth["lasers"][laser]["d"]
        for off in sorted((cap / "calibration" / f"laser_{laser}").glob("*_board.png")):
            on = off.with_name(off.name.replace("_board", "_laser"))
            s = stripe_points(cam, board, read_image(off), read_image(on), name=on.name)
            r = s.points @ n_t + d_t
            near = np.abs(r) < 0.02  # a few centres on remnants of the rings: the robust fit's job
            assert len(s.points) > 300 and near.mean() > 0.99
            assert np.sqrt(np.mean(r[near] ** 2)) < 0.005 and abs(np.mean(r[near])) < 0.001


def test_no_stripe_on_the_board_names_the_file(rays: np.ndarray) -> None:
    """A laser image without a stripe is an error that names the laser image."""
    b, off = _pair(_pose(110.0, 15.0, 0.5), rays, 3, laser=False)
    with pytest.raises(CalibrationError) as exc:
        stripe_points(CAM, BOARD, b, off, name="calibration/laser_B/pose_01_laser.png")
    assert str(exc.value).startswith("calibration/laser_B/pose_01_laser.png: no laser stripe on the board")


def test_stripe_beside_the_board_is_no_stripe_on_the_board(rays: np.ndarray) -> None:
    """A stripe that misses the board (on the table only) is the same named error."""
    T = _pose(150.0, 0.0, 0.0)
    b = render_view(CAM, BOARD, T, rays=rays, noise=1.0)
    # a plane parallel to the optical axis at x = -28 mm: the image's left edge, the table
    n = np.array([1.0, 0.0, 0.0])
    on = render_view(CAM, BOARD, T, rays=rays, light=20, dark=2.5, table=20, noise=1.0,
                     laser_plane=(n, 28.0), laser_sigma_mm=0.05, laser_peak=170.0)
    assert (on.astype(int) - b // 10).max() > 100  # the stripe is in the image
    off_plate = r"^x\.png: no laser stripe on the board: the stripe .* lies off the board's plate"
    with pytest.raises(CalibrationError, match=off_plate):
        stripe_points(CAM, BOARD, b, on, name="x.png")


def test_board_not_found_in_the_lasers_off_image() -> None:
    """No board in the lasers-off image: the error names the file and says why."""
    blank = np.full((768, 1024), 100, np.uint8)
    with pytest.raises(CalibrationError, match=r"^p\.png: board not found: .* lasers-off image"):
        stripe_points(CAM, BOARD, blank, blank, name="p.png")


def test_edge_clearance() -> None:
    """Distance to the nearest albedo edge: circle rims, square edges, off the board < 0."""
    b = Board("symmetric", 5, 4, 4.0, 2.0)
    xy = np.array([[0.0, 0.0], [2.0, 0.0], [1.0, 0.0], [2.0, 2.0], [-3.0, 0.0], [8.0, 6.5]])
    c = edge_clearance(b, xy)
    assert np.allclose(c[:4], [1.0, 1.0, 0.0, np.hypot(2, 2) - 1.0])
    assert c[4] < 0  # beyond the board's margin (one diameter past the outer centres)
    assert np.isclose(c[5], min(abs(np.hypot(0.0, 1.5) - 1.0), abs(np.hypot(0.0, 2.5) - 1.0)))
    a = Board("asymmetric", 3, 4, 4.0, 3.0)
    # asymmetric layout: circle (r=1, c=0) is at (4, 4)
    assert np.isclose(edge_clearance(a, np.array([[4.0, 4.0]]))[0], 1.5)
    ch = Board("chessboard", 4, 3, 5.0)
    assert np.allclose(edge_clearance(ch, np.array([[2.5, 2.5], [1.0, 2.5], [-4.0, 7.5]])), [2.5, 1.0, 1.0])


def test_robust_plane_ignores_outliers() -> None:
    """Exact plane through 90 % inliers with 10 % gross outliers; trimmed fit is exact."""
    rng = np.random.default_rng(0)
    u = rng.uniform(-20, 20, (500, 2))
    e1 = np.cross(N_TRUE, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(N_TRUE, e1)
    p = -D_TRUE * N_TRUE + u[:, :1] * e1 + u[:, 1:] * e2
    noisy = p + rng.normal(0, 0.002, (500, 1)) * N_TRUE
    noisy[:50] += rng.uniform(0.5, 3.0, (50, 1)) * N_TRUE
    n, d, inl = robust_plane(noisy)
    if n @ N_TRUE < 0:
        n, d = -n, -d
    assert not inl[:50].any() and inl[50:].mean() > 0.97
    assert np.degrees(angle_between(n, N_TRUE)) < 0.003
    assert abs(d - D_TRUE) < 0.001
    n, d, inl = robust_plane(p)
    assert abs(abs(n @ N_TRUE) - 1) < 1e-12 and inl.all()


def test_ambient_model() -> None:
    """laser = a board + b is recovered despite a bright stripe."""
    rng = np.random.default_rng(1)
    board = rng.integers(20, 220, (200, 300)).astype(np.uint8)
    laser = 0.1 * board.astype(float) + 3.0 + rng.normal(0, 0.3, board.shape)
    laser[100:104] = 250
    a, b = ambient_model(board, np.clip(np.round(laser), 0, 255).astype(np.uint8))
    assert abs(a - 0.1) < 0.002 and abs(b - 3.0) < 0.2


def test_robust_plane_is_not_taken_by_the_largest_pose() -> None:
    """Each pose's stripe is a line that its own board plane holds exactly: with one pose
    holding most points, the fit must still be the laser plane through all the lines."""
    rng = np.random.default_rng(3)
    n = np.array([0.1, -0.7, 0.7]) / np.linalg.norm([0.1, -0.7, 0.7])
    d = -50.0
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    lines, groups = [], []
    for k, (m, ang) in enumerate([(3000, 0.0), (700, 1.0), (600, 2.1)]):
        direction = np.cos(ang) * u + np.sin(ang) * v  # a line in the laser plane
        t = rng.uniform(-15, 15, m)
        q = -d * n + np.outer(t, direction) + 3.0 * k * np.cross(n, direction)
        # the centres' noise moves them within their board's plane (tilted 40 deg from the
        # laser plane about the line), which therefore holds them exactly
        b = np.cos(0.7) * n + np.sin(0.7) * np.cross(n, direction)
        w = np.cross(b, direction)
        lines.append(q + np.outer(rng.normal(scale=0.003, size=m), w))
        groups.append(np.full(m, k))
    pts, grp = np.concatenate(lines), np.concatenate(groups)
    nf, df, inl = robust_plane(pts, groups=grp)
    if nf @ n < 0:
        nf, df = -nf, -df
    assert np.degrees(angle_between(nf, n)) < 0.01 and abs(df - d) < 0.005
    assert inl.mean() > 0.95


# ----------------------------------------------------------------------------- one or two lasers, any board


def test_laser_planes_one_or_two(tmp_path) -> None:
    """lasers.json holds one plane (a one-line rig: no angle, no crossing line) or two (with
    both); two parallel planes are written without a line instead of failing."""
    from crossline.laser import LaserPlane, LaserPlanes

    a = LaserPlane(N_TRUE, D_TRUE)
    one = LaserPlanes(a)
    one.save(tmp_path / "one.json")
    back = LaserPlanes.load(tmp_path / "one.json")
    data = json.loads((tmp_path / "one.json").read_text())
    assert back.names == ("A",) and "B" not in data and "intersection_line" not in data
    assert np.allclose(back["A"].normal, N_TRUE) and "B" not in back
    with pytest.raises(KeyError, match="has \\['A'\\]"):
        back["B"]
    with pytest.raises(ValueError, match="one laser plane"):
        one.intersection_line()
    b = LaserPlane(np.array([0.6, -0.3, 0.74]), -80.0)
    two = LaserPlanes(a, b)
    d2 = two.to_dict()
    assert d2["angle_AB_deg"] == pytest.approx(np.degrees(angle_between(a.normal, b.normal)))
    p, u = (np.array(d2["intersection_line"][k]) for k in ("point", "direction"))
    assert abs(a.distance(p[None])[0]) < 1e-9 and abs(b.distance((p + 10 * u)[None])[0]) < 1e-9
    par = LaserPlanes(a, LaserPlane(N_TRUE, D_TRUE + 5.0)).to_dict()
    assert par["angle_AB_deg"] == pytest.approx(0.0, abs=1e-6) and "intersection_line" not in par


def _true_camera(cap, tmp_path):
    truth = json.loads((cap / "truth.json").read_text())
    cam = Camera(np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"]),
                 tuple(truth["camera"]["image_size"]))
    cam.save(tmp_path / "camera.json")
    return truth, tmp_path / "camera.json"


def _score(planes, truth) -> None:
    for laser in planes.names:
        n_t, d_t = np.array(truth["lasers"][laser]["normal"]), truth["lasers"][laser]["d"]
        n, d = planes[laser].normal, planes[laser].d
        if n @ n_t < 0:
            n, d = -n, -d
        assert np.degrees(angle_between(n, n_t)) < 0.005, laser
        assert abs(d - d_t) < 0.01, laser


@pytest.mark.slow
def test_small_chessboard_squares_with_the_albedo_taken_out(rays: np.ndarray) -> None:
    """A chessboard whose squares (30 px) are hardly wider than the stripe's window, and a
    sensor black level in both images: the albedo gain finds the black level and the albedo
    ratio from the stripe, and centres whose windows cross square edges land on the true plane.
    Without the gain a window must fit inside one square, which leaves few centres or none."""
    board = Board("chessboard", 17, 13, 1.5)
    black, light, dark = 12.0, 200.0, 25.0
    pts, classes, n_plain = [], [], 0
    for k, (z, tilt, az) in enumerate([(105.0, 15.0, 0.3), (120.0, 25.0, 2.0), (135.0, 10.0, 4.0)]):
        ex, ey = board.extent()
        c = np.array([ex / 2, ey / 2, 0.0])
        t = np.radians(tilt)
        eye = c + z * np.array([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), -np.cos(t)])
        T = invert_transform(look_at(eye, c))
        rng = np.random.default_rng(k)
        off = render_view(CAM, board, T, rays=rays, light=light, dark=dark, table=60,
                          ambient=black, noise=1.0, rng=rng)
        on = render_view(CAM, board, T, rays=rays, light=light / 10, dark=dark / 10, table=6,
                         ambient=black, noise=1.0, rng=rng, laser_plane=(N_TRUE, D_TRUE),
                         laser_sigma_mm=0.15, laser_peak=170.0)
        s = stripe_points(CAM, board, off, on, name=f"pose_{k:02d}")
        assert s.albedo is not None
        assert abs(s.albedo["black_level"] - black) < 3.0, s.albedo
        assert s.albedo["ratio"] == pytest.approx(dark / light, rel=0.15)
        r = s.points @ N_TRUE + D_TRUE
        assert len(s.points) > 50
        # scatter: noise on the dark squares, where the stripe peaks at ~21 counts against 1.4
        # counts of noise in the difference over a 3.5 px sigma profile, ~0.08 px or ~4 um per
        # centre (a pixel is ~0.05 mm here); no bias beyond 1 um
        assert np.sqrt(np.mean(r**2)) < 0.008 and abs(np.mean(r)) < 0.001
        pts.append(s.points)
        classes.append(2 * k + s.on_other)
        try:
            n_plain += len(stripe_points(CAM, board, off, on, normalise_albedo=False).points)
        except CalibrationError:
            pass
    assert n_plain < sum(map(len, pts)) / 3
    P = np.concatenate(pts)
    n, d, _ = robust_plane(P, groups=np.concatenate(classes) // 2,
                           noise_groups=np.concatenate(classes))
    # the fitted plane against the true one where the board was (three short segments on a
    # 25 mm board: the angle alone would overstate what a measurement there feels)
    on_true = P - (P @ N_TRUE + D_TRUE)[:, None] * N_TRUE
    gap = on_true @ n + d
    print("plane: angle", np.degrees(angle_between(n, N_TRUE)), "gap max", np.abs(gap).max())
    assert np.abs(gap).max() < 0.003


@pytest.mark.slow
def test_chessboard_poses_of_a_drawn_rig(tmp_path) -> None:
    """Random rig 4's chessboard (dark squares at 7 % of the light ones): every laser pose is
    used, the stripe crosses the squares (the simulated user turns the board so that it does
    not run along a row or a diagonal), and no centre comes from the dark squares' noise that
    the albedo gain lifts with the stripe (before: 74 % of one pose's points 1-12 mm off)."""
    from crossline.calibrate.lasers import run_calibrate_lasers
    from crossline.io.capture import open_capture
    from crossline.laser import LaserPlanes
    from crossline.sim import simulate

    cap = simulate(tmp_path / "cap", "random-small", seed=4, quick=True, calibration_only=True,
                   progress=False)
    truth, cam_json = _true_camera(cap, tmp_path)
    cam = Camera.load(cam_json)
    c = open_capture(cap)
    assert c.rig.board.pattern == "chessboard"
    for laser in ("A", "B"):
        n_t, d_t = np.array(truth["lasers"][laser]["normal"]), truth["lasers"][laser]["d"]
        for v in c.laser_views[laser]:
            s = stripe_points(cam, c.rig.board, read_image(v.board_image), read_image(v.laser_image),
                              name=v.pose)
            assert np.abs(s.points @ n_t + d_t).max() < 0.1, (laser, v.pose)
    run_calibrate_lasers(cap, cam_json, tmp_path / "lasers.json")
    planes = LaserPlanes.load(tmp_path / "lasers.json")
    for laser in ("A", "B"):
        assert planes[laser].extra["skipped_poses"] == []
        assert planes[laser].extra["rms_mm"] < 0.03


def test_stripe_cut_into_pieces_by_dark_circles_is_removed_whole() -> None:
    """Laser always on: a stripe dimmed to nothing on each dark circle it crosses is pieces
    shorter than a stripe must be (a tenth of the image's short side), each on one line; the
    pieces are joined and the stripe removed everywhere, the circles left alone."""
    from crossline.calibrate.lasers import remove_stripe

    h, w = 600, 900
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    albedo = np.full((h, w), 0.8)
    circles = np.zeros((h, w), bool)
    for cu in range(60, w, 90):  # a row of dark circles 40 px across, 50 px of plate between
        for cv_ in (150, 300, 450):
            circles |= (u - cu) ** 2 + (v - cv_) ** 2 < 20**2
    albedo[circles] = 0.04
    # the stripe runs along the row of circles at v = 300, turned 2 degrees
    dist = (v - 300 - np.tan(np.radians(2)) * (u - w / 2)) * np.cos(np.radians(2))
    stripe = 200.0 * np.exp(-0.5 * (dist / 2.0) ** 2)
    rng = np.random.default_rng(3)
    img = np.clip(albedo * (60 + stripe) + rng.normal(0, 1.0, (h, w)), 0, 255).round().astype(np.uint8)
    out, mask = remove_stripe(img)
    on_plate = (np.abs(dist) < 2) & ~circles & (u > 20) & (u < w - 20)
    assert mask[on_plate].mean() > 0.99
    # what is left where the stripe was is the plate, not the stripe
    assert np.median(out[on_plate].astype(float)) < 0.8 * 60 + 6
    assert not mask[np.abs(dist) > 20].any()


def test_chessboard_corners_are_not_taken_for_stripe_pieces() -> None:
    """Laser always on, a chessboard: the opening leaves X-shaped residues at every corner,
    which line up along the board's rows like the pieces of a cut stripe; only the stripe (a
    segment, long for its width) is removed, the corners away from it are left alone (before,
    every corner in line was masked and the board could not be found)."""
    from crossline.calibrate.lasers import remove_stripe

    h, w = 600, 900
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    sq = 32  # squares a little wider than the opening's disc (17 px at 900 px)
    board = ((u // sq + v // sq) % 2 == 0) & (u >= 128) & (u < 768) & (v >= 96) & (v < 480)
    albedo = np.where(board, 0.85, 0.08)
    albedo[(u < 128) | (u >= 768) | (v < 96) | (v >= 480)] = 0.3
    dist = (v - 290 - np.tan(np.radians(8)) * (u - w / 2)) * np.cos(np.radians(8))
    stripe = 300.0 * np.exp(-0.5 * (dist / 2.5) ** 2)
    rng = np.random.default_rng(5)
    img = np.clip(albedo * (120 + stripe) + rng.normal(0, 1.0, (h, w)), 0, 255).round().astype(np.uint8)
    _, mask = remove_stripe(img)
    lit = (np.abs(dist) < 2) & (albedo > 0.5)
    assert mask[lit].mean() > 0.95
    # the corners 40 px or more from the stripe: none masked
    cu, cv_ = np.meshgrid(np.arange(128 + sq, 768, sq), np.arange(96 + sq, 480, sq))
    far = np.abs((cv_ - 290 - np.tan(np.radians(8)) * (cu - w / 2)) * np.cos(np.radians(8))) > 40
    assert far.sum() > 100
    win = [mask[y - 3:y + 4, x - 3:x + 4].any() for x, y in zip(cu[far], cv_[far], strict=True)]
    assert not any(win), f"{sum(win)} corners away from the stripe masked"

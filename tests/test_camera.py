"""Camera model and geometry helpers against OpenCV and independent computation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from crossline.camera import Camera
from crossline.geometry import (
    fit_plane,
    fit_sphere,
    invert_transform,
    make_transform,
    matrix_to_quat,
    plane_line_intersection,
    quat_to_matrix,
    rotation_angle,
    rotvec_to_matrix,
    transform_from_pose,
    transform_points,
    transform_to_pose,
)
from crossline.laser import LaserPlane, LaserPlanes

K = np.array([[5145.362, 0, 1517.375], [0, 5153.664, 1023.363], [0, 0, 1]])
DIST = np.array([-0.09903, 0.195427, -0.000065974, -0.0000978477, 0.41673])
CAM = Camera(K, DIST, (3072, 2048))


def test_project_matches_opencv() -> None:
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-40, 40, (500, 2)), rng.uniform(110, 190, 500)]
    uv_cv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), K, DIST)
    np.testing.assert_allclose(CAM.project(p), uv_cv[:, 0], atol=1e-9)


@pytest.mark.parametrize(
    "dist", [DIST, np.array([-0.35, 0.12, 1e-3, -8e-4, -0.02]), np.zeros(5)], ids=["paper", "barrel", "none"]
)
def test_undistort_inverts_distortion_over_the_sensor(dist) -> None:
    cam = Camera(K, dist, (3072, 2048))
    u, v = np.meshgrid(np.linspace(0, 3071, 97), np.linspace(0, 2047, 65))
    uv = np.c_[u.ravel(), v.ravel()]
    xy = cam.undistort(uv)
    back = cam.project(np.c_[xy, np.ones(len(xy))])
    assert np.abs(back - uv).max() < 1e-9  # px; the requirement is well under 1e-3 px


def test_undistort_agrees_with_opencv_iterative() -> None:
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [3072, 2048], (200, 2))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPointsIter(uv[:, None], K, DIST, None, None, crit)[:, 0]
    np.testing.assert_allclose(CAM.undistort(uv), ref, atol=1e-9)


def test_rays_are_unit_and_reproject() -> None:
    uv = np.array([[0.0, 0.0], [1517.375, 1023.363], [3071.0, 2047.0]])
    r = CAM.rays(uv)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(CAM.project(r * 150.0), uv, atol=1e-9)
    np.testing.assert_allclose(r[1], [0, 0, 1], atol=1e-15)


def test_camera_json_roundtrip(tmp_path) -> None:
    cam = Camera(K, DIST, (3072, 2048), {"rms_px": 0.1})
    cam.save(tmp_path / "camera.json")
    back = Camera.load(tmp_path / "camera.json")
    np.testing.assert_array_equal(back.K, K)
    np.testing.assert_array_equal(back.dist, DIST)
    assert back.image_size == (3072, 2048) and back.extra["rms_px"] == 0.1
    (tmp_path / "bad.json").write_text('{"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}')
    msg = r"bad.json: not a camera model: .*lacks key\(s\) \['dist', 'image_size'\]"
    with pytest.raises(ValueError, match=msg):
        Camera.load(tmp_path / "bad.json")


def test_transforms_and_quaternions() -> None:
    rng = np.random.default_rng(2)
    rv = rng.normal(size=(50, 3))
    R = rotvec_to_matrix(rv)
    q = matrix_to_quat(R)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-14)
    small = np.linalg.norm(rv, axis=1) < np.pi
    np.testing.assert_allclose(rotation_angle(R[small]), np.linalg.norm(rv[small], axis=1), atol=1e-12)
    T = make_transform(R, rng.normal(size=(50, 3)) * 100)
    np.testing.assert_allclose(invert_transform(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    xyz, quat = transform_to_pose(T)
    np.testing.assert_allclose(transform_from_pose(xyz, quat), T, atol=1e-12)
    p = rng.normal(size=(50, 3))
    np.testing.assert_allclose(transform_points(T, p), np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3])
    # quaternion convention: qw first; a 90 deg turn about z maps x to y
    Rz = quat_to_matrix(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))
    np.testing.assert_allclose(Rz @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_rotation_angle_small_is_precise() -> None:
    assert rotation_angle(rotvec_to_matrix([1e-9, 0, 0])) == pytest.approx(1e-9, rel=1e-6)


def test_plane_and_sphere_fits() -> None:
    rng = np.random.default_rng(3)
    n = np.array([0.3, -0.2, 0.93])
    n /= np.linalg.norm(n)
    a = np.cross(n, [1, 0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    p = 40 * rng.normal(size=(300, 1)) * a + 40 * rng.normal(size=(300, 1)) * b - 120 * n
    nf, d = fit_plane(p)
    assert abs(abs(nf @ n) - 1) < 1e-14 and d == pytest.approx(-120, abs=1e-10)
    s = rng.normal(size=(400, 3))
    s = s / np.linalg.norm(s, axis=1, keepdims=True)
    pts = s[s[:, 2] > -0.3] * 12.5 + [10, -4, 150]  # a cap, as a scanner sees a ball
    c, r, res = fit_sphere(pts + rng.normal(scale=0.002, size=pts.shape))
    assert np.linalg.norm(c - [10, -4, 150]) < 1e-3 and abs(r - 12.5) < 1e-3
    assert np.std(res) == pytest.approx(0.002, rel=0.2)


def test_laser_planes_normalise_and_meet() -> None:
    A = LaserPlane([-0.659905, -0.551732, 0.51], -68.7215)
    B = LaserPlane([0.76417, -0.543156, 0.34787], -49.616)
    assert np.linalg.norm(A.normal) == pytest.approx(1, abs=1e-15)
    planes = LaserPlanes(A, B)
    assert planes.angle_deg() == pytest.approx(91.558, abs=1e-3)
    p, u = planes.intersection_line()
    for t in (-50, 0, 80):
        assert abs(A.distance(p + t * u)) < 1e-12 and abs(B.distance(p + t * u)) < 1e-12
    with pytest.raises(ValueError, match="parallel"):
        plane_line_intersection(A.normal, A.d, A.normal, A.d + 1)
    r = CAM.rays(np.array([[1000.0, 900.0]]))
    assert abs(A.distance(A.intersect_rays(r))[0]) < 1e-12

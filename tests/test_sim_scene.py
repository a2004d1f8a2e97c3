"""The analytic scenes: exact hits, shadows, plane sections, and the freeform's truth mesh."""

from __future__ import annotations

import numpy as np
import pytest

from crossline.geometry import invert_transform
from crossline.sim import arm
from crossline.sim.part import part_mesh, write_ply
from crossline.sim.presets import PRESETS
from crossline.sim.render import RigModel, stripe_truth
from crossline.sim.scene import Box, Cylinder, FreeformPart, HalfSpace, Scene, Sphere
from crossline.sim.scenes import freeform_part, scan_scene


def _rays(n, seed=0, spread=0.25):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-spread, spread, n), rng.uniform(-spread, spread, n),
                            np.ones(n)])


def _brute_first_hit(prim, d, t_max=400.0, steps=40001):
    """First t along each ray where the point enters the solid (dense march, for comparison)."""
    ts = np.linspace(1.0, t_max, steps)
    first = np.full(len(d), np.inf)
    for k in range(0, steps, 2000):
        T = ts[k : k + 2000]
        P = (d[:, None, :] * T[None, :, None]).reshape(-1, 3)
        ins = prim.inside(P, tol=0.0).reshape(len(d), -1)
        hit = ins.any(1) & ~np.isfinite(first)
        first[hit] = T[np.argmax(ins[hit], axis=1)]
    return first


@pytest.mark.parametrize(
    "prim",
    [
        Box(np.array([3.0, -2.0, 150.0]), np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
            * np.array([1, 1, 1]), np.array([20.0, 9.0, 10.0])),
        Sphere(np.array([5.0, 4.0, 140.0]), 12.5),
        # long and across the view: its caps (always buried in a scene) stay out of sight
        Cylinder(np.array([-120.0, 10.0, 170.0]), np.array([0.98, 0.0, 0.2]) / np.hypot(0.98, 0.2),
                 5.0, 240.0),
        FreeformPart(np.array([0.0, 0.0, 160.0]), np.diag([1 / 25, -1 / 20, -1 / 25])),
        HalfSpace(np.array([0.0, 0.0, 180.0]), np.array([0.1, 0.0, -1.0]) / np.hypot(0.1, 1.0)),
    ],
    ids=["box", "sphere", "cylinder", "freeform", "plane"],
)
def test_first_hit_is_exact_and_first(prim):
    d = _rays(3000)
    t, _ = prim.intersect(np.zeros(3), d, 1e-9)
    hit = np.isfinite(t)
    assert 0.05 < hit.mean() <= 1.0
    # the hit lies on the surface: just before it outside, just after it inside
    P = t[hit, None] * d[hit]
    step = 1e-7 * d[hit] / np.linalg.norm(d[hit], axis=1, keepdims=True)
    assert not prim.inside(P - step, tol=0.0).any()
    assert prim.inside(P + step, tol=0.0).all()
    # and no earlier entry exists (dense march, 0.01 mm steps)
    brute = _brute_first_hit(prim, d[:600])
    both = np.isfinite(brute) & np.isfinite(t[:600])
    assert np.all(np.abs(brute[both] - t[:600][both]) < 0.02)
    # a march of 0.01 mm steps can only miss grazing hits
    assert np.isfinite(t[:600])[np.isfinite(brute)].all()
    assert (np.isfinite(t[:600]) & ~np.isfinite(brute)).sum() <= 3


def test_freeform_hits_lie_on_the_design_surface_to_a_nanometre():
    part = FreeformPart(np.array([0.0, 0.0, 160.0]), np.diag([1 / 25, -1 / 20, -1 / 25]))
    d = _rays(20000, seed=2)
    t, face = part.intersect(np.zeros(3), d, 1e-9)
    ok = np.isfinite(t) & (face == 0)
    X = part.to_unit(t[ok, None] * d[ok])
    N = part.gauge(X)
    grad = np.linalg.norm((X**3 / (N**3)[:, None]) @ part.M, axis=1)
    assert np.abs(N - 1.0).max() / grad.min() < 1e-9  # mm


def test_truth_mesh_is_within_half_a_micrometre_of_the_design_surface(tmp_path):
    """Random points of every kind of triangle, and Open3D's distance from design points to the mesh."""
    import open3d as o3d

    rig = PRESETS["paper"]
    spec = next(s for s in rig.scans if s.artefact == "freeform")
    part = freeform_part(rig, spec)
    V, F = part_mesh(part)
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    # outward orientation
    normal = np.cross(B - A, C - A)
    X = part.to_unit((A + B + C) / 3)
    assert np.all(np.einsum("ij,ij->i", normal, (X**3) @ part.M) > 0)
    rng = np.random.default_rng(0)
    idx = rng.integers(0, len(F), 300000)
    w = rng.dirichlet([1, 1, 1], len(idx))
    Q = w[:, :1] * A[idx] + w[:, 1:2] * B[idx] + w[:, 2:] * C[idx]
    Q = np.vstack([Q, (A + B) / 2, (B + C) / 2, (A + C) / 2])
    X = part.to_unit(Q)
    N = part.gauge(X)
    dist = (1.0 - N) / np.linalg.norm((X**3 / (N**3)[:, None]) @ part.M, axis=1)
    assert np.abs(dist[X[:, 2] >= 0]).max() < 0.5e-3
    # the file Open3D reads is that mesh; design points (rendered hits) are within 0.5 um of it
    write_ply(tmp_path / "part.ply", V, F)
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "part.ply"))
    Vr = np.asarray(mesh.vertices)
    assert np.array_equal(Vr, V) and np.array_equal(np.asarray(mesh.triangles), F)
    # design points (rendered hits) lie within 0.5 um of the mesh: Open3D (float32) finds the
    # triangle a ray from inside the part towards each point meets; the distance along that
    # ray to the triangle's plane, in float64, bounds the distance to the mesh from above
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((Vr - part.c).astype(np.float32)),
                        o3d.core.Tensor(F.astype(np.uint32)))
    T_cam_base = np.linalg.inv(arm.scan_trajectory(rig, spec, part.c + np.array([0, 0, 20.0]), 3)[1][1])
    part_cam = part.transformed(T_cam_base)
    d = _rays(20000, seed=4, spread=0.2)
    t, face = part_cam.intersect(np.zeros(3), d, 1e-9)
    ok = np.isfinite(t) & (face == 0)
    assert ok.sum() > 1000
    P_cam = t[ok, None] * d[ok]
    Q = (P_cam - T_cam_base[:3, 3]) @ T_cam_base[:3, :3] - part.c
    inner = part.Minv @ np.array([0.0, 0.0, 0.3])
    D = Q - inner
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    rays = np.hstack([np.broadcast_to(inner, Q.shape), D]).astype(np.float32)
    tri = scene.cast_rays(o3d.core.Tensor(rays))["primitive_ids"].numpy().astype(np.int64)
    assert np.all(tri < len(F))
    a, b, c = (Vr[F[tri, k]] - part.c for k in range(3))
    n = np.cross(b - a, c - a)
    s = np.einsum("ij,ij->i", n, a - inner) / np.einsum("ij,ij->i", n, D)
    H = inner + s[:, None] * D  # on the triangle's plane, float64
    # barycentric coordinates of H: it must lie in the triangle (float32 may pick a neighbour)
    v0, v1, v2 = b - a, c - a, H - a
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    bv = (d11 * d20 - d01 * d21) / den
    bw = (d00 * d21 - d01 * d20) / den
    inside = (bv >= -1e-6) & (bw >= -1e-6) & (bv + bw <= 1 + 1e-6)
    assert inside.mean() > 0.98
    assert np.linalg.norm(H - Q, axis=1)[inside].max() < 0.5e-3


def test_shadow_rays_see_the_gauge_block():
    """A point on the plate behind the block (seen from the emitter) is shadowed, one in front is not."""
    plate = HalfSpace(np.zeros(3), np.array([0.0, 0.0, 1.0]))
    block = Box(np.array([0.0, 0.0, 10.0]), np.eye(3), np.array([5.0, 5.0, 10.0]))
    scene = Scene([plate, block])
    emitter = np.array([-100.0, 0.0, 100.0])
    P = np.array([[8.0, 0.0, 0.0], [-8.0, 0.0, 0.0], [8.0, 30.0, 0.0]])
    assert scene.blocked(P, emitter).tolist() == [True, False, False]


@pytest.mark.parametrize("scan", ["gauge", "ball", "part"])
def test_centreline_truth_lies_on_plane_and_surface_and_flags_agree(scan):
    rig = PRESETS["paper"]
    model = RigModel(rig)
    spec = next(s for s in rig.scans if s.name == scan)
    scene_b, _, aim = scan_scene(rig, spec)
    _, Tbc = arm.scan_trajectory(rig, spec, aim, spec.frames)
    scene = scene_b.transformed(invert_transform(Tbc[spec.frames // 2]))
    sheet = model.lasers["A"]
    mask, rows, _ = stripe_truth(model, scene, sheet, model.scan_window)
    P = np.column_stack([rows["x_cam"], rows["y_cam"], rows["z_cam"]])
    assert np.abs(sheet.distance(P)).max() < 1e-9
    uv = model.camera.project(P)
    assert np.abs(uv[:, 0] - rows["u"]).max() < 1e-6
    assert np.abs(uv[:, 1] - rows["v"]).max() < 1e-6
    # unoccluded points are the camera's first hit; occluded ones are not
    t, _, _ = scene.trace(np.zeros(3), P)
    assert np.all(np.abs(t[rows["unoccluded"]] - 1.0) < 1e-9)
    assert np.all(t[~rows["unoccluded"]] < 1.0 - 1e-9)
    assert rows["visible"].sum() > 200
    # every visible centreline pixel is inside the band that was rendered
    x0, y0 = model.scan_window[:2]
    vis = rows["visible"]
    vi = np.rint(rows["v"][vis]).astype(int) - y0
    inside = (vi >= 0) & (vi < mask.shape[0])
    assert mask[vi[inside], rows["u"][vis][inside] - x0].all()


def test_face_albedo_of_a_board_view_agrees_with_tracing_the_scene():
    """Albedo, outline and edge distance on the board's face: the face's plane equation (the
    fast path of the supersampled edge pixels) against full first-hit tracing and shading."""
    from crossline.sim.render import _face_albedo
    from crossline.sim.scenes import board_scene_free
    from crossline.sim.views import camera_views

    rig = PRESETS["paper"]
    model = RigModel(rig)
    T = camera_views(model.camera, rig.board, rig.quick_calibration, 3)[1]
    scene = board_scene_free(rig.board).transformed(T)
    rng = np.random.default_rng(8)
    xy = np.column_stack([rng.uniform(-0.35, 0.35, 200_000), rng.uniform(-0.25, 0.25, 200_000)])
    d = np.column_stack([xy, np.ones(len(xy))])
    t, pid, face = scene.trace(np.zeros(3), d)
    board = np.isfinite(t) & (pid == 0) & (face == 4)
    assert 0.2 < board.mean() < 0.95
    P = t[board, None] * d[board]
    _, alb, edge = scene.shade(P, pid[board], face[board], edges=True)
    # all rays labelled with the board's face code, as the renderer does inside a cell
    a, on, e = _face_albedo(scene, np.full(len(xy), 4, np.int32), xy, edges=True)
    assert np.array_equal(on, board)
    same = a[board] == alb
    assert same.mean() > 0.9999 and (~same).sum() < 5  # only rays on an edge, to 1e-12 mm
    assert np.abs(e[board] - edge).max() < 1e-9
    # mixed codes (board face and background) go through the masked path
    codes = np.where(board, 4, 16)
    a2, on2 = _face_albedo(scene, codes, xy)
    assert np.array_equal(a2[board], a[board]) and on2[~board].mean() > 0.99


def test_differs_at_sees_every_other_neighbour():
    """8-neighbour test on a bordered code image against a direct loop."""
    from crossline.sim.render import _differs_at

    rng = np.random.default_rng(5)
    H, W, ignore = 23, 31, -2
    code = rng.integers(0, 3, (H, W)).astype(np.int32)
    code[rng.random((H, W)) < 0.3] = ignore
    code[5:12, 8:20] = 1  # a flat patch: its inner pixels differ from nothing
    padded = np.full((H + 2, W + 2), ignore, np.int32)
    padded[1:-1, 1:-1] = code
    rows, cols = np.nonzero(code != ignore)
    got = _differs_at(padded, rows, cols, ignore)
    want = np.zeros(rows.size, bool)
    for k, (r, c) in enumerate(zip(rows, cols, strict=True)):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                rr, cc = r + dy, c + dx
                if (dy or dx) and 0 <= rr < H and 0 <= cc < W and code[rr, cc] not in (ignore, code[r, c]):
                    want[k] = True
    assert np.array_equal(got, want) and want.any() and not want.all()


def test_a_dent_is_pressed_into_hits_normals_sections_and_the_truth_mesh():
    """A 0.1 mm Gaussian dent: rays meet the surface that deep below the design's, in the
    camera frame too; sections and the truth mesh lie on it; the design elsewhere is untouched."""
    import dataclasses

    from crossline.sim.scene import Dent

    rig = PRESETS["paper"]
    spec = next(s for s in rig.scans if s.artefact == "freeform")
    spec = dataclasses.replace(spec, params={**spec.params, "dent": {
        "depth_mm": 0.1, "sigma_mm": 2.0, "at": (0.3, -0.2)}})
    part = freeform_part(rig, spec)
    plain = dataclasses.replace(part, dent=None)
    dent = part.dent
    assert isinstance(dent, Dent) and abs(plain.gauge(plain.to_unit(dent.centre[None]))[0] - 1) < 1e-12
    # vertical rays over the dent: the hit lies below the design's by the dent's depth there,
    # measured along the design normal (~vertical on the top: the ray's own length differs by
    # 1/cos of the normal's tilt)
    rng = np.random.default_rng(1)
    xy = dent.centre[:2] + rng.uniform(-7.0, 7.0, (400, 2))
    o = np.column_stack([xy, np.full(len(xy), dent.centre[2] + 50.0)])
    d = np.tile([0.0, 0.0, -1.0], (len(o), 1))
    t0, _ = plain.intersect(o, d, 0.0)
    t1, face = part.intersect(o, d, 0.0)
    assert np.isfinite(t0).all() and np.isfinite(t1).all() and (face == 0).all()
    P0 = o + t0[:, None] * d
    n0 = plain.normal(P0, face)
    expect = dent.depth(P0) / n0[:, 2]
    # (to first order: the dent's own slope, up to 0.03 here, moves the hit sideways)
    assert np.abs((t1 - t0) - expect).max() < 1e-3 and (t1 - t0).max() > 0.095
    assert np.abs(part.dent_function(o + t1[:, None] * d)).max() < 1e-9
    # the same in a camera frame
    T = np.linalg.inv(arm.scan_trajectory(rig, spec, part.c + np.array([0, 0, 20.0]), 3)[1][1])
    tc, _ = part.transformed(T).intersect(o @ T[:3, :3].T + T[:3, 3], d @ T[:3, :3].T, 0.0)
    assert np.allclose(tc, t1, atol=1e-9)
    # inside: just under the dented surface yes, between it and the design surface no
    P1 = o + t1[:, None] * d
    deep = dent.depth(P1) > 0.01
    up = np.array([0.0, 0.0, 1.0])
    assert part.inside(P1 - 1e-4 * up).all()
    assert not part.inside(P1[deep] + 0.005 * up).any()
    assert plain.inside(P1[deep] + 0.005 * up).all()
    # a section through the dent lies in its plane and on the dented surface
    n_pl = np.array([0.6, 0.8, 0.0])
    (curve,) = part.sections(n_pl, -n_pl @ dent.centre)
    Pc, Nc, _ = curve.fn(np.linspace(0, 2 * np.pi, 4000))
    near = dent.near(Pc)
    assert near.sum() > 50
    assert np.abs(Pc @ n_pl - n_pl @ dent.centre).max() < 1e-9
    assert np.abs(part.dent_function(Pc[near])).max() < 1e-9
    assert np.allclose(Nc[near], part.normal(Pc[near], np.zeros(int(near.sum()), np.int8)))
    # the truth mesh: vertices on the dented surface, triangles within 0.5 um of it
    V, F = part_mesh(part)
    Vp, _ = part_mesh(plain)
    on = dent.near(V)
    assert np.abs(part.dent_function(V[on])).max() < 1e-9
    tri = V[F]
    c = tri.mean(1)
    close = dent.near(c)
    nrm = np.cross(tri[close, 1] - tri[close, 0], tri[close, 2] - tri[close, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    tt, _ = part.intersect(c[close] + nrm, -nrm, 0.0)
    assert np.abs(tt - 1.0).max() < 0.5e-3
    # away from the dent the mesh is the design's
    far = ~dent.near(Vp) & (np.linalg.norm(Vp - dent.centre, axis=1) > 6 * dent.sigma_mm)
    assert far.sum() > 0.5 * len(Vp)
    assert len(np.intersect1d(Vp[far].view("f8,f8,f8"), V.view("f8,f8,f8"))) == far.sum()

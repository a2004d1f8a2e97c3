"""The sheet-curvature correction of stripe centres, against ray-traced profiles and a render."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from crossline.camera import Camera
from crossline.scan.sheet_curvature import (
    CellSums,
    centre_shift,
    sheet_sigma,
    skew_response,
    surface_shape,
)
from crossline.scan.stripes import _frame_work, run_extract_stripes
from crossline.scan.triangulate import run_triangulate

CAM = Camera(np.array([[4000.0, 0, 640.0], [0, 4000.0, 512.0], [0, 0, 1]]), np.zeros(5), (1280, 1024))
PLANE_N = np.array([0.0, -np.sin(np.radians(30.0)), np.cos(np.radians(30.0))])  # tilted about x
CENTRE = np.array([2.0, 3.0, 300.0])  # a ball of radius 10 mm, 300 mm in front of the camera
R = 10.0
EMITTER = np.array([0.0, 150.0, 0.0])


def _ray_sphere(uv: np.ndarray) -> np.ndarray:
    """The near hit of each pixel's ray with the ball (NaN where it misses)."""
    r = CAM.rays(uv)
    b = r @ CENTRE
    disc = b * b - (CENTRE @ CENTRE - R * R)
    with np.errstate(invalid="ignore"):
        t = b - np.sqrt(disc)
    return r * t[:, None]


def _sphere_shape(P: np.ndarray):
    N = (P - CENTRE) / R  # outward: the surface falls away along it, h = -x^2 / 2R
    e1 = np.cross(N, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(N, e1)
    second = np.tile([-1.0 / R, 0.0, -1.0 / R], (len(P), 1))
    return N, e1, e2, second


def _column_profiles(d: float, sigma_f: float, lambert: bool):
    """For columns crossing the ball's stripe: the true centre row (f = 0), the centroid of the
    ray-traced profile along the column, and the centre's point on the ball."""
    out = []
    for u in np.arange(560.0, 720.0, 8.0):
        v = np.arange(0.0, 1024.0, 0.01)
        X = _ray_sphere(np.column_stack([np.full(v.size, u), v]))
        f = X @ PLANE_N + d
        hit = np.isfinite(f)
        if hit.sum() < 100:
            continue
        v, X, f = v[hit], X[hit], f[hit]
        # the crossing nearest the ball's visible middle (f changes sign once on the near cap)
        s = np.flatnonzero(np.diff(np.sign(f)) != 0)
        if s.size != 1:
            continue
        i = s[0]
        v0 = v[i] - f[i] * (v[i + 1] - v[i]) / (f[i + 1] - f[i])
        E = np.exp(-0.5 * (f / sigma_f) ** 2)
        if lambert:
            N = (X - CENTRE) / R
            ell = X - EMITTER
            E *= np.abs(np.einsum("ij,ij->i", ell, N)) / np.linalg.norm(ell, axis=1)
        near = np.abs(v - v0) < 60.0
        if E[near][[0, -1]].max() > 1e-6 * E[near].max():  # the profile runs off the ball
            continue
        vc = np.sum(v[near] * E[near]) / np.sum(E[near])
        out.append((u, v0, vc, _ray_sphere(np.array([[u, v0]]))[0]))
    return out


@pytest.mark.parametrize("lambert", [False, True])
def test_centre_shift_is_the_traced_profile_centroid(lambert):
    """A centroid (K = -3 sigma^2 per unit skew) of the exact ray-traced column profile of a
    thick sheet on a ball moves as centre_shift says, with and without Lambert's cosine."""
    d = -(PLANE_N @ CENTRE) + 4.0  # the sheet cuts the ball 4 mm off its centre
    sigma_f = 0.15
    rows = _column_profiles(d, sigma_f, lambert)
    assert len(rows) >= 8
    u, v0, vc, P = (np.array(x) for x in zip(*rows, strict=True))
    N, e1, e2, second = _sphere_shape(P)
    bias, direction, _ = centre_shift(
        CAM, PLANE_N, d, np.column_stack([u, v0]), P, N, e1, e2, second, sigma_f=sigma_f,
        k=np.full(len(u), -3.0), along=np.tile([0.0, 1.0], (len(u), 1)),
        emitter=EMITTER if lambert else None)
    np.testing.assert_array_equal(direction, np.tile([0.0, 1.0], (len(u), 1)))
    traced = vc - v0
    assert np.abs(traced).max() > 0.05  # the bias is there to be found (px)
    np.testing.assert_allclose(bias, traced, rtol=0.05, atol=0.003)


def test_surface_shape_of_a_ball_and_a_plane():
    """Principal curvatures of scattered points on a ball (1/R) and a plane (0), and the cell
    sums of two batches equal those of one."""
    rng = np.random.default_rng(1)
    n = rng.normal(size=(40000, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.6
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pts = CENTRE + R * n + rng.normal(0, 0.002, (len(n), 1)) * n
    sh = surface_shape(pts)
    k = sh.curvature()[sh.ok]
    assert sh.ok.mean() > 0.9
    assert abs(np.median(k) - 1.0 / R) < 0.05 / R
    flat = np.column_stack([rng.uniform(0, 30, 40000), rng.uniform(0, 30, 40000),
                            rng.normal(0, 0.002, 40000)])
    acc = CellSums(batch=15000)
    acc.add(flat[:20000])
    acc.add(flat[20000:])
    one = surface_shape(flat)
    two = acc.shape()
    two.ensure()
    np.testing.assert_array_equal(one.keys, two.keys)
    np.testing.assert_allclose(one.second, two.second, atol=1e-9)
    assert np.quantile(one.curvature()[one.ok], 0.9) < 0.01


def test_sheet_sigma_from_widths():
    """The sheet of each laser and the shared blur from widths at different gradients; a laser
    whose centres all see the sheet alike still gets its sheet from the shared blur."""
    rng = np.random.default_rng(2)
    g_a = rng.uniform(0.02, 0.08, 5000)
    g_b = rng.uniform(0.045, 0.05, 5000)  # narrow: alone it could not tell sheet from blur
    ws = {}
    for name, g, sf in (("A", g_a, 0.12), ("B", g_b, 0.2)):
        w = np.sqrt((sf / g) ** 2 + 0.8**2) * (1 + rng.normal(0, 0.02, g.size))
        w[:50] *= 2.5  # merged stripes
        ws[name] = (g, w)
    # a few centres where the sheet runs almost along the ray (|grad f| ~ 0; random rig 8's
    # ball had one, and every sheet came out 0)
    g, w = ws["B"]
    ws["B"] = (np.r_[g, 1e-14, 3e-9], np.r_[w, 1.3, 1.1])
    sig, blur = sheet_sigma(ws)
    assert abs(sig["A"] - 0.12) < 0.004
    assert abs(sig["B"] - 0.2) < 0.006
    assert abs(blur - 0.8) < 0.08


def test_skew_response_predicts_the_gaussian_fit():
    """The table measured at one skew predicts the speckle-weighted Gaussian fit's shift at
    another skew and sheet width (a profile it was not measured on), blurred alike."""
    from crossline.scan.sheet_curvature import _synthetic_frame

    params = {"threshold": 0.1, "min_width": 2.0, "max_width": 30.0, "fit_pad": 6,
              "relative_noise": None, "fit_across": True, "min_peak": 0.17}
    work = _frame_work("gaussian", params, 4095.0)
    kw = {"peak": 2500.0, "background": 80.0, "relative_noise": 0.12, "noise_dn": 3.0,
          "data_max": 4095.0}
    sk, kk = skew_response(lambda imT: work(0, imT), np.array([1.5, 2.5, 4.0, 6.0]), blur=0.8, **kw)
    assert len(sk) >= 3 and np.all(kk < 0)
    rng = np.random.default_rng(5)
    sigma, beta = 3.2, 0.012
    shifts = []
    for b in (beta, -beta):
        img, centre = _synthetic_frame(sigma, b, kw["peak"], kw["background"], kw["relative_noise"],
                                       kw["noise_dn"], 4095.0, np.dtype(np.uint16), rng, 0.8)
        c = work(0, np.ascontiguousarray(img.T))
        u = np.round(c["u"]).astype(int)
        shifts.append(np.median(c["v"] - centre[u]))
    measured = (shifts[0] - shifts[1]) / 2
    predicted = np.interp(sigma, sk, kk) * sigma**2 * beta / sigma
    assert abs(predicted - measured) < 0.12 * abs(measured)


def _true_capture(root: Path, seed: int, scans: list[str]) -> tuple[Path, tuple, dict]:
    """A quick render of random rig ``seed``'s ``scans`` whose frames.csv give the arm's true
    poses, the true calibration's files, and the truth."""
    from crossline.sim import simulate, write_true_calibration

    cap = simulate(root / "cap", "random-small", seed=seed, quick=True, scans=scans,
                   parts=("scans",), progress=False)
    for scan in scans:
        frames = pd.read_csv(cap / f"scans/{scan}/frames.csv")
        tp = pd.read_parquet(cap / f"truth/{scan}_poses.parquet").set_index("frame")
        for c in ("x", "y", "z", "qw", "qx", "qy", "qz"):
            frames[c] = tp.loc[frames["frame"], c].to_numpy()
        frames.to_csv(cap / f"scans/{scan}/frames.csv", index=False)
    return cap, write_true_calibration(cap, root / "cal"), json.loads((cap / "truth.json").read_text())


@pytest.fixture(scope="module")
def thick_ball(tmp_path_factory):
    """Random rig 7's ball (a 0.7 mm thick sheet, 20 mm ball), with the true calibration and
    the true arm poses: only the stripe centres can put the points off the ball."""
    root = tmp_path_factory.mktemp("thick")
    cap, cal, truth = _true_capture(root, 7, ["ball"])
    stripes = root / "ball.parquet"
    run_extract_stripes(cap, "ball", stripes, extractor="gaussian", threshold=0.10)
    return cap, cal, stripes, truth


def _radial_um(points: Path, truth: dict) -> float:
    p = pd.read_parquet(points, columns=["x", "y", "z"]).to_numpy()
    c = np.array(truth["scans"]["ball"]["center_base"])
    r = np.linalg.norm(p - c, axis=1) - truth["scans"]["ball"]["diameter"] / 2
    return float(np.median(r[np.abs(r) < 0.2])) * 1e3


def test_rendered_thick_sheet_ball(thick_ball, tmp_path):
    """On the render, the corrected centres put the ball's points on the true sphere (median
    radial residual within 2.5 um; 10 um inside it as extracted); the sheet's thickness found
    from the widths is the render's; the plane's points do not move."""
    cap, (cam, las, he), stripes, truth = thick_ball
    out = {}
    for on in (False, True):
        pts = tmp_path / f"{on}.parquet"
        meta = run_triangulate(cap, "ball", stripes, cam, las, he, pts, smooth_px=7, sheet_curvature=on)
        out[on] = (_radial_um(pts, truth), meta, pts)
    assert out[False][0] < -6.0
    assert abs(out[True][0]) < 2.5
    info = out[True][1]["sheet_curvature"]
    for name in ("A", "B"):
        w0 = truth["lasers"][name]["waist_mm"]  # the 1/e^2 half-thickness: sigma = w / 2
        assert info["sheet_sigma_mm"][name] == pytest.approx(w0 / 2, rel=0.08)
    a = pd.read_parquet(out[False][2], columns=["x", "y", "z"]).to_numpy()
    b = pd.read_parquet(out[True][2], columns=["x", "y", "z"]).to_numpy()
    c = np.array(truth["scans"]["ball"]["center_base"])
    far = np.linalg.norm(a - c, axis=1) > 15.0  # the table around the ball
    assert far.sum() > 1000
    assert np.median(np.linalg.norm(b[far] - a[far], axis=1)) == 0.0


@pytest.mark.parametrize("seed", [7, 8])
def test_rendered_surfaces_carry_no_offset(seed, tmp_path):
    """Issue 22.3: with the true calibration and poses, the points of the ball, the gauge
    block's top and plate faces and the plate sit on the true surfaces within 1 um (median
    signed distance), extracted and triangulated as the workflow does. Rig 7 has the thickest
    sheet (its ball 10 um inside without the sheet-curvature correction); rig 8's ball has a
    centre where the sheet runs along the ray, which had once turned the correction off."""
    from crossline.report.scan_truth import surface_distances

    cap, cal, truth = _true_capture(tmp_path, seed, ["ball", "gauge", "plate"])
    offsets = {}
    for scan in ("ball", "gauge", "plate"):
        stripes = tmp_path / f"{scan}.stripes.parquet"
        run_extract_stripes(cap, scan, stripes, extractor="gaussian", threshold=0.10)
        for on in (False, True):
            pts = tmp_path / f"{scan}-{on}.parquet"
            run_triangulate(cap, scan, stripes, *cal, pts, smooth_px=7, sheet_curvature=on)
            p = pd.read_parquet(pts, columns=["x", "y", "z"]).to_numpy()
            for surface, d in surface_distances(p, truth["scans"][scan]).items():
                assert d.size > 1000, surface
                offsets[surface, on] = 1e3 * float(np.median(d))
    assert {s for s, _ in offsets} == {"ball", "gauge top", "gauge plate", "plate"}
    assert offsets["ball", False] < -2.5  # inside the ball as extracted
    for surface in ("ball", "gauge top", "gauge plate", "plate"):
        assert abs(offsets[surface, True]) <= 1.0, (surface, offsets)

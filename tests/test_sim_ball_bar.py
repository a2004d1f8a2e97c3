"""The simulated ball bar (ISO 10360-8 sphere-spacing error): its scans, scene, truth and frames."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from crossline.errors import CrosslineError
from crossline.geometry import transform_from_pose
from crossline.sim.presets import PRESETS, ball_bar_scans
from tests.conftest import render_cached

BAR = "bar_3"  # the inclined position: both balls on stems of different heights


@pytest.fixture(scope="module")
def bar_capture() -> Path:
    """A quick compact capture of one ball bar scan (no calibration views)."""
    return render_cached("compact", seed=0, ball_bar=True, scans=[BAR], parts=["scans"])


def _ball_spec(rig):
    return next(s for s in rig.scans if s.artefact == "sphere")


def _rigs():
    from crossline.sim.random_rig import random_rig

    return [PRESETS["paper"], PRESETS["compact"], random_rig(1, small=True)]


def test_bar_specs_follow_each_rigs_ball_scan():
    """Every rig's three bar positions: its ball's size, albedos, distance, tilt and roll; L of
    2-2.4 diameters; turned by 60 and 120 deg, the last inclined; a sweep along the bar past
    both balls, whose quick capture covers it all with as many frames per ball diameter as the
    quick ball scan has in all."""
    from crossline.sim import arm
    from crossline.sim.scenes import scan_scene

    for rig in _rigs():
        ball = _ball_spec(rig)
        bars = ball_bar_scans(rig)
        assert [b.name for b in bars] == ["bar_1", "bar_2", "bar_3"]
        assert not {b.name for b in bars} & {s.name for s in rig.scans}
        D = ball.params["diameter"]
        for b in bars:
            p = b.params
            assert b.artefact == "ball_bar" and p["diameter"] == D
            assert 2.0 * D <= p["length"] <= 2.4 * D + 0.01
            for k in ("stem_radius", "albedo", "stem_albedo"):
                assert p[k] == ball.params[k]
            assert (b.distance_mm, b.tilt_deg, b.tilt_azimuth_deg, b.roll_deg, b.frames) == (
                ball.distance_mm, ball.tilt_deg, ball.tilt_azimuth_deg, ball.roll_deg, ball.frames)
            assert b.sweep_mm == pytest.approx(p["length"] + 1.6 * D, abs=0.01)
            assert b.quick_frames * D / b.sweep_mm >= rig.quick_frames
        turns = [(b.heading_deg - bars[0].heading_deg) % 360.0 for b in bars]
        assert turns == pytest.approx([0.0, 60.0, 120.0], abs=0.02)
        assert bars[0].heading_deg == pytest.approx(ball.heading_deg, abs=0.01)
        assert [b.params["incline_deg"] for b in bars][:2] == [0.0, 0.0]
        assert 15.0 <= bars[2].params["incline_deg"] <= 20.0

        for b in bars:
            scene, truth, aim = scan_scene(rig, b)
            c1, c2 = (np.array(c) for c in truth["centers_base"])
            r = D / 2
            assert np.linalg.norm(c2 - c1) == pytest.approx(b.params["length"], abs=1e-9)
            # along the sweep: the bar's plan direction is the heading
            h = np.radians(b.heading_deg)
            u = np.array([np.cos(h), np.sin(h)])
            assert (c2 - c1)[:2] @ u == pytest.approx(np.hypot(*(c2 - c1)[:2]), abs=1e-9)
            dz = (c2 - c1)[2]
            assert dz == pytest.approx(b.params["length"] * np.sin(np.radians(b.params["incline_deg"])))
            for c in (c1, c2):  # above the table, clear of it by more than the stem's radius
                assert c[2] - r > rig.table_z_mm + b.params["stem_radius"]
            assert aim == pytest.approx((c1 + c2) / 2 + [0.0, 0.0, r])
            assert [pr.name for pr in scene.prims] == ["table", "ball_1", "stem_1", "ball_2", "stem_2"]
            # the quick sweep's targets (the optical axis at the aim's distance) pass both balls
            q = dataclasses.replace(b, frames=b.quick_frames)
            _, T = arm.scan_trajectory(rig, q, aim, q.quick_frames)
            target = T[:, :3, 3] + b.distance_mm * T[:, :3, 2]
            s = (target[:, :2] - aim[:2]) @ u
            half = (c2 - c1)[:2] @ u / 2
            assert s.min() < -half - r and s.max() > half + r


def test_bar_scans_only_with_the_flag(tmp_path):
    with pytest.raises(CrosslineError, match=r"unknown scan\(s\) \['bar_1'\]"):
        from crossline.sim import simulate

        simulate(tmp_path / "x", "compact", quick=True, scans=["bar_1"], progress=False)
    from crossline.cli import build_parser

    assert build_parser().parse_args(["simulate", "OUT", "--ball-bar"]).ball_bar is True
    assert build_parser().parse_args(["simulate", "OUT"]).ball_bar is False


@pytest.mark.slow
def test_bar_truth_and_rig_yaml(bar_capture):
    """rig.yaml gives the bar's diameter and length; truth.json its two centres, L apart, each
    ball on its own vertical stem above the table; the capture checks."""
    from crossline.io.capture import check_capture

    rig = yaml.safe_load((bar_capture / "rig.yaml").read_text())
    spec = next(b for b in ball_bar_scans(PRESETS["compact"]) if b.name == BAR)
    D, L = spec.params["diameter"], spec.params["length"]
    assert rig["scans"] == {BAR: {"artefact": "ball_bar", "diameter": D, "length": L}}
    truth = json.loads((bar_capture / "truth.json").read_text())
    sc = truth["scans"][BAR]
    assert (sc["diameter"], sc["length"]) == (D, L)
    c = np.array(sc["centers_base"])
    assert c.shape == (2, 3)
    assert np.linalg.norm(c[1] - c[0]) == pytest.approx(L, abs=1e-9)
    z0 = truth["table_z_base"]
    for ck, stem in zip(c, sc["stems"], strict=True):
        assert stem["top_base"] == pytest.approx(ck.tolist(), abs=1e-12)
        assert ck[2] - D / 2 > z0 and stem["radius"] < D / 2
    assert c[1][2] - c[0][2] == pytest.approx(L * np.sin(np.radians(sc["incline_deg"])), abs=1e-9)
    assert sc["surfaces"] == ["table", "ball_1", "stem_1", "ball_2", "stem_2"]
    assert sc["frames"] == spec.quick_frames
    assert truth["capture_options"]["ball_bar"] is True

    summary = check_capture(bar_capture)
    assert summary["scans"][BAR]["frames"] == spec.quick_frames
    assert summary["scans"][BAR]["nominal"] == {"diameter": D, "length": L}


@pytest.mark.slow
def test_bar_frames_show_both_balls(bar_capture):
    """The true stripe points, taken to the base frame with the true poses, land on each ball
    (within D/2 of its centre) in as many frames as the quick ball scan has, over the ball's
    whole length along the bar; the rendered images are bright at those points."""
    from crossline.io.images import read_image

    truth = json.loads((bar_capture / "truth.json").read_text())
    sc = truth["scans"][BAR]
    X = np.array(truth["T_tool_cam"])
    cl = pd.read_parquet(bar_capture / sc["centrelines"])
    po = pd.read_parquet(bar_capture / sc["poses"])
    T = transform_from_pose(po[["x", "y", "z"]].to_numpy(), po[["qw", "qx", "qy", "qz"]].to_numpy()) @ X
    vis = cl[cl["visible"]].reset_index(drop=True)
    Tf = T[vis["frame"].to_numpy()]
    P = np.einsum("nij,nj->ni", Tf[:, :3, :3], vis[["x_cam", "y_cam", "z_cam"]].to_numpy()) + Tf[:, :3, 3]
    r = sc["diameter"] / 2
    c = np.array(sc["centers_base"])
    u = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])
    x0, y0 = truth["sensor"]["scan_window"][:2]
    quick_ball_frames = PRESETS["compact"].quick_frames
    for k in range(2):
        d = np.linalg.norm(P - c[k], axis=1)
        on = d <= r + 0.01
        frames = np.unique(vis["frame"][on])
        assert len(frames) >= quick_ball_frames, (k, len(frames))
        assert (vis["surface"][on] == f"ball_{k + 1}").all()
        along = (P[on] - c[k]) @ u
        assert along.min() < -0.9 * r and along.max() > 0.9 * r
        # the images: the stripe is there (well above the frame's median) at its true pixels in
        # as many frames (at the ball's rim, in grazing light, it is fainter)
        ratios = []
        for f in frames:
            img = read_image(bar_capture / "scans" / BAR / "frames" / f"{f:06d}.png").astype(float)
            rows = vis[on & (vis["frame"] == f).to_numpy()]
            px = img[np.rint(rows["v"].to_numpy() - y0).astype(int), rows["u"].to_numpy() - x0]
            ratios.append(np.median(px) / max(np.median(img), 1.0))
        assert sum(x > 3.0 for x in ratios) >= quick_ball_frames, np.round(ratios, 1)

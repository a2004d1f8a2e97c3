"""A dent rendered into the freeform part is found by the report's nominal comparison.

The simulator presses a 0.1 mm dent into the part (not into its drawing, part.stl) and gives
the part's placement as probed with the arm (``nominal_pose``, with the arm's error); the scan
goes through stripe extraction, triangulation and fusion on the true calibration, and the
report compares the cloud with the drawing. The map must find the dent: one region, where the
truth put it, as deep within 15 µm.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crossline.cli import main
from tests.conftest import render_cached

pytestmark = pytest.mark.slow

DEPTH_MM = 0.1


def _true_calibration(capture: Path, folder: Path) -> None:
    """camera.json, lasers.json and handeye.json of the rig's truth (the stages' formats)."""
    from crossline import Camera, HandEye, LaserPlanes

    t = json.loads((capture / "truth.json").read_text())
    folder.mkdir(parents=True)
    c = t["camera"]
    Camera(np.asarray(c["K"]), np.asarray(c["dist"]), tuple(c["image_size"]), {}).save(
        folder / "camera.json")
    LaserPlanes.from_dict({k: {"normal": v["normal"], "d": v["d"]}
                           for k, v in t["lasers"].items()}).save(folder / "lasers.json")
    HandEye(np.asarray(t["T_tool_cam"]), "truth", {}).save(folder / "handeye.json")


@pytest.fixture(scope="module")
def dented(tmp_path_factory):
    cap = render_cached("paper", seed=0, scans=["part"], parts=["scans"], dent_mm=DEPTH_MM,
                        nominal_datum=True)
    root = tmp_path_factory.mktemp("dent")
    cal = root / "interim" / "calibration"
    _true_calibration(cap, cal)
    st, pts = root / "interim" / "stripes" / "part.parquet", root / "interim" / "points" / "part.parquet"
    steps = [
        ["extract-stripes", str(cap), "part", "--out", str(st), "--threads", "2"],
        ["triangulate", str(cap), "part", "--stripes", str(st), "--camera", str(cal / "camera.json"),
         "--lasers", str(cal / "lasers.json"), "--handeye", str(cal / "handeye.json"), "--out", str(pts)],
        ["fuse", str(pts), "--out", str(root / "processed" / "part.ply"), "--stats",
         str(root / "processed" / "part.fuse.json"), "--refine-poses", "true",
         "--frames", str(cap / "scans" / "part" / "frames.csv"), "--arm-draws-out",
         str(root / "processed" / "part.arm.npz")],
        ["report", str(cap), "--interim", str(root / "interim"), "--processed", str(root / "processed"),
         "--pdf", str(root / "accuracy.pdf"), "--metrics", str(root / "metrics.json"),
         "--deviation-dir", str(root / "deviation")],
    ]
    for argv in steps:
        assert main(argv) == 0, f"stage failed: crossline {' '.join(argv)}"
    truth = json.loads((cap / "truth.json").read_text())["scans"]["part"]
    m = json.loads((root / "metrics.json").read_text())
    return m["scans"]["part"] | {"_summary": m["summary"]}, truth, root


def test_the_dent_is_in_the_part_and_the_truth_mesh_not_in_the_drawing(dented):
    s, truth, _ = dented
    dent = truth["dent"]
    assert dent["depth_mm"] == DEPTH_MM
    # the cloud lies on the true (dented) mesh as closely as anywhere: renderer and truth agree
    dt = s["truth"]["deviation_to_true_mesh"]
    assert abs(dt["mean_mm"]) < 0.005 and dt["max_abs_mm"] < 0.03, dt
    # rig.yaml's placement is the truth's, off by the simulated probing error only
    err = truth["nominal_pose_error"]
    assert 0 < np.linalg.norm(err["translation_mm"]) < 0.05


def test_the_map_finds_the_dent_where_and_how_deep(dented):
    s, truth, root = dented
    nc = s["nominal_comparison"]
    assert nc["alignment"]["coarse"] == "datum" and not nc["alignment"]["ambiguous"]
    # one defect seen on several stripes is one region, and nothing else is out of tolerance
    assert nc["n_regions"] == 1, nc["regions"]
    (region,) = nc["regions"]
    assert abs(region["depth_mm"] - (-DEPTH_MM)) <= 0.015, region
    where = np.asarray(region["depth_at_mm"]) - np.asarray(truth["dent"]["centre_nominal"])
    # within a third of the dent's sigma of its centre (the stripes sample it 3 mm apart)
    assert np.linalg.norm(where) < truth["dent"]["sigma_mm"] / 3, where
    # the coloured cloud holds the compared points and their deviations
    import open3d as o3d

    dev = o3d.t.io.read_point_cloud(str(root / "deviation" / "part.ply")).point.deviation.numpy().ravel()
    assert len(dev) == nc["n"] and np.isclose(dev.min(), nc["min_mm"])


def test_the_comparison_has_its_uncertainty(dented):
    """The freeform's deviation figures carry a Monte Carlo U (the true calibration has no
    covariance: the arm's draws and the frames' bootstrap), and the summary's row of the share
    within the band gets it and the ISO 14253-1 decision."""
    s, _, _ = dented
    figs = s["uncertainty"]["figures"]
    assert set(figs) == {"deviation_mean_mm", "deviation_rms_mm", "share_within_tolerance"}
    nc = s["nominal_comparison"]
    for key, value in (("deviation_mean_mm", nc["mean_mm"]), ("deviation_rms_mm", nc["rms_mm"]),
                       ("share_within_tolerance", nc["share_within_tolerance"])):
        f = figs[key]
        assert f["value"] == pytest.approx(value, abs=1e-9), key  # the report's own figure
        assert 0 < f["U"] < 0.1 and abs(f["mc_mean"] - f["value"]) < f["U"], (key, f)
        assert f["budget"]["arm"]["u"] > 0 and f["budget"]["repeatability"]["u"] > 0, key
    row = next(r for r in s["_summary"] if r["id"] == "nominal_within_share")
    assert row["U"] == figs["share_within_tolerance"]["U"] and row["decision"]

"""The accuracy report on a small synthetic capture: every section, numbers that agree, same bytes."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pandas as pd
import pytest

from crossline.fuse import run_fuse
from crossline.report.accuracy import FORM_KEYS, build_report, load_config, points_per_frame, run_report
from crossline.report.pages import build_pages, fmt, fmt_row_value, fmt_tolerance, page_texts
from tests.test_report_synthetic import make_capture

SCANS = ("gauge", "plate", "ball", "part")


@pytest.fixture(scope="session")
def synthetic(tmp_path_factory):
    """A synthetic capture with truth, its calibrations, points and fused clouds."""
    root = tmp_path_factory.mktemp("report")
    raw, interim, processed = root / "raw" / "syn", root / "interim", root / "processed"
    info = make_capture(raw, interim, frames=60, rays=250, noise=0.004)
    for s in SCANS:
        run_fuse(interim / "points" / f"{s}.parquet", processed / f"{s}.ply",
                 stats=processed / f"{s}.fuse.json")
    PLANTED.update(info)
    return raw, interim, processed


PLANTED: dict = {}


@pytest.fixture(scope="session")
def report_data(synthetic):
    return build_report(*synthetic, config=None)


def _sha(p) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_gain_over_a_single_line_is_four_thirds():
    # pattern A, B, AB with 3 points per stripe: 12 points in 3 frames against 3 per frame
    frames = np.arange(9)
    states = np.array(["A", "B", "AB"] * 3)
    pf = np.repeat(frames, [3, 3, 6] * 3)
    g = points_per_frame(frames, states, pf)
    assert g["gain_over_single_line"] == pytest.approx(4 / 3)
    assert g["by_state"]["AB"]["points_per_frame"] == 6
    # an "off" frame costs time too: A, B, AB, off gives 12 points in 4 frames = 1.0
    frames = np.arange(8)
    states = np.array(["A", "B", "AB", "off"] * 2)
    pf = np.repeat(frames, [3, 3, 6, 0] * 2)
    assert points_per_frame(frames, states, pf)["gain_over_single_line"] == pytest.approx(1.0)


def test_residual_vectors_in_either_layout(synthetic):
    from crossline.report.pages import _find_residuals

    raw = json.loads((synthetic[1] / "calibration" / "camera.json").read_text())
    uv, du = _find_residuals(raw)
    assert len(uv) == len(du) == 14 * 165
    # every circle of each used view projects inside the sensor
    assert (uv >= 0).all() and (uv[:, 0] < 3072).all() and (uv[:, 1] < 2048).all()
    flat = {"K": raw["K"], "residuals": {"uv": uv[:5].tolist(), "duv": du[:5].tolist()}}
    uv2, du2 = _find_residuals(flat)
    assert np.allclose(uv2, uv[:5]) and np.allclose(du2, du[:5])
    assert _find_residuals({"K": raw["K"]}) is None


def test_every_section_is_there(report_data, synthetic):
    m = report_data.metrics
    raw, interim, _ = synthetic
    assert m["format"] == "crossline-metrics/1"
    assert m["capture"] == {"name": "syn", "date": "2024-05-17", "simulated": True,
                            "scans": sorted(SCANS)}
    assert set(m["calibration"]) == {"camera", "lasers", "handeye"}
    assert m["calibration"]["camera"]["views_used"] == 14
    assert set(m["calibration"]["handeye"]["methods"]) == {"chou_kamel", "tsai", "park", "refined",
                                                           "andreff"}
    assert m["calibration"]["handeye"]["methods"]["andreff"]["error"] == "degenerate motion"
    for s in SCANS:
        sc = m["scans"][s]
        assert "error" not in sc, sc.get("error")
        # 4/3 within a few %: centres around the crossing of AB frames are dropped (biased
        # by the other stripe), trace ends are trimmed, and the part moves between frames
        assert sc["counts"]["gain_over_single_line"] == pytest.approx(4 / 3, abs=0.035)
        # and exactly the gain counted from the points and frames files
        fr = pd.read_csv(raw / "scans" / s / "frames.csv")
        per = pd.read_parquet(interim / "points" / f"{s}.parquet")["frame"].value_counts()
        n = fr["frame"].map(per).fillna(0)
        single = fr["lasers"].isin(["A", "B"])
        assert sc["counts"]["gain_over_single_line"] == pytest.approx(n.mean() / n[single].mean(),
                                                                      rel=1e-12)
        assert sc["counts"]["fused"]["n_output"] == sc["cloud_points"]
        assert sc["truth"]
    for s in ("gauge", "plate", "ball"):
        assert m["scans"][s]["a_vs_b"]["A_minus_B"]
    v = m["validation"]
    assert set(v) >= {"camera", "lasers", "handeye"}
    assert {f["file"] for f in m["provenance"]["inputs"]} >= {
        "rig.yaml", "truth.json", "truth/part.ply", "calibration/camera.json", "gauge.ply",
        "points/gauge.parquet", "scans/gauge/frames.csv", "gauge.fuse.json"}
    assert m["result"] == "PASS"


def test_figures_against_truth(report_data):
    # the synthetic points are exact plus 4 µm noise, so every artefact figure is near truth
    m = report_data.metrics
    g = m["scans"]["gauge"]["measurement"]
    assert abs(g["error_mm"]) < 4 * g["sem_mm"] + 1e-5
    assert g["std_mm"] == pytest.approx(0.004, rel=0.1)
    assert m["scans"]["plate"]["truth"]["distance_to_true_plane"]["rms_mm"] == pytest.approx(
        0.004, rel=0.1)
    assert m["scans"]["ball"]["truth"]["centre_distance_mm"] < 0.002
    assert abs(m["scans"]["ball"]["truth"]["diameter_error_mm"]) < 0.002
    dev = m["scans"]["part"]["truth"]["deviation_to_true_mesh"]
    assert dev["rms_mm"] == pytest.approx(0.004, rel=0.1)
    # the patch planted 3 mm off the part is counted apart (fusion may drop a few of it)
    planted = PLANTED["planted_off_part"]
    assert 0.9 * planted <= dev["n_off_part"] <= planted and planted > 50
    assert dev["n"] + dev["n_off_part"] == dev["n_total"]
    # the calibration errors put into the synthetic JSONs are found again
    v = m["validation"]
    assert v["camera"]["dcx_px"] == pytest.approx(0.5) and v["camera"]["dfx_px"] == pytest.approx(0.8)
    assert v["lasers"]["A"]["d_diff_mm"] == pytest.approx(0.003, abs=1e-9)
    assert v["handeye"]["chosen"]["translation_mm"] == pytest.approx(
        np.linalg.norm([0.01, -0.02, 0.015]) / 4, rel=1e-6)



def test_validation_volume_is_where_the_scans_measured(synthetic, report_data):
    # no volume configured: the depths (camera z) of the scans' points, 1-99 %, recomputed
    _, interim, _ = synthetic
    z = np.concatenate([pd.read_parquet(interim / "points" / f"{s}.parquet")["z_cam"].to_numpy()
                        for s in SCANS])
    v = report_data.metrics["validation"]
    assert v["volume_z_mm"] == pytest.approx(np.quantile(z, [0.01, 0.99]), rel=1e-3)
    assert "scans measured" in v["volume_from"]
    # a configured volume wins
    m = build_report(*synthetic, config={"report": {"metrology": {"volume_z_mm": [100, 200]}}})
    assert m.metrics["validation"]["volume_z_mm"] == [100.0, 200.0]
    assert "configuration" in m.metrics["validation"]["volume_from"]


def test_summary_rows_are_the_measured_figures(report_data):
    m = report_data.metrics
    rows = {(r["id"], r["scan"]): r for r in m["summary"]}
    t = m["provenance"]["tolerances"]
    g = m["scans"]["gauge"]
    assert rows["gauge_mean_error_mm", "gauge"]["value"] == g["measurement"]["error_mm"]
    assert rows["gauge_mean_error_mm", "gauge"]["tolerance"] == t["gauge_mean_error_mm"] == 0.003
    assert rows["gauge_std_mm", "gauge"]["value"] == g["measurement"]["std_mm"]
    assert rows["ab_height_difference_mm", "gauge"]["value"] == g["a_vs_b"]["A_minus_B"]["height_mm"]
    assert rows["plane_within_share", "plate"]["value"] == \
        m["scans"]["plate"]["measurement"]["share_within_band"]
    ball = m["scans"]["ball"]["measurement"]
    stat = m["provenance"]["metrology"]["sphere_form_statistic"]
    assert rows["sphere_form_error_mm", "ball"]["value"] == ball[FORM_KEYS[stat]]
    assert rows["sphere_form_error_d95_mm", "ball"]["value"] == ball["form_error_d95_mm"]
    assert rows["sphere_form_error_vdi_mm", "ball"]["value"] == ball["form_error_vdi_mm"]
    assert ball["form_error_d95_mm"] <= ball["form_error_vdi_mm"] <= ball["form_error_mm"]
    plate = m["scans"]["plate"]["measurement"]
    assert rows["plane_flatness_mm", "plate"]["value"] == plate["flatness_mm"] >= plate["flatness_95_mm"]
    for r in m["summary"]:
        if r["tolerance"] is not None:
            v = abs(r["value"]) if r["abs"] else r["value"]
            ok = v <= r["tolerance"] if r["comparison"] == "<=" else v >= r["tolerance"]
            assert r["status"] == ("PASS" if ok else "FAIL")


def test_pages_show_the_numbers_of_metrics(report_data):
    m = report_data.metrics
    figs = build_pages(m, report_data.plots)
    texts = [" ".join(page_texts(f)) for f in figs]
    first = texts[0]
    for r in m["summary"]:
        assert fmt_row_value(r) in first and fmt_tolerance(r) in first and r["status"] in first
    assert "2024-05-17" in first and m["result"] in first
    gauge_page = next(t for t in texts if "Scan 'gauge'" in t)
    g = m["scans"]["gauge"]["measurement"]
    for s in (fmt(g["mean_mm"], "mm"), fmt(g["std_mm"], "mm"), fmt(g["nominal_mm"], "mm"),
              fmt(g["n"]), fmt(m["scans"]["gauge"]["counts"]["gain_over_single_line"], "", 3)):
        assert s in gauge_page, s
    plate_page = next(t for t in texts if "Scan 'plate'" in t)
    p = m["scans"]["plate"]["measurement"]
    assert fmt(p["share_within_band"], "%") in plate_page
    assert fmt(p["flatness_95_mm"], "mm") in plate_page
    ball_page = next(t for t in texts if "Scan 'ball'" in t)
    b = m["scans"]["ball"]["measurement"]
    assert fmt(b["diameter_mm"], "mm") in ball_page and fmt(b["form_error_d95_mm"], "mm") in ball_page
    val = next(t for t in texts if "Validation against truth" in t)
    assert fmt(m["validation"]["camera"]["rms_px"], "px") in val
    assert any("Validation: 'part'" in t for t in texts)
    prov = " ".join(t for t in texts if "Provenance" in t)
    for f in m["provenance"]["inputs"]:
        assert f["sha256"] in prov
    for name in ("Calibration: camera", "Calibration: laser planes", "Calibration: hand-eye"):
        assert any(name in t for t in texts)
    assert f"page {len(figs)} of {len(figs)}" in texts[-1]


def test_camera_page_names_the_board_s_corner_method(report_data):
    """Circle grids: the bias correction's state; chessboards: the X-junction fit (no bias)."""
    import copy

    def camera_page(m):
        return next(" ".join(page_texts(f)) for f in build_pages(m, report_data.plots)
                    if "Calibration: camera" in " ".join(page_texts(f)))

    m = copy.deepcopy(report_data.metrics)
    assert "circle-centre bias correction" in camera_page(m)
    m["calibration"]["camera"]["board"] = {"pattern": "chessboard", "cols": 12, "rows": 9, "spacing": 4.0}
    page = camera_page(m)
    assert "chessboard corners fitted as X-junctions" in page and "circle-centre" not in page


@pytest.mark.slow
def test_run_twice_same_bytes_and_inputs_hashed(synthetic, tmp_path):
    raw, interim, processed = synthetic
    cfg = {"report": {"tolerances": {"gauge_std_mm": 0.006}}, "fuse": {"voxel_mm": 0.0}}
    run_report(raw, interim, processed, tmp_path / "a.pdf", tmp_path / "a.json", config=cfg)
    run_report(raw, interim, processed, tmp_path / "b.pdf", tmp_path / "b.json", config=cfg)
    assert _sha(tmp_path / "a.pdf") == _sha(tmp_path / "b.pdf")
    assert _sha(tmp_path / "a.json") == _sha(tmp_path / "b.json")
    pdf = (tmp_path / "a.pdf").read_bytes()
    assert b"CreationDate" not in pdf and b"ModDate" not in pdf
    m = json.loads((tmp_path / "a.json").read_text())
    assert m["provenance"]["parameters"] == cfg
    roots = {"capture": raw, "interim": interim, "processed": processed}
    for f in m["provenance"]["inputs"]:
        assert f["sha256"] == _sha(roots[f["root"]] / f["file"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "a.pdf", "b.json", "b.pdf"]


@pytest.mark.slow
def test_pdf_text_carries_the_numbers(synthetic, tmp_path):
    from pypdf import PdfReader

    raw, interim, processed = synthetic
    m = run_report(raw, interim, processed, tmp_path / "r.pdf", tmp_path / "r.json")
    text = "\n".join(page.extract_text() for page in PdfReader(tmp_path / "r.pdf").pages)
    for r in m["summary"]:
        assert fmt_row_value(r).replace("−", "-") in text.replace("−", "-")
    assert fmt(m["scans"]["gauge"]["measurement"]["mean_mm"], "mm") in text


def test_tolerances_from_the_config_decide(synthetic, report_data, tmp_path):
    raw, interim, processed = synthetic
    strict = {"report": {"tolerances": {"gauge_std_mm": 0.001}}}
    m = build_report(raw, interim, processed, config=json.dumps(strict)).metrics
    row = next(r for r in m["summary"] if r["id"] == "gauge_std_mm")
    assert row["tolerance"] == 0.001 and row["status"] == "FAIL" and m["result"] == "FAIL"
    # a file works as well as JSON text
    (tmp_path / "cfg.json").write_text(json.dumps(strict))
    assert load_config(tmp_path / "cfg.json")[1]["gauge_std_mm"] == 0.001
    with pytest.raises(Exception, match="sphere_form_statistic"):
        load_config({"report": {"metrology": {"sphere_form_statistic": "median"}}})


@pytest.mark.slow
def test_capture_without_truth_date_or_calibrations(synthetic, tmp_path):
    raw, interim, processed = synthetic
    cap = tmp_path / "measured"
    shutil.copytree(raw, cap)
    (cap / "truth.json").unlink()
    rig = (cap / "rig.yaml").read_text().replace("capture_date: '2024-05-17'\n", "")
    (cap / "rig.yaml").write_text(rig)
    inter = tmp_path / "interim"
    shutil.copytree(interim, inter)
    (inter / "calibration" / "handeye.json").unlink()
    m = run_report(cap, inter, processed, tmp_path / "r.pdf", tmp_path / "r.json")
    assert m["validation"] is None and m["capture"]["date"] is None
    assert "handeye" not in m["calibration"]
    assert all("truth" not in s for s in m["scans"].values())
    assert m["scans"]["gauge"]["measurement"]["n"] > 100
    data = build_report(cap, inter, processed)
    texts = [" ".join(page_texts(f)) for f in build_pages(data.metrics, data.plots)]
    assert "not recorded (no capture_date in rig.yaml)" in texts[0]
    assert not any("Validation" in t for t in texts)
    assert any("No handeye.json" in t for t in texts)


def test_scan_page_warns_of_an_arm_noisier_than_stated(report_data):
    """The fuse stage's prior beside the hand-eye views' estimate of the arm's noise: the scan's
    page names both, and warns where the views measured it over 3x the stated precision."""
    import copy

    def gauge_page(ratio: float) -> str:
        m = copy.deepcopy(report_data.metrics)
        m["scans"]["gauge"]["counts"].setdefault("fused", {})["arm_prior"] = {
            "source": "stated (arm_precision_mm)", "precision_mm": 0.02, "sigma_mm": 0.00577,
            "handeye_sigma_mm": 0.00577 * ratio, "handeye_ratio": ratio}
        texts = [" ".join(page_texts(f)) for f in build_pages(m, report_data.plots)]
        return next(t for t in texts if "Scan 'gauge'" in t)

    noisy, fine = gauge_page(9.2), gauge_page(1.5)
    assert "arm prior 0.020 mm" in noisy and "measured 9.2× that" in noisy
    assert "The hand-eye views put the arm's noise at 9.2× the stated precision" in noisy
    assert "measured 1.5× that" in fine and "put the arm's noise" not in fine


def test_missing_cloud_falls_back_to_points(synthetic, tmp_path):
    raw, interim, processed = synthetic
    proc = tmp_path / "processed"
    shutil.copytree(processed, proc)
    (proc / "plate.ply").unlink()
    m = build_report(raw, interim, proc).metrics
    assert m["scans"]["plate"]["cloud_source"].startswith("points/plate.parquet")
    assert m["scans"]["plate"]["measurement"]["n"] == m["scans"]["plate"]["counts"]["points"]


@pytest.mark.slow
def test_cli_report(synthetic, tmp_path):
    from crossline.cli import main

    raw, interim, processed = synthetic
    cfg = json.dumps({"report": {"tolerances": {"plane_within_share": 0.5}}})
    rc = main(["report", str(raw), "--interim", str(interim), "--processed", str(processed),
               "--config-json", cfg, "--pdf", str(tmp_path / "a.pdf"),
               "--metrics", str(tmp_path / "m.json")])
    assert rc == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert next(r for r in m["summary"] if r["id"] == "plane_within_share")["tolerance"] == 0.5
    assert main(["report", str(tmp_path), "--interim", str(interim), "--processed",
                 str(processed), "--pdf", str(tmp_path / "x.pdf"),
                 "--metrics", str(tmp_path / "x.json")]) == 2


def test_read_mesh_is_exact(tmp_path):
    import open3d as o3d

    from crossline.report.accuracy import read_mesh

    rng = np.random.default_rng(3)
    V = rng.uniform(-500, 500, (50, 3)) + 1e-7 * rng.random((50, 3))  # digits float32 would lose
    F = rng.integers(0, 50, (80, 3))
    try:
        from crossline.sim.part import write_ply
    except ImportError:  # pragma: no cover - the simulator's writer, if present
        write_ply = None
    if write_ply is not None:
        write_ply(tmp_path / "sim.ply", V, F)
        V2, F2 = read_mesh(tmp_path / "sim.ply")
        assert np.array_equal(V2, V) and np.array_equal(F2, F)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F))
    o3d.io.write_triangle_mesh(str(tmp_path / "o3d.ply"), m)
    V3, F3 = read_mesh(tmp_path / "o3d.ply")
    assert np.allclose(V3, V, rtol=0, atol=1e-4) and np.array_equal(F3, F)


def test_nominal_comparison_and_its_page(tmp_path, report_data):
    """A freeform cloud against its nominal STL through the report's own path: aligned, the
    support plane left out, the share within the band counted again here, and the page."""
    from crossline.report.accuracy import DEFAULT_METROLOGY, DEFAULT_TOLERANCES, _nominal_comparison
    from crossline.report.nominal import load_nominal, signed_deviation
    from crossline.report.pages import page_nominal
    from crossline.sim.part import write_stl
    from tests.test_nominal import _part_mesh, _sample

    V, F = _part_mesh()
    keep = V[:, 2] >= 0  # an open drawing: the part cut at z = 0, where it stands
    F = F[keep[F].all(axis=1)]
    write_stl(tmp_path / "part.stl", V, F)
    rng = np.random.default_rng(5)
    p, _ = _sample(V, F, 20000, rng)
    p = p + rng.normal(0.0, 0.004, p.shape)
    table = np.column_stack([rng.uniform(-50, 50, 3000), rng.uniform(-40, 40, 3000),
                             rng.normal(0.0, 0.004, 3000)])
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T[:3, 3] = [400.0, 80.0, -30.0]
    cloud = np.vstack([p, table]) @ T[:3, :3].T + T[:3, 3]
    nc, plots = _nominal_comparison(cloud, tmp_path / "part.stl", DEFAULT_TOLERANCES,
                                    DEFAULT_METROLOGY)
    A = np.asarray(nc["T_nominal_cloud"]) @ T
    assert np.allclose(A[:3, :3], np.eye(3), atol=1e-5) and np.allclose(A[:3, 3], 0, atol=2e-3)
    assert nc["n_support"] >= 0.9 * len(table) and nc["n"] <= len(p)
    Vn, Fn = load_nominal(tmp_path / "part.stl")
    d = signed_deviation(p, Vn, Fn)
    above = p[:, 2] > nc["support_margin_mm"]
    assert nc["share_within_tolerance"] == pytest.approx(np.mean(np.abs(d[above]) <= 0.05), abs=2e-3)
    m = json.loads(json.dumps(report_data.metrics))
    m["scans"]["part"]["nominal_comparison"] = nc
    text = " ".join(page_texts(page_nominal(m, "part", {"nominal": plots})))
    assert f"{fmt(nc['share_within_tolerance'], '%')} of {fmt(nc['n'])} points" in text
    assert "RANSAC on FPFH features" in text


def test_deviation_cloud_is_the_compared_points_coloured_as_on_the_page(tmp_path, report_data):
    """The report's coloured cloud of a freeform scan: the aligned points, their signed
    deviation as a scalar field, coloured on the page's scale; a folder without a compared
    scan is still made (the workflow's output)."""
    import open3d as o3d

    from crossline.report.accuracy import (
        DEFAULT_METROLOGY,
        DEFAULT_TOLERANCES,
        ReportData,
        _nominal_comparison,
        deviation_limit_mm,
        write_deviation_clouds,
    )
    from crossline.report.nominal import deviation_colours
    from crossline.sim.part import write_stl
    from tests.test_nominal import _part_mesh, _sample

    V, F = _part_mesh()
    write_stl(tmp_path / "part.stl", V, F)
    rng = np.random.default_rng(7)
    p, _ = _sample(V, F, 5000, rng)
    nc, plots = _nominal_comparison(p + rng.normal(0.0, 0.004, p.shape), tmp_path / "part.stl",
                                    DEFAULT_TOLERANCES, DEFAULT_METROLOGY)
    data = ReportData({"scans": {"part": {"nominal_comparison": nc}, "plate": {}}},
                      {"scans": {"part": {"nominal": plots}, "plate": {}}})
    written = write_deviation_clouds(data, tmp_path / "dev")
    assert written == [tmp_path / "dev" / "part.ply"]
    pc = o3d.t.io.read_point_cloud(str(written[0]))
    assert np.allclose(pc.point.positions.numpy(), plots["points"])
    dev = pc.point.deviation.numpy().ravel()
    assert np.array_equal(dev, plots["dev"]) and len(dev) > 4000
    want = np.rint(deviation_colours(dev, deviation_limit_mm(dev, nc["tolerance_mm"])) * 255)
    assert np.array_equal(pc.point.colors.numpy(), want.astype(np.uint8))
    assert write_deviation_clouds(ReportData({"scans": {}}, {"scans": {}}), tmp_path / "none") == []
    assert (tmp_path / "none").is_dir()


def test_table_cells_wrap_inside_their_column():
    """A note longer than its column wraps onto more lines of its row instead of running
    under the next column or off the page; short cells stay on one line."""
    import matplotlib

    from crossline.report.pages_common import LEFT, RC, RIGHT, Page

    note = "+1.42 (U 0.0085 mm; NOT covered: U misses a contributor, far longer than its column)"
    xs = [LEFT, LEFT + 0.14, LEFT + 0.62]
    with matplotlib.rc_context(RC):
        p = Page({"capture": {"name": "c"}}, "s")
        y0 = p.y
        p.table(["Scan", "Figure", "Error"], [["ball", "error / U (k = 2), E_n", note],
                                              ["gauge", "mean height", "-0.0027 mm"]], xs)
        fig = p.fig
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        r = FigureCanvasAgg(fig).get_renderer()
        texts = [t for t in fig.texts if t.get_position()[0] == xs[2] and t.get_position()[1] <= y0]
        parts = [t.get_text() for t in texts]
        # the header, the note on several lines, the short cell on one
        assert parts[0] == "Error" and parts[-1] == "-0.0027 mm" and len(parts) >= 4
        assert " ".join(parts[1:-1]) == note
        right = max(t.get_window_extent(r).x1 for t in texts) / fig.bbox.width
        assert right <= RIGHT + 1e-3
        ys = [t.get_position()[1] for t in texts]
        assert np.all(np.diff(ys) < 0)  # one line below the other, in order

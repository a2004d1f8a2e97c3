"""The Snakemake workflow end to end on a quick capture: lint, partial re-runs, determinism,
bad captures beside good ones, interruption.

Each test works in its own copy of the workflow (Snakefile, rules, schema, profile and the
crossline sources that the rules declare as inputs), so editing a module or a parameter
there does not disturb the repository or other tests.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.conftest import REPO

pytestmark = pytest.mark.slow

SNAKEMAKE = [sys.executable, "-m", "snakemake"]


def make_workdir(root: Path, captures: dict[str, Path], **overrides) -> Path:
    """A private copy of the workflow with ``captures`` linked under data/raw."""
    root.mkdir(parents=True, exist_ok=True)
    shutil.copy(REPO / "Snakefile", root)
    for d in ("workflow", "profiles", "crossline"):
        shutil.copytree(REPO / d, root / d, ignore=shutil.ignore_patterns("__pycache__"))
    cfg = yaml.safe_load((REPO / "config.yaml").read_text())
    cfg["captures"] = list(captures)
    cfg["simulate"] = {}
    for key, value in overrides.items():
        section, _, name = key.partition("__")
        cfg[section][name] = value
    (root / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    (root / "data" / "raw").mkdir(parents=True, exist_ok=True)
    for name, path in captures.items():
        (root / "data" / "raw" / name).symlink_to(path, target_is_directory=True)
    return root


def set_config(workdir: Path, section: str, key: str, value) -> None:
    cfg = yaml.safe_load((workdir / "config.yaml").read_text())
    cfg[section][key] = value
    (workdir / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))


def snakemake(workdir: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [*SNAKEMAKE, "--cores", "2", *args], cwd=workdir, capture_output=True, text=True,
        timeout=900,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake {' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}")
    return proc


def planned_jobs(workdir: Path, *args: str) -> dict[str, int]:
    """Rule -> job count of a dry run (from Snakemake's job-stats table)."""
    proc = snakemake(workdir, "-n", *args)
    text = proc.stdout + proc.stderr
    if "Nothing to be done" in text:
        return {}
    table = text.split("Job stats:", 1)[1].split("total", 1)[0]
    jobs = {}
    for line in table.splitlines():
        m = re.fullmatch(r"\s*(\w+)\s+(\d+)\s*", line)
        if m:
            jobs[m.group(1)] = int(m.group(2))
    jobs.pop("all", None)
    return jobs


def outputs(workdir: Path) -> dict[str, bytes]:
    """Every artefact of a run, by path relative to the workdir."""
    files = {}
    for top in ("data/interim", "data/processed", "reports"):
        for p in sorted((workdir / top).rglob("*")):
            if p.is_file():
                files[str(p.relative_to(workdir))] = p.read_bytes()
    return files


@pytest.fixture(scope="module")
def done_workdir(tmp_path_factory, quick_capture: Path) -> Path:
    """A workdir in which the whole workflow has run once on the quick capture."""
    wd = make_workdir(tmp_path_factory.mktemp("wf") / "run", {"q": quick_capture})
    snakemake(wd)
    return wd


def test_lint_clean() -> None:
    proc = subprocess.run([*SNAKEMAKE, "--lint"], cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Congratulations, your workflow is in a good condition!" in proc.stdout + proc.stderr


def test_full_run_outputs(done_workdir: Path) -> None:
    wd = done_workdir
    for f in ("camera.json", "lasers.json", "handeye.json"):
        assert (wd / "data/interim/q/calibration" / f).is_file()
    scans = sorted(json.loads((wd / "data/interim/q/check.json").read_text())["scans"])
    assert scans
    for s in scans:
        assert (wd / f"data/interim/q/points/{s}.parquet").is_file()
        assert (wd / f"data/processed/q/{s}.ply").is_file()
    assert (wd / "reports/q/accuracy.pdf").read_bytes().startswith(b"%PDF")
    # a full capture gets the calibration certificate too
    assert (wd / "reports/q/calibration.pdf").read_bytes().startswith(b"%PDF")
    assert json.loads((wd / "reports/q/calibration.json").read_text())["handeye"]
    assert planned_jobs(wd) == {}


def test_export_formats_add_the_e57_clouds(done_workdir: Path, tmp_path: Path) -> None:
    """export.formats [e57]: one export job per scan and nothing else; the rule's E57 holds
    the points of its PLY (read back with Open3D), in mm. (One scan's job is run: the
    writer itself is tested in test_clouds.py.)"""
    import open3d as o3d

    from crossline.io.clouds import read_e57

    wd = tmp_path / "export"
    shutil.copytree(done_workdir, wd, symlinks=True)
    cfg = yaml.safe_load((wd / "config.yaml").read_text())
    cfg["export"] = {"formats": ["e57"]}
    (wd / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    scans = sorted(json.loads((wd / "data/interim/q/check.json").read_text())["scans"])
    assert planned_jobs(wd) == {"export_cloud": len(scans)}
    s = scans[0]
    snakemake(wd, f"data/processed/q/{s}.e57")
    ply = np.asarray(o3d.io.read_point_cloud(str(wd / f"data/processed/q/{s}.ply")).points)
    e57 = read_e57(wd / f"data/processed/q/{s}.e57")["points"]
    assert len(ply) > 100
    np.testing.assert_allclose(e57, ply, atol=1e-6)
    assert planned_jobs(wd) == {"export_cloud": len(scans) - 1}


def _rerun_set(done: Path, tmp: Path, section: str, key: str, value) -> dict[str, int]:
    wd = tmp / "copy"
    shutil.copytree(done, wd, symlinks=True)
    set_config(wd, section, key, value)
    return planned_jobs(wd)


def test_changing_T_reruns_labelling_onward(done_workdir: Path, tmp_path: Path) -> None:
    n = len(json.loads((done_workdir / "data/interim/q/check.json").read_text())["scans"])
    jobs = _rerun_set(done_workdir, tmp_path, "points", "threshold_px", 12.5)
    assert jobs == {"triangulate_points": n, "fuse_points": n, "render_report": 1}


def test_changing_extractor_reruns_extraction_onward(done_workdir: Path, tmp_path: Path) -> None:
    n = len(json.loads((done_workdir / "data/interim/q/check.json").read_text())["scans"])
    jobs = _rerun_set(done_workdir, tmp_path, "stripes", "extractor", "steger")
    assert jobs == {
        "extract_stripes": n, "triangulate_points": n, "fuse_points": n, "render_report": 1,
    }


def test_changing_camera_option_reruns_all_that_uses_the_camera(
    done_workdir: Path, tmp_path: Path
) -> None:
    n = len(json.loads((done_workdir / "data/interim/q/check.json").read_text())["scans"])
    jobs = _rerun_set(done_workdir, tmp_path, "camera", "outlier_factor", 4.0)
    assert jobs == {
        "calibrate_camera": 1, "calibrate_lasers": 1, "calibrate_handeye": 1,
        "triangulate_points": n, "fuse_points": n, "render_report": 1,
        "calibration_certificate": 1,
    }


def test_editing_a_module_reruns_its_stages(done_workdir: Path, tmp_path: Path) -> None:
    n = len(json.loads((done_workdir / "data/interim/q/check.json").read_text())["scans"])
    wd = tmp_path / "copy"
    shutil.copytree(done_workdir, wd, symlinks=True)
    module = wd / "crossline" / "scan" / "stripes.py"
    module.write_text(module.read_text() + "\n# an edit\n")
    jobs = planned_jobs(wd)
    # the laser-plane calibration centres its stripes with the same extractor
    assert jobs == {
        "calibrate_lasers": 1, "extract_stripes": n,
        "triangulate_points": n, "fuse_points": n, "render_report": 1,
        "calibration_certificate": 1,
    }
    # the report module is imported by the two reports alone (the certificate shares its
    # calibration summary), the certificate's pages by the certificate alone
    wd2 = tmp_path / "copy2"
    shutil.copytree(done_workdir, wd2, symlinks=True)
    report = wd2 / "crossline" / "report" / "accuracy.py"
    report.write_text(report.read_text() + "\n# an edit\n")
    assert planned_jobs(wd2) == {"render_report": 1, "calibration_certificate": 1}
    wd3 = tmp_path / "copy3"
    shutil.copytree(done_workdir, wd3, symlinks=True)
    pages = wd3 / "crossline" / "report" / "certificate_pages.py"
    pages.write_text(pages.read_text() + "\n# an edit\n")
    assert planned_jobs(wd3) == {"calibration_certificate": 1}


@pytest.mark.e2e  # after the suite (make e2e-workflow): a whole second run
def test_deterministic_across_runs_and_cores(done_workdir: Path, tmp_path: Path) -> None:
    first = outputs(done_workdir)
    wd = make_workdir(tmp_path / "again", {"q": (done_workdir / "data/raw/q").resolve()})
    snakemake(wd, "--cores", "1")
    second = outputs(wd)
    assert sorted(first) == sorted(second)
    differ = [k for k in first if first[k] != second[k]]
    assert differ == [], f"artefacts differ between runs: {differ}"


@pytest.mark.e2e  # after the suite (make e2e-workflow)
def test_chunked_extraction_gives_identical_points(done_workdir: Path, tmp_path: Path) -> None:
    wd = tmp_path / "chunks"  # the calibrations are kept: the chunks change extraction only
    shutil.copytree(done_workdir, wd, symlinks=True)
    set_config(wd, "stripes", "chunks", 3)
    scans = sorted(json.loads((done_workdir / "data/interim/q/check.json").read_text())["scans"])
    targets = [f"data/interim/q/points/{s}.parquet" for s in scans]
    snakemake(wd, *targets)
    for s in scans:  # the copies' points were made again, from three chunks each
        assert (wd / f"logs/q/extract_stripes/{s}.part2-of-3.log").is_file(), s
    for t in targets:
        assert (wd / t).read_bytes() == (done_workdir / t).read_bytes(), t


@pytest.mark.e2e  # after the suite (make e2e-workflow): a whole second run
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["ctrl-c", "kill-9"])
def test_interrupted_run_completes_identically(done_workdir: Path, tmp_path: Path, sig) -> None:
    wd = make_workdir(tmp_path / "kill", {"q": (done_workdir / "data/raw/q").resolve()})
    proc = subprocess.Popen(
        [*SNAKEMAKE, "--cores", "2"], cwd=wd, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL, start_new_session=True,
    )
    # wait until stripe extraction (a heavy stage) is under way, then interrupt
    deadline = time.time() + 600
    while time.time() < deadline and not (wd / "logs/q/extract_stripes").is_dir():
        time.sleep(0.1)
    time.sleep(0.5)
    if sig == signal.SIGKILL:
        os.killpg(proc.pid, sig)  # power cut: snakemake and its jobs die at once
    else:
        os.kill(proc.pid, sig)
    proc.wait(timeout=120)
    assert proc.returncode != 0
    assert not (wd / "reports/q/accuracy.pdf").exists()
    leftovers = [p for p in (wd / "data").rglob("*.tmp")]
    if sig == signal.SIGKILL:
        snakemake(wd, "--unlock")
    snakemake(wd)
    assert outputs(wd) == outputs(done_workdir)
    assert not [p for p in leftovers if p.exists()], "stale temporary files were not cleared"


def test_bad_captures_beside_a_good_one(done_workdir: Path, tmp_path: Path) -> None:
    """Each broken capture fails at its stage with a message naming the file and the fault,
    leaves no output of that stage, and the good capture and good scans still go through."""
    from tests.broken import break_capture

    wd = tmp_path / "bad"
    shutil.copytree(done_workdir, wd, symlinks=True)
    good = (done_workdir / "data/raw/q").resolve()
    faults = ["empty", "corrupt_png", "nan_pose", "misspelt_rig_key", "rig_wrong_type", "table_faults",
              "wrong_size", "few_views", "scan_faults", "degenerate_handeye"]
    for f in faults:
        break_capture(good, tmp_path / "raw" / f, f)
        (wd / "data/raw" / f).symlink_to(tmp_path / "raw" / f, target_is_directory=True)
    cfg = yaml.safe_load((wd / "config.yaml").read_text())
    cfg["captures"] = ["q", *faults]
    (wd / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    before = outputs(done_workdir)
    proc = snakemake(wd, "--keep-going", check=False)
    assert proc.returncode != 0

    def log(capture: str, name: str) -> str:
        return (wd / "logs" / capture / name).read_text()

    interim = wd / "data/interim"
    expect_check = {
        "empty": "is empty; expected rig.yaml, calibration/ and scans/",
        "corrupt_png": "scans/plate/frames/000005.png: truncated PNG",
        "nan_pose": "calibration/handeye/poses.csv, line 4: 'y' = nan is not a finite pose value",
        "misspelt_rig_key": "rig.yaml: unknown key 'frame_rat' (misspelt 'frame_rate'?)",
        "rig_wrong_type": "rig.yaml: 'rig.frame_rate' must be a number, got 'fast'",
        "wrong_size": "scans/part/frames/000002.png: image is 2658x792 px, expected the scan window "
                      "2658x800 px",
    }
    for capture, message in expect_check.items():
        assert message in log(capture, "check.log"), capture
        assert not (interim / capture).exists(), capture
    # one check finds every table fault, one line each, and not their consequences
    text = log("table_faults", "check.log")
    csv = "scans/{}/frames.csv, line {}: "
    for message in [
        "calibration/handeye/poses.csv: has 7 pose rows for 8 hand-eye images",
        "calibration/handeye/pose_07.png: has no row in calibration/handeye/poses.csv",
        csv.format("gauge", 3) + "unknown laser state 'C'; expected one of A, B, AB, off",
        csv.format("gauge", 5) + "quaternion (qw, qx, qy, qz) has length 1.1",
        csv.format("plate", 25) + "has 9 fields, expected 10",
        csv.format("ball", 1) + "missing column(s) ['qz']",
    ]:
        assert message in text, message
    assert "7 problems" in text and "scans/ball/frames/000000.png" not in text
    assert not (interim / "table_faults").exists()
    # too few views: the camera calibration names every view and why it was not used
    text = log("few_views", "calibrate_camera.log")
    assert "needs at least 6 usable views, got 2 of 22" in text
    assert all(f"camera/view_{i:02d}.png" in text for i in range(2, 8))
    assert not (interim / "few_views/calibration/camera.json").exists()
    # hand-eye views that all turn about one axis: the camera and lasers still calibrate,
    # hand-eye fails with what is wrong and what to do, and nothing after it is made
    text = log("degenerate_handeye", "calibrate_handeye.log")
    assert ("degenerate hand-eye motion: all 28 rotating motion pairs turn about nearly the same "
            "axis") in text
    assert ("Re-take the hand-eye views (calibration/handeye) rotating the scanner about at least "
            "two different axes between views") in text
    # images and poses agree: no pair or view is rejected for mismatching rotation angles
    assert "rejected: rotation angles" not in text and "matching rotation angles" not in text
    cal = interim / "degenerate_handeye/calibration"
    assert (cal / "camera.json").is_file() and (cal / "lasers.json").is_file()
    assert not (cal / "handeye.json").exists()
    assert not (interim / "degenerate_handeye/points").exists()
    assert not (wd / "data/processed/degenerate_handeye").exists()
    assert not (wd / "reports/degenerate_handeye").exists()
    # scan faults: the broken scans fail, the capture's other scans are processed
    assert "scan gauge: no stripe centre could be labelled A or B" in log(
        "scan_faults", "triangulate_points/gauge.log")
    assert "scan plate: no stripe found in any of its 24 frames" in log(
        "scan_faults", "extract_stripes/plate.log")
    points = interim / "scan_faults/points"
    assert not (points / "gauge.parquet").exists() and not (points / "plate.parquet").exists()
    assert (points / "ball.parquet").is_file() and (points / "part.parquet").is_file()
    # its calibrations are sound, so it gets its certificate; with scans broken, no report
    assert (wd / "reports/scan_faults/calibration.pdf").is_file()
    assert not (wd / "reports/scan_faults/accuracy.pdf").exists()
    # nothing of the good capture was redone or changed, no temporary file left anywhere
    after = {k: v for k, v in outputs(wd).items() if "/q/" in k or k.startswith("reports/q/")}
    assert after == before
    assert not list((wd / "data").rglob("*.tmp"))


@pytest.mark.parametrize("name", ["with space", "a/b"])
def test_capture_name_with_space_or_slash_stops_before_any_job(tmp_path: Path, name: str) -> None:
    wd = make_workdir(tmp_path / "names", {})
    cfg = yaml.safe_load((wd / "config.yaml").read_text())
    cfg["captures"] = [name]
    (wd / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    proc = snakemake(wd, "-n", check=False)
    assert proc.returncode != 0
    assert (f"config.yaml: capture name {name!r} is not allowed: use letters, digits, '_', '-' "
            "and '.', no spaces or slashes") in proc.stdout + proc.stderr
    assert not (wd / "data/interim").exists()


def test_config_value_out_of_range_names_the_key(tmp_path: Path) -> None:
    wd = make_workdir(tmp_path / "schema", {}, points__threshold_px=-3)
    proc = snakemake(wd, "-n", check=False)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "threshold_px" in text and "-3" in text and "exclusiveMinimum" in text


# ----------------------------------------------------------------------------- partial captures


def _rig_without(rig: Path, dest: Path, *, scans: list[str] | None = None,
                 lasers: list[str] | None = None) -> None:
    """rig.yaml of ``rig`` with only ``scans`` (none: no scans key) and, if given, ``lasers``."""
    data = yaml.safe_load(rig.read_text())
    if scans is None:
        data.pop("scans", None)
    else:
        data["scans"] = {k: v for k, v in data["scans"].items() if k in scans}
    if lasers is not None:
        data["lasers"] = lasers
    (dest / "rig.yaml").write_text(yaml.safe_dump(data, sort_keys=False))


def calibration_only(good: Path, dest: Path) -> Path:
    """The capture's calibration views alone: no scans/ and no scans in rig.yaml."""
    dest.mkdir(parents=True)
    shutil.copytree(good / "calibration", dest / "calibration", copy_function=os.link)
    shutil.copy(good / "truth.json", dest)
    _rig_without(good / "rig.yaml", dest)
    return dest


def without_handeye(good: Path, dest: Path) -> Path:
    """Camera and laser views, scans, but no hand-eye views: the scans cannot be measured."""
    shutil.copytree(good, dest, copy_function=os.link,
                    ignore=lambda d, names: ["handeye"] if Path(d).name == "calibration" else [])
    return dest


def one_laser(good: Path, dest: Path, scans: tuple[str, ...] = ("gauge", "plate", "ball")) -> Path:
    """A one-line rig's capture from a two-laser one: laser A's views and its frames alone.

    A frame lit by laser A alone is what a rig with laser A only records; its arm pose and
    time stay, so each scan keeps every third frame of the pattern A, B, AB.
    """
    dest.mkdir(parents=True)
    cal = dest / "calibration"
    shutil.copytree(good / "calibration", cal, copy_function=os.link,
                    ignore=lambda d, names: [n for n in names if n.startswith("laser_B")])
    shutil.copy(good / "truth.json", dest)
    for s in scans:
        src, out = good / "scans" / s, dest / "scans" / s
        (out / "frames").mkdir(parents=True)
        rows = (src / "frames.csv").read_text().splitlines()
        kept = [r for r in rows[1:] if r.split(",")[2] == "A"]
        assert kept and len(kept) < len(rows) - 1
        (out / "frames.csv").write_text("\n".join([rows[0], *kept]) + "\n")
        for r in kept:
            name = f"{int(r.split(',')[0]):06d}.png"
            os.link(src / "frames" / name, out / "frames" / name)
    _rig_without(good / "rig.yaml", dest, scans=list(scans), lasers=["A"])
    return dest


@pytest.fixture(scope="module")
def partial_workdir(tmp_path_factory, quick_capture: Path) -> Path:
    """One plain `snakemake` over a calibration-only, a hand-eye-less and a one-laser capture."""
    root = tmp_path_factory.mktemp("partial")
    caps = {"cal": calibration_only(quick_capture, root / "raw" / "cal"),
            "nohe": without_handeye(quick_capture, root / "raw" / "nohe"),
            "one": one_laser(quick_capture, root / "raw" / "one")}
    wd = make_workdir(root / "run", caps)
    proc = snakemake(wd)
    (wd / "snakemake.out").write_text(proc.stdout + proc.stderr)
    return wd


def test_calibration_only_capture_gets_its_certificate(partial_workdir: Path) -> None:
    wd = partial_workdir
    check = json.loads((wd / "data/interim/cal/check.json").read_text())
    assert check["stages"]["scans"]["allowed"] is False
    cert = json.loads((wd / "reports/cal/calibration.json").read_text())
    assert (wd / "reports/cal/calibration.pdf").read_bytes().startswith(b"%PDF")
    assert not (wd / "reports/cal/accuracy.pdf").exists()
    # no scan stage ran, and the run said why not
    assert not (wd / "logs/cal/extract_stripes").exists()
    assert not (wd / "data/interim/cal/points").exists()
    assert "capture cal: scans not run: rig.yaml describes no scans" in (
        wd / "snakemake.out").read_text()
    # every calibration with its figures, each check against its limit
    ids = {r["id"]: r for r in cert["checks"]}
    for key in ("camera_rms_px", "camera_view_rms_px", "projection_rms_px", "coverage_share",
                "laser_A_rms_mm", "laser_B_rms_mm", "handeye_consistency_mm"):
        assert ids[key]["status"] in ("PASS", "FAIL"), key
    assert cert["result"] == ("FAIL" if any(r["status"] == "FAIL" for r in cert["checks"])
                              else "PASS")
    cam = json.loads((wd / "data/interim/cal/calibration/camera.json").read_text())
    sigma = {p["name"]: p["sigma"] for p in cert["camera"]["parameters"]}
    assert sigma["fx"] == pytest.approx(cam["uncertainty"]["std"]["fx"])
    # the coverage counts every used view's board points once
    cov = cert["camera"]["coverage"]
    n_points = sum(len(r) for r in cam["residuals"].values())
    assert cov["points"] == n_points == int(np.sum(cov["counts"]))
    assert 0 < cov["share"] <= 1
    assert [p["pose"] for p in cert["lasers"]["A"]["poses"]]
    assert cert["handeye"]["board_consistency_mm"] > 0


def test_capture_without_handeye_calibrates_camera_and_lasers_only(partial_workdir: Path) -> None:
    wd = partial_workdir
    cal = wd / "data/interim/nohe/calibration"
    assert (cal / "camera.json").is_file() and (cal / "lasers.json").is_file()
    assert not (cal / "handeye.json").exists()
    assert not (wd / "reports/nohe/accuracy.pdf").exists()
    cert = json.loads((wd / "reports/nohe/calibration.json").read_text())
    assert cert["handeye"] is None and "calibration/handeye" in cert["handeye_missing"]
    assert "handeye_consistency_mm" not in {r["id"] for r in cert["checks"]}
    # the camera took no hand-eye views: none exist
    views = json.loads((cal / "camera.json").read_text())["views"]
    assert not [v for v in views if "handeye" in v["image"]]


def test_one_laser_capture_through_to_the_report(partial_workdir: Path) -> None:
    wd = partial_workdir
    lasers = json.loads((wd / "data/interim/one/calibration/lasers.json").read_text())
    assert "A" in lasers and "B" not in lasers
    metrics = json.loads((wd / "reports/one/metrics.json").read_text())
    assert (wd / "reports/one/accuracy.pdf").read_bytes().startswith(b"%PDF")
    assert (wd / "reports/one/calibration.pdf").is_file()
    for s in ("gauge", "plate", "ball"):
        tri = json.loads((wd / f"data/interim/one/points/{s}.json").read_text())
        assert tri["lasers"] == ["A"] and "B" not in tri["counts"]["labelled"]
        assert tri["counts"]["labelled"]["A"] == tri["points"] + sum(tri["counts"]["trimmed"].values())
        fused = json.loads((wd / f"data/processed/one/{s}.fuse.json").read_text())
        assert "needs stripes of both lasers" in fused["refine"]["skipped"]
        sc = metrics["scans"][s]
        assert "a_vs_b" not in sc or sc["a_vs_b"] is None
        assert "no laser B" in sc["a_vs_b_note"]
        assert set(sc["counts"]["points_by_laser"]) == {"A"}
    ids = {r["id"] for r in metrics["summary"]}
    assert "ab_height_difference_mm" not in ids and "ab_diameter_difference_mm" not in ids
    assert "gauge_mean_error_mm" in ids

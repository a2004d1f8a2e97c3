"""E57 export of fused clouds: exact round trip, an independent reader, same bytes."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pye57
import pytest

from crossline.errors import StageError
from crossline.fuse import FusedCloud, write_ply
from crossline.io.clouds import read_e57, write_e57


def _cloud(n: int = 5000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(n, 3)) * [40.0, 25.0, 5.0] + [120.0, -30.0, 310.0]
    N = rng.normal(size=(n, 3))
    return P, N / np.linalg.norm(N, axis=1, keepdims=True)


def test_e57_round_trip_is_exact_and_in_metres(tmp_path):
    """Doubles survive to the last bit; an independent reader (pye57) sees metres."""
    P, N = _cloud()
    write_e57(tmp_path / "a.e57", P, N)
    back = read_e57(tmp_path / "a.e57")
    assert np.array_equal(back["points"], P / 1000.0 * 1000.0)
    assert np.allclose(back["points"], P, atol=1e-12)
    assert np.allclose(back["normals"], N, atol=1e-6)  # normals are single precision
    e57 = pye57.E57(str(tmp_path / "a.e57"))
    raw = e57.read_scan_raw(0, ignore_unsupported_fields=True)
    e57.close()
    assert np.allclose(raw["cartesianX"], P[:, 0] / 1000.0, rtol=0, atol=1e-15)
    assert np.allclose(raw["cartesianZ"], P[:, 2] / 1000.0, rtol=0, atol=1e-15)


def test_e57_without_normals_reads(tmp_path):
    """Clouds from other programs (here pye57's writer) and ours without normals: points only."""
    P, _ = _cloud(800, seed=3)
    e57 = pye57.E57(str(tmp_path / "other.e57"), mode="w")
    e57.write_scan_raw({"cartesianX": P[:, 0] / 1000.0, "cartesianY": P[:, 1] / 1000.0,
                        "cartesianZ": P[:, 2] / 1000.0})
    e57.close()
    back = read_e57(tmp_path / "other.e57")
    assert set(back) == {"points"} and np.allclose(back["points"], P, atol=1e-9)
    write_e57(tmp_path / "ours.e57", P, None)
    back = read_e57(tmp_path / "ours.e57")
    assert set(back) == {"points"} and np.allclose(back["points"], P, atol=1e-12)


def test_e57_same_cloud_same_bytes_other_cloud_other_guid(tmp_path):
    P, N = _cloud()
    write_e57(tmp_path / "a.e57", P, N)
    write_e57(tmp_path / "b.e57", P, N)
    assert (tmp_path / "a.e57").read_bytes() == (tmp_path / "b.e57").read_bytes()
    P2 = P.copy()
    P2[0, 0] += 1e-6
    write_e57(tmp_path / "c.e57", P2, N)
    guids = []
    for f in ("a.e57", "c.e57"):
        e57 = pye57.E57(str(tmp_path / f))
        guids.append(e57.root["guid"].value())
        e57.close()
    assert guids[0] != guids[1] and guids[0].startswith("{")


def test_export_cloud_command_from_a_fused_ply(tmp_path):
    P, N = _cloud(2000, seed=1)
    cloud = FusedCloud(points=P, normals=N.astype(np.float32), laser=np.ones(len(P), np.uint8),
                       frame=np.arange(len(P), dtype=np.int32))
    write_ply(tmp_path / "scan.ply", cloud)
    out = subprocess.run([sys.executable, "-m", "crossline.cli", "export-cloud",
                          str(tmp_path / "scan.ply"), "--out", str(tmp_path / "scan.e57")],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert np.allclose(read_e57(tmp_path / "scan.e57")["points"], P, atol=1e-12)


def test_bad_export_inputs_are_named_errors(tmp_path):
    with pytest.raises(StageError, match=r"\(N, 3\)"):
        write_e57(tmp_path / "x.e57", np.zeros((0, 3)))
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    out = subprocess.run([sys.executable, "-m", "crossline.cli", "export-cloud",
                          str(tmp_path / "bad.ply"), "--out", str(tmp_path / "x.e57")],
                         capture_output=True, text=True)
    assert out.returncode == 2 and "bad.ply" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "x.e57").exists()

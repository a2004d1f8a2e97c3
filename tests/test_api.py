"""The public API: ``from crossline import ...`` gives the objects users read and write."""

from __future__ import annotations

import importlib
import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import crossline
from tests.conftest import REPO

# modules that make ``import crossline`` slow, which only the stages that need them may load
HEAVY = ("cv2", "open3d", "matplotlib", "numba", "scipy", "pandas", "pyarrow", "snakemake")


def test_every_public_name_is_its_modules_object():
    assert set(crossline.__all__) == {"__version__", *crossline._EXPORTS}
    assert crossline.__all__ == sorted(crossline.__all__)
    for name, module in crossline._EXPORTS.items():
        assert getattr(crossline, name) is getattr(importlib.import_module(module), name), name
        assert name in dir(crossline)
    ns: dict = {}
    exec("from crossline import *", ns)
    assert {k for k in ns if k != "__builtins__"} == set(crossline.__all__)


def test_unknown_names_raise_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'Kamera'"):
        crossline.Kamera  # noqa: B018
    assert not hasattr(crossline, "_not_public")


def test_import_crossline_loads_no_heavy_library():
    """``import crossline`` (and so the CLI's start) stays cheap: names load on first use."""
    code = ("import sys, crossline; print(crossline.__version__); print(sorted(m for m in "
            f"sys.modules if m.split('.')[0] in {HEAVY!r} or m.startswith('crossline.')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         check=True)
    version, loaded = out.stdout.splitlines()
    assert version
    assert loaded == "[]", loaded
    # the first use imports the defining module, and only that
    code = "import sys, crossline; crossline.Board; print('cv2' in sys.modules, 'open3d' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["False", "False"]



def test_the_lazy_exports_make_no_stage_depend_on_every_module():
    """The workflow re-runs a stage when a module it imports changes; the top level's exports
    (imported for type checkers only) are not imports of every stage."""
    from crossline.io.provenance import module_files

    check = module_files("crossline.io.capture")
    assert "crossline/__init__.py" in check and "crossline/io/images.py" in check
    for other in ("crossline/scan/stripes.py", "crossline/fuse/__init__.py", "crossline/camera.py"):
        assert other not in check
    # an import that does run is still followed through the package's __init__
    assert "crossline/camera.py" in module_files("crossline.scan.triangulate")

def _calibration(folder: Path) -> tuple:
    """camera.json, lasers.json and handeye.json of a plausible rig, written to ``folder``."""
    folder.mkdir(parents=True)
    K = np.array([[5100.0, 0.0, 1530.0], [0.0, 5110.0, 1020.0], [0.0, 0.0, 1.0]])
    camera = crossline.Camera(K, [-0.08, 0.15, 1e-4, -2e-4, 0.0], (3072, 2048),
                              {"rms_px": 0.05})
    A = {"normal": [0.0, -0.8, 0.6], "d": -80.0}  # 0.6 z = 80 + 0.8 y: in front
    B = {"normal": [0.8, 0.0, 0.6], "d": -75.0}
    planes = crossline.LaserPlanes.from_dict({"A": A, "B": B})
    T = np.eye(4)
    T[:3, 3] = [10.0, -5.0, 120.0]
    handeye = crossline.HandEye(T, "refined", {"note": "test"})
    camera.save(folder / "camera.json")
    planes.save(folder / "lasers.json")
    handeye.save(folder / "handeye.json")
    return camera, planes, handeye


def test_calibration_files_round_trip(tmp_path):
    camera, planes, handeye = _calibration(tmp_path / "cal")
    cam = crossline.Camera.load(tmp_path / "cal" / "camera.json")
    assert np.array_equal(cam.K, camera.K) and np.array_equal(cam.dist, camera.dist)
    assert cam.image_size == (3072, 2048)
    assert cam.extra == {"rms_px": 0.05}
    assert cam.to_dict() == json.loads((tmp_path / "cal" / "camera.json").read_text())
    cam.save(tmp_path / "again.json")
    assert (tmp_path / "again.json").read_bytes() == (tmp_path / "cal" / "camera.json").read_bytes()
    lp = crossline.LaserPlanes.load(tmp_path / "cal" / "lasers.json")
    assert lp.names == ("A", "B")
    assert np.allclose(lp["A"].normal, planes["A"].normal) and lp["B"].d == planes["B"].d
    he = crossline.HandEye.load(tmp_path / "cal" / "handeye.json")
    assert np.array_equal(he.T_tool_cam, handeye.T_tool_cam) and he.method == "refined"

    # triangulate a pixel on laser A's plane and project the point back to the same pixel
    uv = np.array([[1500.0, 1000.0], [200.0, 1900.0]])
    p = lp["A"].intersect_rays(cam.rays(uv))
    assert np.allclose(lp["A"].distance(p), 0.0, atol=1e-9) and (p[:, 2] > 0).all()
    assert np.allclose(cam.project(p), uv, atol=1e-6)


def _examples(text: str) -> list[str]:
    return [textwrap.dedent(b) for b in re.findall(r"```python\n(.*?)```", text, re.S)]


def test_the_documented_examples_run(tmp_path, monkeypatch):
    """The module docstring's example and the README's Python API section run as written."""
    _calibration(tmp_path / "data" / "interim" / "demo" / "calibration")
    monkeypatch.chdir(tmp_path)
    doc = textwrap.dedent(crossline.__doc__.split("::\n", 1)[1])
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    section = re.split(r"\n#{1,3} ", readme.split("\n### Python API\n", 1)[1], maxsplit=1)[0]
    examples = _examples(section)
    assert examples, "README's Python API section has no python example"
    for code in (doc, *examples):
        ns: dict = {}
        exec(compile(code, "<example>", "exec"), ns)
        if "back" in ns:
            assert np.allclose(ns["back"], ns["uv"], atol=1e-6)


def test_cloud_round_trips(tmp_path):
    """A fused cloud's PLY read back by name, and the same points through E57 (mm both ways)."""
    from crossline.fuse import FusedCloud, write_ply

    rng = np.random.default_rng(0)
    pts = rng.uniform(-100.0, 100.0, (50, 3))
    nrm = rng.normal(size=(50, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cloud = FusedCloud(pts, nrm, np.ones(50, np.uint8), np.arange(50, dtype=np.int32))
    write_ply(tmp_path / "c.ply", cloud)
    ply = crossline.read_ply(tmp_path / "c.ply")
    assert np.allclose(ply["points"], pts, atol=1e-4)
    pytest.importorskip("pye57")
    crossline.write_e57(tmp_path / "c.e57", ply["points"], ply["normals"])
    got = crossline.read_e57(tmp_path / "c.e57")
    assert np.allclose(got["points"], ply["points"], atol=1e-9)

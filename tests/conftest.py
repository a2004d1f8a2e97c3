"""Shared fixtures: small rendered captures, rendered once and cached on disk.

A capture is keyed by the simulator's source code and its arguments, so editing the
renderer re-renders it and nothing stale is ever used. A file lock makes pytest-xdist
workers wait for one render instead of each rendering their own.
"""

from __future__ import annotations

import fcntl
import hashlib
import shutil
from pathlib import Path

import numpy  # noqa: F401 - loaded here so that the BLAS limit below reaches its OpenBLAS
import pytest
import scipy.linalg  # noqa: F401 - and scipy's own OpenBLAS build
from threadpoolctl import threadpool_limits

from crossline.io.provenance import PACKAGE_ROOT, module_files

# One BLAS thread per test process, as the crossline command runs (crossline.cli): each
# pytest-xdist worker is already one of the cores, and a second BLAS thread per worker only
# spins against the other worker. threadpoolctl limits the libraries already loaded.
_ONE_BLAS_THREAD = threadpool_limits(limits=1, user_api="blas")

REPO = PACKAGE_ROOT.parent
CACHE = REPO / ".pytest_cache" / "crossline-captures"


def render_cached(preset: str = "paper", seed: int = 0, **kwargs) -> Path:
    """A quick capture of ``preset``, rendered once per simulator version and arguments."""
    from crossline.sim import simulate

    h = hashlib.sha256()
    for f in module_files("crossline.sim"):
        h.update(f.encode())
        h.update((REPO / f).read_bytes())
    h.update(repr((preset, seed, sorted(kwargs.items()))).encode())
    out = CACHE / f"{preset}-{seed}-{h.hexdigest()[:16]}"
    CACHE.mkdir(parents=True, exist_ok=True)
    with open(CACHE / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not (out / "rig.yaml").is_file():
                shutil.rmtree(out, ignore_errors=True)
                simulate(out, preset=preset, seed=seed, quick=True, progress=False, threads=2, **kwargs)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return out


@pytest.fixture(scope="session")
def quick_capture() -> Path:
    """A `--quick` capture of the paper's rig (read-only: copy it before changing anything)."""
    return render_cached("paper", seed=0)


@pytest.fixture(scope="session")
def quick_capture_compact() -> Path:
    """A `--quick` capture of the second rig preset (read-only)."""
    from crossline.sim.presets import PRESETS

    other = sorted(p for p in PRESETS if p != "paper")[0]
    return render_cached(other, seed=0)


CHESSBOARD = "chessboard:12x9:4"  # inner corners, square size (mm): about the paper's grid's extent


@pytest.fixture(scope="session")
def quick_capture_chessboard() -> Path:
    """A `--quick` capture of the paper's rig with a chessboard, calibration and 3 plate frames."""
    from crossline.board import Board

    return render_cached("paper", seed=0, board=Board.parse(CHESSBOARD), scans=["plate"], frames=3)


@pytest.fixture
def capture_copy(quick_capture: Path, tmp_path: Path) -> Path:
    """A private copy of the quick capture that a test may break."""
    dst = tmp_path / "capture"
    shutil.copytree(quick_capture, dst)
    return dst


# Module fixtures that take a minute or more to build: every test using one runs on the same
# pytest-xdist worker (`make test` runs with --dist loadgroup), so that each is built once
# rather than once on each worker that draws one of its tests.
SHARED_FIXTURES = ("done_workdir", "partial_workdir", "quick_pipeline", "calibrated")


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own hook reads the groups
def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        name = next((n for n in SHARED_FIXTURES if n in getattr(item, "fixturenames", ())), None)
        if name is not None:
            item.add_marker(pytest.mark.xdist_group(name))

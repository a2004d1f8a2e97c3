"""A stage that meets a full disk (ENOSPC) fails with a clear error naming the file and leaves
nothing a later run could take for a good artefact (issue 23.3).

The full disk is real, not mocked: a 64 KiB tmpfs in a private mount namespace
(``unshare -m``), filled to the last byte before the stage runs.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

FILL = "dd if=/dev/zero of={d}/filler bs=4k 2>/dev/null; "


def _can_mount() -> bool:
    if shutil.which("unshare") is None:
        return False
    proc = subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"],
                          capture_output=True)
    return proc.returncode == 0


pytestmark = pytest.mark.skipif(not _can_mount(), reason="a full disk is simulated with a tmpfs "
                                "in a private mount namespace (unshare -m), not allowed here")


def _on_full_disk(out_dir: Path, command: list[str]) -> tuple[int, str, list[str]]:
    """Run ``command`` with ``out_dir`` a full tmpfs; return its exit code, its stderr and the
    names left in ``out_dir`` afterwards (the filler aside)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    cmd = " ".join(f"'{c}'" for c in command)
    script = (f"mount -t tmpfs -o size=64k tmpfs '{out_dir}' && " + FILL.format(d=out_dir)
              + f"{cmd}; rc=$?; echo; echo LEFT; ls -A '{out_dir}'; exit $rc")
    proc = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True,
                          timeout=600)
    left = proc.stdout.split("LEFT", 1)[1].split()
    return proc.returncode, proc.stderr, [n for n in left if n != "filler"]


CROSSLINE = [sys.executable, "-m", "crossline.cli"]


def test_check_on_a_full_disk_names_the_file_and_leaves_nothing(quick_capture: Path,
                                                                tmp_path: Path) -> None:
    out = tmp_path / "interim"
    rc, err, left = _on_full_disk(out, [*CROSSLINE, "check", str(quick_capture), "--json",
                                        str(out / "check.json")])
    assert rc == 2, err
    assert f"cannot write {out / 'check.json'}: No space left on device" in err, err
    assert "Traceback" not in err
    assert left == [], f"left behind on the full disk: {left}"


def test_stripes_on_a_full_disk_fail_cleanly(quick_capture: Path, tmp_path: Path) -> None:
    out = tmp_path / "stripes"
    rc, err, left = _on_full_disk(out, [*CROSSLINE, "extract-stripes", str(quick_capture), "gauge",
                                        "--out", str(out / "gauge.parquet"), "--threads", "2"])
    assert rc == 2, err
    assert f"cannot write {out / 'gauge.parquet'}: No space left on device" in err, err
    assert "Traceback" not in err and "internal error" not in err, err
    assert left == [], f"left behind on the full disk: {left}"

"""The configuration reference is generated from the schema and must match it."""

from __future__ import annotations

import subprocess
import sys

from tests.conftest import REPO


def test_configuration_reference_matches_the_schema():
    """docs/configuration.md is what tools/config_doc.py writes from the schema today."""
    out = subprocess.run([sys.executable, "tools/config_doc.py", "--check"], cwd=REPO,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr

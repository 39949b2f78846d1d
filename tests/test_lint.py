"""ruff (configured in pyproject.toml) keeps the tree clean: lint and format."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("args", [["check", "."], ["format", "--check", "."]])
def test_ruff(args):
    exe = shutil.which("ruff")
    if exe is None:
        pytest.skip("ruff not installed (it comes with the test extras)")
    res = subprocess.run([exe, *args], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_layering():
    """factors/ and devices/ never import fgslam (docs/design.md, 1)."""
    for pkg in ("factors", "devices"):
        for path in (ROOT / pkg).rglob("*.py"):
            text = path.read_text()
            assert "import fgslam" not in text and "from fgslam" not in text, path

"""The linter's rules hold for the whole repository: ``ruff check`` (imports sorted, pyflakes, lines of at most 120
characters; ``[tool.ruff]`` in pyproject.toml)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _ruff() -> list[str]:
    """The command that runs ruff: the module where installed with the test extra, else a ruff on PATH."""
    try:
        import ruff  # noqa: F401
    except ImportError:
        found = shutil.which("ruff")
        if found is None:
            pytest.skip("ruff is not installed (pip install -e '.[test]' brings it)")
        return [found]
    return [sys.executable, "-m", "ruff"]


def test_ruff_finds_nothing():
    result = subprocess.run([*_ruff(), "check", "--no-cache", "--output-format", "concise", str(ROOT)], cwd=ROOT,
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


def test_ruff_reports_a_planted_fault(tmp_path):
    """Guards the guard: the configuration is read and a fault of each kind it selects is reported."""
    planted = tmp_path / "planted.py"
    planted.write_text("import os\nimport sys\n\nvalue = 1  # " + "x" * 130 + "\nprint(undefined_name)\n")
    config = ["--config", str(ROOT / "pyproject.toml")]
    result = subprocess.run([*_ruff(), "check", "--no-cache", *config, "--output-format", "concise", str(planted)],
                            capture_output=True, text=True)
    assert result.returncode == 1
    for code in ("F401", "E501", "F821"):
        assert code in result.stdout, result.stdout

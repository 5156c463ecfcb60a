"""Lint and type checks as part of the suite (CI runs the README's test command only).

ruff (rules E, F, I, B, UP; ``[tool.ruff]`` in pyproject.toml) over the library, the tests
and the examples, and mypy over ``navapp/`` (``[tool.mypy]``: every function body checked,
untyped third-party libraries not counted; its cache in ``.mypy_cache`` makes a rerun take
seconds). Each is skipped, with the reason, when the tool is not installed (``pip install
-e ".[test]"`` installs both).
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _run(cmd):
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)


def _missing(module):
    return importlib.util.find_spec(module) is None


@pytest.mark.skipif(_missing("ruff"), reason="ruff is not installed (it is in the 'test' extra)")
def test_ruff_is_clean():
    out = _run([sys.executable, "-m", "ruff", "check", "--no-fix", "--output-format", "concise",
                "navapp", "tests", "examples"])
    assert out.returncode == 0, out.stdout + out.stderr


def test_import_contracts_are_kept():
    """The layers, the I/O-only tracking, viser's two rooms and no import cycles
    (``[tool.importlinter]`` in pyproject.toml): the architecture picture, in code."""
    out = _run([sys.executable, "-c", "import sys; from importlinter.cli import lint_imports; "
                                      "sys.exit(lint_imports(no_cache=True))"])
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.skipif(_missing("mypy"), reason="mypy is not installed (it is in the 'test' extra)")
def test_mypy_is_clean():
    out = _run([sys.executable, "-m", "mypy", "navapp"])
    assert out.returncode == 0, out.stdout + out.stderr

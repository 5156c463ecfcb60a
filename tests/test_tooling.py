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


def test_the_import_graph_has_no_cycle_and_every_top_module_is_in_a_layer():
    """Import-linter's acyclic contract compares the siblings of each package only; a cycle
    between a package and its own module (``app/panels/__init__`` importing ``layers``,
    ``layers`` importing back from the package in a function) passes it. Here the whole
    module graph, type-only imports counted: no module reaches itself. And each top module of
    ``navapp`` is in a layer of the contract, so none can import upward unchecked."""
    import tomllib

    import grimp

    graph = grimp.build_graph("navapp", exclude_type_checking_imports=False, cache_dir=None)
    cycles = []
    for a in sorted(graph.modules):
        for b in sorted(graph.find_modules_directly_imported_by(a)):
            back = graph.find_shortest_chain(importer=b, imported=a)
            if back is not None:
                cycles.append(" → ".join((a, *back)))
    assert not cycles, "\n".join(cycles)
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    assert config["exclude_type_checking_imports"] is False
    layered = {name.strip() for contract in config["contracts"] if contract["type"] == "layers"
               for layer in contract["layers"] for name in layer.replace("|", ":").split(":")}
    top = {".".join(m.split(".")[:2]) for m in graph.modules if m != "navapp"}
    assert top <= layered, f"not in a layer: {sorted(top - layered)}"

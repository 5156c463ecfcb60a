"""The public API: every name in ``navapp.__all__`` resolves to its home module's object,
``docs/api.md`` documents exactly those names, and importing navapp stays cheap."""

import re
import subprocess
import sys
from importlib import import_module
from pathlib import Path

import navapp

API_MD = Path(__file__).resolve().parent.parent / "docs" / "api.md"
NAME = re.compile(r"[A-Za-z_][A-Za-z_0-9]*")


def test_all_names_resolve_and_match_the_export_table():
    assert navapp.__all__ == sorted(navapp._EXPORTS)
    for name in navapp.__all__:
        target = navapp._EXPORTS[name]
        module, attr = target if isinstance(target, tuple) else (target, name)
        assert getattr(navapp, name) is getattr(import_module(module), attr), name
    assert navapp.FEATURES[0].name == "anterior" and navapp.K == 45 and navapp.EDGE_MM == 4.0
    assert callable(navapp.register) and navapp.register.__doc__ and "Parameters" in navapp.register.__doc__


def test_import_is_lazy():
    """``import navapp`` (the CLI's first step) must not pull in the numerical stack."""
    code = "import sys, navapp; print('scipy' in sys.modules, 'trimesh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]


def test_every_public_name_is_documented():
    import inspect

    for name in navapp.__all__:
        obj = getattr(navapp, name)
        if callable(obj) or inspect.isclass(obj):
            doc = obj.__doc__ or ""
            assert doc and not doc.startswith(f"{name}("), name  # a dataclass's generated signature is no doc


def test_api_md_documents_exactly_the_public_names():
    """Every public name is in docs/api.md, and every name a table row of it opens with
    (``name(...)``, ``Name.method``) is public: the page cannot drift from ``__all__``."""
    text = re.sub(r"```.*?```", "", API_MD.read_text(), flags=re.S)  # the page's code blocks hold no names
    spans = re.findall(r"`([^`]+)`", text)
    documented = {m.group(0) for s in spans if (m := NAME.match(s))}
    missing = sorted(set(navapp.__all__) - documented)
    assert not missing, f"public names docs/api.md does not mention: {missing}"
    listed = set()
    for line in text.splitlines():
        cell = re.match(r"^\|([^|]*)\|", line)
        if cell is None or set(cell.group(1).strip()) <= set("-: "):
            continue
        listed |= {m.group(0) for s in re.findall(r"`([^`]+)`", cell.group(1)) if (m := NAME.match(s))}
    listed.discard("name")  # the tables' header
    unknown = sorted(listed - set(navapp.__all__))
    assert not unknown, f"docs/api.md lists names navapp does not export: {unknown}"


def test_named_defaults_are_the_ones_in_use():
    """``navapp.defaults`` is the one home of these numbers: the classes that use them agree."""
    from navapp.defaults import LM_MAX_ITERATIONS, PROBE_HEIGHT_PX, PROBE_SPACING_MM, PROBE_WIDTH_PX
    from navapp.registration import next_plane
    from navapp.registration.libr import LMOptions
    from navapp.simulation.probe import Probe

    assert LMOptions().max_iterations == LM_MAX_ITERATIONS
    p = Probe()
    assert (p.width_px, p.height_px, p.spacing_mm) == (PROBE_WIDTH_PX, PROBE_HEIGHT_PX, PROBE_SPACING_MM)
    assert next_plane.IMAGE_WIDTH_MM == p.width_px * p.spacing_mm and next_plane.IMAGE_DEPTH_MM == 80.0

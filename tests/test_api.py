"""The public API: every name in ``navapp.__all__`` resolves, and importing navapp stays cheap."""

import subprocess
import sys

import navapp


def test_all_names_resolve_and_match_the_export_table():
    assert navapp.__all__ == sorted(navapp._EXPORTS)
    for name in navapp.__all__:
        assert getattr(navapp, name) is not None, name
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

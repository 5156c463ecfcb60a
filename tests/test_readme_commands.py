"""The README's commands run as a user runs them, in a fresh folder, with their output checked
(small meshes where the command takes them, so that the suite stays within its budget). One case
folder, made by ``navapp demo``, serves the commands that read a case."""

import json

import numpy as np
import pytest

from navapp.cli import main

QUICK = ["--edge", "12", "--k", "12"]


def last_json(out: str) -> dict:
    return json.loads(out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """``navapp demo`` in a fresh folder, default ``--out``: it simulated the demo scene and then
    ended in a traceback (``'Namespace' object has no attribute 'local_modes'``) when it handed
    the case to ``register`` with a Namespace written out by hand."""
    import contextlib
    import io
    import os

    folder = tmp_path_factory.mktemp("readme")
    out, err = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["--quiet", "demo", "--truth-edge", "12", *QUICK])
    finally:
        os.chdir(cwd)
    return folder, code, out.getvalue(), err.getvalue()


def test_demo_simulates_and_registers(demo_run):
    folder, code, out, err = demo_run
    assert code == 0, err
    brief = last_json(out)
    case = folder / "navapp-demo"
    assert brief["case"] == "demo" and brief["out"] == "navapp-demo/registration"
    assert brief["tre_deformable"] < brief["tre_rigid"]
    assert set(brief["target_centroid_error_mm"]) == {"tumour1", "tumour2"}
    assert "navapp: demo case simulated into navapp-demo" in err
    result = json.loads((case / "registration/result.json").read_text())
    assert result["k"] == 12 and result["mesher"]["edge_mm"] == 12.0
    assert np.isfinite(result["omega"])
    for name in ("case.toml", "preop/liver.ply", "truth/field.npz", "registration/liver.ply",
                 "registration/targets.csv"):
        assert (case / name).is_file(), name

"""Issue 47, item 1: a case says where its organ is held (case.toml ``[intraop.supports]``,
``navapp register --supports``), and the registration's basis vanishes there."""

import json

import numpy as np
import pytest
from test_register_cli import make_case

from navapp.cli import main
from navapp.mechanics.supports import HeldSupports, Supports, case_supports, held_nodes


@pytest.fixture
def spied(monkeypatch):
    """Every model ``navapp register`` prepares, with the keyword arguments it was asked for."""
    from navapp.registration import pipeline

    made = []
    real = pipeline.prepare

    def prepare(case, *args, **kwargs):
        model, sec = real(case, *args, **kwargs)
        made.append((kwargs, model))
        return model, sec

    monkeypatch.setattr(pipeline, "prepare", prepare)
    return made


def _result(case):
    return json.loads((case / "registration" / "result.json").read_text())


def test_declared_supports_reach_the_basis_of_the_registration(tmp_path, spied):
    case = tmp_path / "c"
    make_case(case)
    args = ["--quiet", "register", str(case), "--edge", "15", "--k", "10", "--json"]
    with (case / "case.toml").open("a") as fh:
        fh.write('[intraop.supports]\nheld = "posterior"\n')
    assert main(args) == 0
    assert _result(case)["supports"] == {"held": "posterior", "release": "N"}
    kwargs, model = spied[-1]
    assert kwargs == {"supports": "posterior", "release": "N"}
    from navapp.anatomy.meshing import TetMesh

    held = held_nodes(TetMesh(model.basis.nodes, model.basis.tets), Supports.POSTERIOR)
    assert len(held) > 10
    Ju = model.basis.Ju.toarray() if hasattr(model.basis.Ju, "toarray") else np.asarray(model.basis.Ju)
    rows = (3 * held[:, None] + np.arange(3)).ravel()
    assert np.abs(Ju[rows]).max() == 0.0  # every mode vanishes where the organ is held
    assert np.abs(Ju).max() > 0.01
    # the command overrides the case: free-floating, then the ligaments with the left one released
    assert main([*args, "--supports", "none"]) == 0
    assert _result(case)["supports"] is None and spied[-1][0] == {}
    assert main([*args, "--supports", "ligaments", "--release", "L"]) == 0
    assert _result(case)["supports"] == {"held": "ligaments", "release": "L"}
    # surface forces on the declared supports: the answer says which deformation it chose
    assert main([*args, "--surface-forces"]) == 0
    chosen = _result(case)["surface_forces"]
    assert chosen["answer"] in ("none", "basis", "forces") and _result(case)["supports"]["held"] == "posterior"


@pytest.mark.parametrize("toml, option, says", [
    ('[intraop.supports]\nheld = "floor"\n', [], "case.toml: supports must be one of ligaments, posterior, bare_area"),
    ('[intraop.supports]\nrelease = "L"\n', [], "case.toml: [intraop.supports] needs held"),
    ('[intraop.supports]\nheld = "ligaments"\nrelease = "X"\n', [], "case.toml: the released side must be"),
    ("", ["--supports", "floor"], "--supports: supports must be one of"),
    ("", ["--release", "L"], "--release needs --supports ligaments"),
    ("", ["--supports", "none", "--release", "L"], "a free-floating organ has no ligaments"),
    ("", ["--surface-forces"], "--surface-forces needs declared supports"),
])
def test_a_bad_declaration_is_one_line(tmp_path, capsys, toml, option, says):
    case = tmp_path / "c"
    make_case(case)
    with (case / "case.toml").open("a") as fh:
        fh.write(toml)
    capsys.readouterr()
    assert main(["--quiet", "register", str(case), "--edge", "15", "--k", "10", *option]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0] and "Traceback" not in err[0], err


def test_the_local_load_study_takes_the_cases_declaration_before_its_scene():
    from navapp.anatomy.caseio import Case
    from navapp.anatomy.model import PreopModel
    from navapp.evaluation.loads import declared_supports

    settings = {"scene": "/no/such/scene.toml", "intraop": {"supports": {"held": "bare_area"}}}
    case = Case(preop=PreopModel(liver=None, name="x"), settings=settings)  # the scene is never read
    assert declared_supports(case) == {"supports": "bare_area", "release": "N"}
    assert case_supports({}) is None
    assert HeldSupports.parse("ligaments", "R").prepare_args() == {"supports": "ligaments", "release": "R"}


def _surface_points(case, rows):
    """Points on the case's liver surface (its vertices, nudged 0.5 mm outward), as CSV text."""
    import trimesh

    v = trimesh.load(case / "preop" / "liver.ply").vertices[rows]
    v = v * (1 + 0.5 / np.linalg.norm(v, axis=1, keepdims=True))
    return "x,y,z\n" + "\n".join(",".join(repr(float(c)) for c in p) for p in v) + "\n"


def test_support_points_and_springs_reach_the_basis(tmp_path, spied):
    """``held = "points"`` with preop/supports.csv, on springs of ``stiffness_pa_per_mm``: the
    basis of the registration holds the nodes around the points on those springs; the command's
    ``--support-stiffness`` overrides the case's, and without one the points are held firmly."""
    from navapp.anatomy.meshing import TetMesh
    from navapp.mechanics.supports import point_nodes

    case = tmp_path / "c"
    make_case(case)
    (case / "preop" / "supports.csv").write_text(_surface_points(case, [0, 5, 9, 30]))
    with (case / "case.toml").open("a") as fh:
        fh.write('[intraop.supports]\nheld = "points"\nstiffness_pa_per_mm = 40.0\n')
    args = ["--quiet", "register", str(case), "--edge", "15", "--k", "10"]
    assert main(args) == 0
    said = _result(case)["supports"]
    assert said["held"] == "points" and said["stiffness_pa_per_mm"] == 40.0 and len(said["points"]) == 4
    kwargs, model = spied[-1]
    assert kwargs["stiffness"] == 40.0 and len(kwargs["points"]) == 4
    nodes = point_nodes(TetMesh(model.basis.nodes, model.basis.tets), np.array(kwargs["points"]))
    U = np.asarray(model.basis.Ju).reshape(model.basis.M, 3, -1)
    assert np.abs(U[nodes]).max() > 1e-3  # on springs: the support moves
    assert main([*args, "--support-stiffness", "1e9"]) == 0
    assert spied[-1][0]["stiffness"] == 1e9 and _result(case)["supports"]["stiffness_pa_per_mm"] == 1e9
    U = np.asarray(spied[-1][1].basis.Ju).reshape(model.basis.M, 3, -1)
    assert np.abs(U[nodes]).max() < 1e-3 * np.abs(U).max()  # stiff springs: as good as held
    (case / "case.toml").write_text((case / "case.toml").read_text().replace("stiffness_pa_per_mm = 40.0\n", ""))
    assert main(args) == 0
    assert "stiffness" not in spied[-1][0] and "stiffness_pa_per_mm" not in _result(case)["supports"]
    U = np.asarray(spied[-1][1].basis.Ju).reshape(model.basis.M, 3, -1)
    assert np.abs(U[nodes]).max() == 0.0  # held firmly


@pytest.mark.parametrize("csv, toml, option, says", [
    (None, 'held = "points"\n', [], "case.toml: supports held at points need preop/supports.csv"),
    (None, "", ["--supports", "points"], "supports.csv: supports held at points need preop/supports.csv"),
    ("x,y\n1,2\n", 'held = "points"\n', [], "supports.csv: header is 'x,y', expected 'x,y,z'"),
    ("x,y,z\n1,2,oops\n", 'held = "points"\n', [], "supports.csv"),
    ("far", 'held = "points"\n', [], "supports.csv: 1 of 2 support points are not on the liver surface: row 2 is"),
    (None, 'held = "posterior"\nstiffness_pa_per_mm = -5\n', [],
     "case.toml: intraop.supports.stiffness_pa_per_mm = -5 is out of range"),
    (None, 'held = "posterior"\nstiffness_pa_per_mm = "firm"\n', [], "stiffness_pa_per_mm must be a Real"),
    (None, 'held = "posterior"\n', ["--support-stiffness", "0"],
     "--support-stiffness: the supports' stiffness must be"),
    (None, "", ["--support-stiffness", "10"], "--support-stiffness needs declared supports"),
    ("near", 'held = "posterior"\n', [], "supports.csv: the case has support points but does not declare them"),
    ("near", "", [], "supports.csv: the case has support points but does not declare them"),
])
def test_a_bad_support_point_or_stiffness_is_one_line(tmp_path, capsys, csv, toml, option, says):
    case = tmp_path / "c"
    make_case(case)
    if csv == "far":
        text = _surface_points(case, [0])
        csv = text + "500.0,0.0,0.0\n"
    elif csv == "near":
        csv = _surface_points(case, [0, 7])
    if csv is not None:
        (case / "preop" / "supports.csv").write_text(csv)
    if toml:
        with (case / "case.toml").open("a") as fh:
            fh.write("[intraop.supports]\n" + toml)
    capsys.readouterr()
    assert main(["--quiet", "register", str(case), "--edge", "15", "--k", "10", *option]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0] and "Traceback" not in err[0], err

"""`navapp register` end to end on a hand-made case folder (not a phantom)."""

import json

import numpy as np
import trimesh

from navapp.anatomy.caseio import read_case
from navapp.cli import main


def make_case(folder):
    """An ellipsoidal 'liver' with anterior stylus points and truth, written by hand."""
    liver = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    liver.apply_scale([90.0, 60.0, 50.0])
    (folder / "preop").mkdir(parents=True)
    (folder / "intraop").mkdir()
    (folder / "truth").mkdir()
    liver.export(folder / "preop/liver.ply")
    (folder / "case.toml").write_text('name = "ellipsoid"\nunits = "mm"\n')
    v = liver.vertices

    def bend(p):  # a smooth sag of the anterior-left part plus a shift
        sag = -3.0 * np.clip(p[:, 0] / 90.0, 0, 1) ** 2 * 4
        return p + np.column_stack([np.full(len(p), 1.5), sag, np.zeros(len(p))])

    ant = v[v[:, 1] > 20]
    pts = bend(ant[::3])
    rows = "\n".join(",".join(repr(float(x)) for x in r) for r in pts)
    (folder / "intraop/anterior.csv").write_text("x,y,z\n" + rows + "\n")
    inner = v[::15] * 0.5
    (folder / "truth/targets.csv").write_text(
        "\n".join(",".join(repr(float(x)) for x in r) for r in np.column_stack([inner, bend(inner)])) + "\n")


def test_register_hand_made_case(tmp_path, capsys):
    make_case(tmp_path / "c")
    code = main(["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "10", "--json"])
    assert code == 0
    brief = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert brief["stop_reason"] in ("converged", "stationary", "max_iterations")
    out = tmp_path / "c" / "registration"
    result = json.loads((out / "result.json").read_text())
    assert result["tre_deformable"]["mean_mm"] < result["tre_rigid"]["mean_mm"]
    assert np.isfinite(result["omega"])
    reg = trimesh.load(out / "liver.ply")
    assert len(reg.vertices) == len(read_case(tmp_path / "c").preop.liver.vertices)
    assert np.isfinite(reg.vertices).all()


def test_register_without_data_is_a_clear_error(tmp_path, capsys):
    make_case(tmp_path / "c")
    (tmp_path / "c/intraop/anterior.csv").unlink()
    assert main(["--quiet", "register", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no intraoperative data" in err[0]


def test_more_control_points_than_surface_nodes_is_one_line(tmp_path, capsys):
    make_case(tmp_path / "c")
    assert main(["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "900"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "more control points than the mesh has surface nodes" in err[0], err

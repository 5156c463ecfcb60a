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
    # which mesher made the mesh, and why, is part of the result and of the command's output
    mesher = result["mesher"]
    assert mesher["method"].split()[0] in ("gmsh", "ftetwild") and mesher["why"].startswith(mesher["method"])
    assert brief["mesher"] == mesher["why"] and mesher["edge_mm"] == 15.0 and mesher["nodes"] == result["nodes"]
    assert main(["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "10"]) == 0
    io = capsys.readouterr()
    again = json.loads((out / "result.json").read_text())["mesher"]
    assert again["cached"] and again["why"] == mesher["why"]
    assert f"navapp: mesher {mesher['why']} (mesh from the cache)" in io.err.splitlines()


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


def test_a_patch_too_small_for_the_pose_is_said_by_the_command_as_by_the_viewer(tmp_path, capsys):
    """One rule for "the pose may be grossly wrong": the viewer warned below 10 % of the liver
    surface covered, ``navapp register`` said nothing on the same data (a 300-point patch of
    the demo's sweep, 6.8 %: only a tumour line). The registration now carries the line itself."""
    make_case(tmp_path / "c")
    v = trimesh.load(tmp_path / "c/preop/liver.ply").vertices
    top = v[np.argmax(v[:, 1])]
    patch = v[np.linalg.norm(v - top, axis=1) < 25.0]  # a small cap of the anterior surface
    rows = "\n".join(",".join(repr(float(x)) for x in r) for r in patch)
    (tmp_path / "c/intraop/anterior.csv").write_text("x,y,z\n" + rows + "\n")
    code = main(["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "10", "--json"])
    assert code == 0
    io = capsys.readouterr()
    brief = json.loads(io.out.strip().splitlines()[-1])
    result = json.loads((tmp_path / "c/registration/result.json").read_text())
    said = [w for w in result["warnings"] if "of the liver surface" in w]
    assert len(said) == 1 and "less than the 10 %" in said[0], result["warnings"]
    assert said[0] in brief["warnings"] and said[0] in result["warning"]
    assert any(line.startswith("navapp: warning: ") and line.endswith(said[0]) for line in io.err.splitlines())


def test_each_warning_is_one_line_once(tmp_path, capsys):
    """The undetermined-pose line came twice on stderr: as a Python warning and again from the
    registration's own warnings, with the case's name."""
    make_case(tmp_path / "c")
    (tmp_path / "c/intraop/anterior.csv").write_text("x,y,z\n0.0,60.0,0.0\n")
    assert main(["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "10"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "data points" in line]
    assert len(err) == 1 and err[0].startswith("navapp: warning: ellipsoid: only 1 data points"), err


def test_ok_is_never_said_beside_a_warning(tmp_path, capsys):
    """One rule for "the answer is fine": result.json said ``fit_quality.ok: true`` (the
    residuals, which one point fits exactly) beside the warning that the pose is not
    determined. ``ok`` (top level, in fit_quality and in --json) is now true only with no warning."""
    make_case(tmp_path / "c")
    (tmp_path / "c/intraop/anterior.csv").write_text("x,y,z\n0.0,60.0,0.0\n")
    assert main(["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "10", "--json"]) == 0
    brief = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    result = json.loads((tmp_path / "c/registration/result.json").read_text())
    assert any("only 1 data points" in w for w in result["warnings"])
    assert result["ok"] is False and brief["ok"] is False
    assert result["fit_quality"]["ok"] is False and result["fit_quality"]["residuals_ok"] is True


def test_the_verdict_of_an_older_result_json():
    """A result.json written before the one rule is read by it: its fit_quality.ok judged the
    residuals alone, and the oldest have only ``warning``."""
    from navapp.registration.quality import Verdict

    assert not Verdict.of_result({"fit_quality": {"ok": True}, "warnings": ["the pose is not determined"]}).ok
    assert not Verdict.of_result({"fit_quality": {"ok": True}, "warning": "a; b"}).ok
    assert Verdict.of_result({"fit_quality": {"ok": False}, "warning": None}).warnings == ("poor fit",)
    assert Verdict.of_result({"fit_quality": {"ok": True}, "warning": None}).ok
    assert Verdict.of_result({"answer": "rigid", "warnings": []}).ok


def test_local_modes_are_asked_for_and_reported(tmp_path, capsys):
    """``--local-modes`` reaches the registration: result.json says what the step did (a smooth
    sag in the basis leaves no point off to place a source under, so the answer is the
    default's); without the flag there is no such entry."""
    make_case(tmp_path / "c")
    args = ["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "10", "--json"]
    assert main(args) == 0
    default = json.loads((tmp_path / "c" / "registration" / "result.json").read_text())
    assert main([*args, "--local-modes"]) == 0
    local = json.loads((tmp_path / "c" / "registration" / "result.json").read_text())
    assert "local_modes" not in default and "local_modes" in local["seconds"]
    modes = local["local_modes"]
    assert set(modes) >= {"sources", "adopted", "heldout_base_mm", "heldout_extended_mm"}
    assert modes["sources"] == 0 and not modes["adopted"] and local["tre_deformable"] == default["tre_deformable"]


def test_a_targets_own_line_reaches_result_json_and_stderr(tmp_path, capsys):
    """A target far from every data point: its line (``support.TargetSupport.warning``, carried
    to ``write_outputs`` as a ``FitWarning``) is the target's ``warning`` in result.json, one of
    its ``warnings`` after the answer's, makes ``ok`` false and is said on stderr; a determined
    target has none."""
    from navapp.anatomy.targets import Target, write_targets
    from navapp.registration.support import SupportOptions

    make_case(tmp_path / "c")
    # the data cover y > 20 mm of a 60 mm semi-axis: the posterior pole is 80 mm from them
    write_targets([Target("near", np.array([0.0, 45.0, 0.0])), Target("far", np.array([0.0, -50.0, 0.0]))],
                  tmp_path / "c/preop/targets")
    assert main(["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "10", "--json"]) == 0
    err = capsys.readouterr().err
    result = json.loads((tmp_path / "c/registration/result.json").read_text())
    rows = {r["name"]: r for r in result["targets"]}
    far = rows["far"]
    assert not far["determined"] and far["nearest_data_mm"] > SupportOptions.far_mm
    assert far["warning"] == (f"deformation not determined by the data near far: no data within "
                              f"{SupportOptions.far_mm:g} mm (nearest {far['nearest_data_mm']:.0f} mm)")
    lines = [r["warning"] for r in result["targets"] if "warning" in r]  # in the targets' order, last
    assert result["warnings"][-len(lines):] == lines and not result["ok"]
    assert all(("warning" in r) is not r["determined"] for r in result["targets"])
    assert f"navapp: warning: ellipsoid: {far['warning']}" in err.splitlines()

import numpy as np
import pytest
import trimesh

from navapp.anatomy.caseio import Case, read_case, read_csv, write_case
from navapp.anatomy.truth import TruthPoints
from navapp.cli import main
from navapp.errors import InputError


@pytest.fixture(scope="module")
def case_dir(phantoms, tmp_path_factory):
    rng = np.random.default_rng(0)
    m = phantoms[0]
    m.fiducials = m.liver.vertices[:4] * 0.9
    intraop = {"anterior": rng.normal(size=(20, 3)) * 30, "portal_contour": rng.normal(size=(7, 3)) * 10}
    targets = rng.normal(size=(15, 6)) * 40
    d = tmp_path_factory.mktemp("case")
    write_case(Case(m, intraop, TruthPoints(targets[:, :3], targets[:, 3:]), {"name": "t", "scene": "s.toml"}), d)
    return d, m, intraop, targets


def test_round_trip_is_exact(case_dir):
    d, m, intraop, targets = case_dir
    c = read_case(d)
    assert np.array_equal(c.preop.liver.vertices, m.liver.vertices)
    assert np.array_equal(c.preop.liver.faces, m.liver.faces)
    assert np.array_equal(c.preop.portal.vertices, m.portal.vertices)
    assert np.array_equal(c.preop.hepatic.faces, m.hepatic.faces)
    for v in ("portal", "hepatic"):
        a, b = c.preop.centerline(v), m.centerline(v)
        assert np.array_equal(a.points, b.points) and np.array_equal(a.branch, b.branch)
    assert np.array_equal(c.preop.regions, m.regions)
    assert np.array_equal(c.preop.fiducials, m.fiducials)
    for k in intraop:
        assert np.array_equal(c.intraop[k], intraop[k])
    assert np.array_equal(np.column_stack(c.need_truth().tre_points()), targets)
    assert c.settings["scene"] == "s.toml" and c.name == "t"


def _copy(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return dst


@pytest.mark.parametrize("name,text,message", [
    ("intraop/anterior.csv", "x,y\n1,2\n", "header"),
    ("intraop/anterior.csv", "1,2\n3,4\n", "row 1 has 2 columns"),
    ("intraop/anterior.csv", "1,2,3,4\n", "row 1 has 4 columns"),
    ("intraop/anterior.csv", "1,2,3\nnan,2,3\n", "row 2 has a NaN"),
    ("intraop/anterior.csv", "1,2,inf\n", "NaN or infinite"),
    ("intraop/anterior.csv", "", "empty"),
    ("intraop/anterior.csv", "x,y,z\n", "no rows"),
    ("intraop/anterior.csv", "1,a,3\n", "not numeric"),
    ("truth/targets.csv", "1,2,3\n", "expected 6"),
    ("preop/portal_centerline.csv", "x,y,z,branch\n0,0,0,0\n1,1,1,1.5\n", "whole numbers"),
    ("preop/portal_centerline.csv", "x,y,z,branch\n0,0,0,0\n1,1,1,1\n", "single point"),
    ("preop/regions.csv", "label\nanterior\n", "labels but liver.ply has"),
    ("case.toml", 'units = "m"\n', "millimetres"),
    ("case.toml", "units = [\n", "invalid TOML"),
    ("case.toml", 'name = "t"\nk = 0\n', "unknown key 'k' .*the command's --k"),
    ("case.toml", 'name = "t"\n[solver]\nk = 100000\n', "unknown key 'solver' .*the command's --k"),
    ("case.toml", 'name = "t"\nedge = -1\n', "unknown key 'edge' .*--edge"),
    ("case.toml", 'name = "t"\ncolour = "red"\n',
     "unknown key 'colour' \\(known: frame, intraop, name, scene, units\\)"),
    ("case.toml", 'name = 3\n', "name must be a str"),
    ("case.toml", 'name = "t"\n[frame]\nsauce = "x"\n', "unknown key 'frame.sauce'"),
])
def test_bad_files_give_one_clear_error(case_dir, tmp_path, name, text, message):
    d = _copy(case_dir[0], tmp_path / "c")
    (d / name).write_text(text)
    with pytest.raises(InputError, match=message) as err:
        read_case(d)
    assert name.split("/")[-1] in str(err.value)


def test_unknown_label(case_dir, tmp_path):
    d = _copy(case_dir[0], tmp_path / "c")
    lines = (d / "preop/regions.csv").read_text().splitlines()
    lines[5] = "spleen"
    (d / "preop/regions.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="unknown label.*spleen"):
        read_case(d)


def test_unknown_feature_warns(case_dir, tmp_path):
    d = _copy(case_dir[0], tmp_path / "c")
    (d / "intraop/gallbladder.csv").write_text("1,2,3\n")
    with pytest.warns(UserWarning, match="unknown feature 'gallbladder'"):
        c = read_case(d)
    assert "gallbladder" not in c.intraop


def _write_liver(d, mesh):
    mesh.export(d / "preop/liver.ply")
    (d / "preop/regions.csv").unlink(missing_ok=True)


def test_open_liver(case_dir, tmp_path, phantoms):
    d = _copy(case_dir[0], tmp_path / "c")
    m = phantoms[0].liver
    _write_liver(d, trimesh.Trimesh(m.vertices, m.faces[1:], process=False))
    with pytest.raises(InputError, match="has holes.*must be closed"):
        read_case(d)


def test_self_intersecting_liver(case_dir, tmp_path):
    d = _copy(case_dir[0], tmp_path / "c")
    a = trimesh.creation.icosphere(3, radius=60.0)
    b = trimesh.creation.icosphere(3, radius=60.0)
    b.apply_translation([50.0, 0, 0])
    _write_liver(d, trimesh.util.concatenate([a, b]))
    with pytest.raises(InputError, match="self-intersecting"):
        read_case(d)


@pytest.mark.parametrize("scale,message", [(1e-3, "metres"), (1e3, "too large")])
def test_wrong_units(case_dir, tmp_path, phantoms, scale, message):
    d = _copy(case_dir[0], tmp_path / "c")
    m = phantoms[0].liver
    _write_liver(d, trimesh.Trimesh(m.vertices * scale, m.faces, process=False))
    with pytest.raises(InputError, match=message):
        read_case(d)


def test_missing_liver(tmp_path):
    (tmp_path / "preop").mkdir()
    with pytest.raises(InputError, match="liver.ply"):
        read_case(tmp_path)


def test_cli_prints_one_line_not_a_traceback(case_dir, tmp_path, capsys):
    d = _copy(case_dir[0], tmp_path / "c")
    (d / "intraop/anterior.csv").write_text("1,2,nan\n")
    assert main(["--quiet", "mesh", str(d)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("navapp: error:") and "anterior.csv" in err[0]


def test_phantom_cli_writes_preop(tmp_path, capsys):
    assert main(["--quiet", "phantom", "--liver", "2", "--out", str(tmp_path / "p")]) in (0, None)
    c = read_case(tmp_path / "p")
    assert c.preop.portal is not None and c.preop.regions is not None


def test_integer_column_is_checked_and_read_as_numbers(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text("x,y,z,branch\n0,0,0,1\n1,0,0,1\n")
    assert read_csv(p, ("x", "y", "z", "branch"), integer_last=True)[:, 3].tolist() == [1.0, 1.0]
    p.write_text("x,y,z,branch\n0,0,0,1.5\n")
    with pytest.raises(InputError, match="whole numbers"):
        read_csv(p, ("x", "y", "z", "branch"), integer_last=True)

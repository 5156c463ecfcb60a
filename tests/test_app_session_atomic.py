"""A session folder is never half a case (issue 25, item 7): the first save is written whole
beside the folder and renamed into place, even when the process is killed in the middle of
it, and a folder left incomplete by an earlier navapp is completed at start, saying so, or
refused when it is not a session at all."""

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from navapp.anatomy.caseio import read_case
from navapp.app.session import open_session
from navapp.errors import InputError
from navapp.simulation.scene import parse_scene
from navapp.simulation.scenedata import load_scene_data

SCENE = {"name": "apptest", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.2}, "ius": {"planes": 2}}


@pytest.fixture(scope="module")
def scene_data(cache_root):
    return load_scene_data(parse_scene(SCENE), cache_root, edge=12.0)


def assert_whole(folder, sd, stylus_count):
    """``folder`` is the scene's case with the session's data: what ``navapp register`` reads."""
    case = read_case(folder)
    want = sd.case.preop
    assert np.array_equal(case.preop.liver.vertices, want.liver.vertices)
    for v in ("portal", "hepatic"):
        assert np.array_equal(case.preop.vessel(v).vertices, want.vessel(v).vertices), v
        assert np.array_equal(case.preop.centerline(v).points, want.centerline(v).points), v
    assert len(case.preop.targets) == len(want.targets)
    for k in ("nodes", "tets", "u", "offset"):  # the scene's truth field, bit for bit
        assert np.array_equal(getattr(case.truth, k), getattr(sd.case.truth, k)), k
    assert sum(len(p) for p in case.intraop.values()) == stylus_count


def test_a_kill_during_the_first_save_leaves_no_half_case(scene_data, cache_root, tmp_path):
    folder = tmp_path / "s"
    # the worst moment: the liver written, the vessels not yet, and the process killed (-9)
    prog = f"""
import os, signal
import navapp.app.session as session
from navapp.simulation.scene import parse_scene
from navapp.simulation.scenedata import load_scene_data

def write_preop(model, folder):
    os.makedirs(os.path.join(folder, "preop"), exist_ok=True)
    model.liver.export(os.path.join(folder, "preop", "liver.ply"), encoding="binary")
    os.kill(os.getpid(), signal.SIGKILL)

session.write_preop = write_preop
sd = load_scene_data(parse_scene({SCENE!r}), {str(cache_root)!r}, edge=12.0)
s, planes = session.open_session({str(folder)!r}, sd)
s.stylus_count = 30
s.save(sd, planes)
"""
    proc = subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True, timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    # the session folder itself was not started: the kill hit a temporary folder beside it
    assert not (folder / "case.toml").exists() and not (folder / "preop").exists()
    # the restart: a new session, its first save whole, the dead process's folder gone
    s, planes = open_session(folder, scene_data)
    assert s.note is None
    s.stylus_count = 30
    s.save(scene_data, planes)
    assert_whole(folder, scene_data, 30)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_a_first_save_cut_short_by_an_earlier_navapp_is_written_again(scene_data, tmp_path):
    # what the issue found after a kill -9 during the first save: case.toml and preop/liver.ply only
    folder = tmp_path / "s"
    (folder / "preop").mkdir(parents=True)
    (folder / "case.toml").write_text('name = "session-apptest"\nunits = "mm"\n')
    scene_data.case.preop.liver.export(folder / "preop" / "liver.ply", encoding="binary")
    s, planes = open_session(folder, scene_data)
    assert_whole(folder, scene_data, 0)  # complete at once, before anything is entered
    assert s.note and "cut short" in s.note and str(folder) in s.note
    s.stylus_count = 25
    s.save(scene_data, planes)
    assert_whole(folder, scene_data, 25)


def test_an_incomplete_session_folder_is_completed_at_start_and_said(scene_data, tmp_path):
    folder = tmp_path / "s"
    s, planes = open_session(folder, scene_data)
    s.stylus_count = 40
    s.planes_added.append(0)
    s.save(scene_data, planes)
    again, _ = open_session(folder, scene_data)
    # an earlier navapp's kill: a session.json written over a case whose preop/ was cut short
    (folder / "preop" / "portal.ply").unlink()
    hep = folder / "preop" / "hepatic.ply"
    hep.write_bytes(hep.read_bytes()[:200])
    (folder / "truth" / "field.npz").unlink()
    (folder / "intraop" / "anterior.csv").unlink()
    (folder / "export").mkdir()
    (folder / "export" / "registered_liver.ply").write_text("kept")  # not the case's: left alone
    s2, planes2 = open_session(folder, scene_data)
    assert s2.to_json() == s.to_json()
    data = s.data(scene_data, planes)
    assert_whole(folder, scene_data, sum(len(p) for p in data.values()))
    assert (folder / "export" / "registered_liver.ply").read_text() == "kept"
    assert again.note is None  # a whole folder is said nothing about
    note = s2.note
    assert note and str(folder) in note and "incomplete" in note and "preop/portal.ply" in note, note
    assert "\n" not in note


def test_a_folder_that_is_not_a_session_is_refused_not_overwritten(scene_data, tmp_path):
    folder = tmp_path / "patient"
    (folder / "preop").mkdir(parents=True)
    (folder / "case.toml").write_text('name = "patient"\nunits = "mm"\n')  # navapp import's case folder
    with pytest.raises(InputError, match="not a navapp session"):
        open_session(folder, scene_data)
    other = tmp_path / "notes"
    other.mkdir()
    (other / "todo.txt").write_text("x")
    with pytest.raises(InputError, match="not a navapp session"):
        open_session(other, scene_data)
    assert (folder / "case.toml").read_text().startswith('name = "patient"')
    assert os.listdir(other) == ["todo.txt"]

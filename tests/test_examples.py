"""The scripts in examples/ run as a user would run them (small settings) and give the
numbers they gave when they were written: a change in the public API breaks them here, and
a change in the results shows as a moved pin."""

import runpy
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
SMALL = ["--edge", "12", "--k", "12"]  # small registration model (the truth mesh is given apart)


def example(name):
    return runpy.run_path(str(EXAMPLES / name))["main"]


@pytest.fixture(scope="module")
def scene_run(tmp_path_factory):
    """Example 02 once: the case folder it writes serves examples 01 and 03."""
    out = tmp_path_factory.mktemp("examples") / "case"
    return out, example("02_run_scene.py")(["--out", str(out), "--truth-edge", "12", "--planes", "2"] + SMALL)


@pytest.fixture(scope="module")
def case_dir(scene_run):
    return scene_run[0]


def test_02_run_scene_simulates_and_registers_two_levels(scene_run):
    tre = scene_run[1]
    # pinned: phantom0-L, 12 mm meshes, k = 12 (measured when the example was written)
    assert tre["S"] == pytest.approx(PIN["S"], abs=0.05)
    assert tre["S+2"] == pytest.approx(PIN["S+2"], abs=0.05)
    assert tre["S+2"] < tre["S"] < tre["S rigid"]  # more data, better; deformable beats rigid


def test_01_register_case_folder(case_dir, capsys):
    tre = example("01_register_case.py")([str(case_dir)] + SMALL)
    assert tre["deformable"] == pytest.approx(PIN["all"], abs=0.05)
    assert tre["deformable"] < tre["rigid"]
    assert "mean target error" in capsys.readouterr().out


def test_03_sweep_k(case_dir):
    tre = example("03_sweep_k.py")([str(case_dir), "--ks", "6", "12", "--edge", "12"])
    assert set(tre) == {6, 12}
    assert tre[12] == pytest.approx(PIN["all"], abs=0.05)  # k = 12 is example 01's fit
    assert tre[6] == pytest.approx(PIN["k6"], abs=0.05)


# moved by the given-pose rule (``pose.prefer_given``): at 12 mm and k = 12 the fits from ICP's pose
# (12-14 mm from the given one, which is the true pose in this scene) were in doubt and fitted the
# data only 6-12 % better than the given pose held, which is now kept: S 5.61 -> 4.37, S + 2
# 4.31 -> 4.10, all data 3.30 -> 4.04 (k = 6: 5.55 -> 5.48). Moved back at S + 2 and all data by the
# vessel closest points made exact (4 nearest vertices' triangles on the decimated vessel surfaces, not
# 2: 2 missed the closest triangle of 4 % of the demo's portal contour points by up to 0.28 mm): the
# contour residuals changed the given-pose rule's comparison (within 15 %) to ICP's pose: S + 2
# 4.10 -> 4.32, all data 4.04 -> 3.30
PIN = {"S": 4.37, "S+2": 4.32, "all": 3.30, "k6": 5.48}

"""Defects found in the issue-16 review, each with a test that failed before its fix."""

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from navapp.anatomy.caseio import read_csv
from navapp.errors import InputError
from navapp.mechanics.controlpoints import place_control_points, snap_distinct


def test_control_points_when_the_nearest_nodes_are_all_taken():
    """k-means centres crowding one clump of surface nodes (duplicated nodes: fewer distinct
    positions than k) once ended in StopIteration; now every centre gets a distinct node."""
    rng = np.random.default_rng(0)
    clump = np.zeros((40, 3))  # 40 nodes at one position
    spread = rng.normal(size=(10, 3)) * 30.0
    nodes = np.vstack([clump, spread])
    surface = np.arange(len(nodes))
    with pytest.warns(Warning):  # scikit-learn: fewer distinct clusters than k
        chosen = place_control_points(nodes, surface, 45, seed=0)
    assert len(chosen) == 45 and len(set(chosen.tolist())) == 45


def test_snap_distinct_prefers_the_nearest_free_point():
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [5, 0, 0], [9, 0, 0]])
    centres = np.array([[0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]])
    assert snap_distinct(pts, centres, near=2).tolist() == [0, 1, 2]  # third: beyond its 2 nearest
    with pytest.raises(ValueError):
        snap_distinct(pts, np.zeros((5, 3)))


def test_every_stop_reason_the_solver_returns_is_documented():
    """libr's docstring lists the stop reasons; "stationary" was returned but not listed."""
    import navapp.registration.libr as libr

    src = Path(libr.__file__).read_text()
    returned = {node.value.value for node in ast.walk(ast.parse(src))
                if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "reason" for t in node.targets)
                and isinstance(node.value, ast.Constant)}
    returned |= {"no_data"}  # returned directly, not through ``reason``
    assert returned <= set(libr.STOP_REASONS)
    for r in libr.STOP_REASONS:
        assert f'"{r}"' in libr.__doc__, r


def test_integer_column_is_checked_and_read_as_numbers(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text("x,y,z,branch\n0,0,0,1\n1,0,0,1\n")
    assert read_csv(p, ("x", "y", "z", "branch"), integer_last=True)[:, 3].tolist() == [1.0, 1.0]
    p.write_text("x,y,z,branch\n0,0,0,1.5\n")
    with pytest.raises(InputError, match="whole numbers"):
        read_csv(p, ("x", "y", "z", "branch"), integer_last=True)


def test_rendering_leaves_matplotlib_global_state_alone(tmp_path):
    """Importing the figure modules used to switch every caller's backend to Agg; now they
    draw on their own Figure objects and the PNG is still written."""
    code = f"""
import matplotlib
matplotlib.use("svg")
from navapp.evaluation import render, report, cost_report, robustness_report
from navapp.anatomy.model import PreopModel
import trimesh
m = PreopModel(liver=trimesh.creation.icosphere(subdivisions=2, radius=60.0), name="ball")
render.phantom_figure(m, {str(tmp_path / 'ball.png')!r})
import matplotlib.pyplot as plt
print(matplotlib.get_backend(), len(plt.get_fignums()))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["svg", "0"]
    from skimage.io import imread

    img = imread(tmp_path / "ball.png")
    assert img.shape[0] > 100 and img.std() > 0

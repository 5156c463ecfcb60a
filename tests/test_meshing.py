import numpy as np
import pytest
import trimesh

from navapp.anatomy.meshing import dihedral_angles, quality_report, radius_ratio, tet_volumes
from navapp.errors import NavappError


def test_regular_tet_quality():
    nodes = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    tets = np.array([[0, 1, 2, 3]])
    if tet_volumes(nodes, tets)[0] < 0:
        tets = tets[:, [0, 2, 1, 3]]
    assert np.allclose(dihedral_angles(nodes, tets), np.degrees(np.arccos(1 / 3)))
    assert np.allclose(radius_ratio(nodes, tets), 1.0)


def test_liver_mesh_quality(coarse_mesh, phantoms):
    r = quality_report(coarse_mesh)
    assert r["inverted"] == 0
    assert r["min_dihedral_deg"] > 5.0 and r["tets_below_5deg"] == 0
    assert r["min_radius_ratio"] > 0.1
    # the mesh fills the liver: volumes agree within 3 %
    assert abs(r["volume_mm3"] - phantoms[0].liver.volume) / phantoms[0].liver.volume < 0.03
    # its boundary is a closed surface
    surf = trimesh.Trimesh(coarse_mesh.nodes, coarse_mesh.boundary_faces(), process=True)
    assert surf.is_watertight and surf.is_winding_consistent
    assert surf.volume > 0  # outward-oriented boundary faces


def test_open_surface_refused():
    from navapp.anatomy.meshing import tetrahedralise

    s = trimesh.creation.icosphere(2, radius=50.0)
    with pytest.raises(NavappError, match="watertight"):
        tetrahedralise(trimesh.Trimesh(s.vertices, s.faces[1:]), 10.0)


# ---------------------------------------------------------------- any liver

import surface_fixtures as sf  # noqa: E402

from navapp.anatomy.meshing import MeshAttempt, mesh_liver  # noqa: E402
from navapp.anatomy.meshing import quality_report as _q  # noqa: E402


def _floor(mesh):
    r = _q(mesh)
    assert r["inverted"] == 0 and r["tets_below_5deg"] == 0 and r["min_dihedral_deg"] >= 5.0
    return r


@pytest.fixture(scope="module")
def sharp():
    """The plane-cut liver at 3 mm: Gmsh cannot mesh it at 40° (seen both as the error
    users met, "Wrong topology of boundary mesh for parametrization", and as a hang)."""
    return sf.sharp_ridged_liver(3.0)


@pytest.fixture(scope="module")
def fallback_run(sharp, tmp_path_factory, request):
    import os

    from navapp.anatomy.meshing import _mesh_with_log

    # run from an empty folder: fTetWild writes a debug file into its working directory,
    # which must not be the caller's
    here = tmp_path_factory.mktemp("caller-cwd")
    old = os.getcwd()
    request.addfinalizer(lambda: os.chdir(old))
    os.chdir(here)

    # Gmsh fails on this surface, by an error or by hanging (which of the two depends on
    # the last bits of the coordinates); a Gmsh attempt limited to 0.2 s stands in for a
    # hang in case the first one errs
    attempts = (MeshAttempt("gmsh", 40.0), MeshAttempt("gmsh", 90.0, limit=0.2), MeshAttempt("ftetwild"))
    mesh, log = _mesh_with_log(sharp, 10.0, 0, 900, attempts)
    return mesh, log, sorted(p.name for p in here.iterdir())


def test_the_mesher_leaves_the_callers_folder_alone(fallback_run):
    assert fallback_run[2] == []


def test_a_hanging_mesher_is_stopped(fallback_run):
    _, log, _ = fallback_run
    assert any(e["method"].startswith("gmsh") and e["outcome"].startswith("stopped after") for e in log)


def test_gmsh_failure_falls_back_to_ftetwild(fallback_run, sharp):
    mesh, log, _ = fallback_run
    assert log[0]["method"] == "gmsh 40°" and log[0]["outcome"] != "ok"
    assert log[-1]["method"] == "ftetwild" and log[-1]["outcome"] == "ok"
    _floor(mesh)
    # the fallback mesh fills the same solid
    assert abs(_q(mesh)["volume_mm3"] - sharp.volume) / sharp.volume < 0.03


def test_time_limit_ends_in_one_line(sharp):
    from navapp.anatomy.meshing import tetrahedralise

    with pytest.raises(NavappError, match="meshing did not finish within 3 s") as err:
        tetrahedralise(sharp, 12.0, limit=3.0, attempts=(MeshAttempt("ftetwild"),))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("make, edge", [(sf.genus_one_liver, 10.0), (sf.thin_lobe_liver, 8.0), (sf.uneven_liver, 10.0),
                                        (sf.other_generator_liver, 10.0)])
def test_other_generators_mesh_above_the_floor(make, edge):
    surface = make()
    mesh, report = mesh_liver(surface, edge)
    _floor(mesh)
    assert abs(report["volume_mm3"] - surface.volume) / surface.volume < 0.05
    boundary = trimesh.Trimesh(mesh.nodes, mesh.boundary_faces(), process=True)
    assert boundary.is_watertight and boundary.euler_number == surface.euler_number  # genus kept


def test_no_mesher_outlives_its_caller(tmp_path):
    """A caller killed mid-mesh (Ctrl-C'd CLI, stopped server) leaves no mesher running."""
    import subprocess
    import sys
    import time

    import psutil

    script = tmp_path / "caller.py"
    here = str(__import__("pathlib").Path(__file__).parent)
    script.write_text(
        f"import sys; sys.path.insert(0, {here!r})\n"
        "import surface_fixtures as sf\n"
        "from navapp.anatomy.meshing import tetrahedralise, MeshAttempt\n"
        "tetrahedralise(sf.sharp_ridged_liver(3.0), 10.0, attempts=(MeshAttempt('ftetwild'),))\n")
    caller = subprocess.Popen([sys.executable, str(script)])
    try:
        deadline = time.monotonic() + 60
        workers = []
        while time.monotonic() < deadline and not workers:
            time.sleep(0.2)
            workers = [p for p in psutil.Process(caller.pid).children() if "mesh_worker" in " ".join(p.cmdline())]
        assert workers, "the caller never started a mesher"
        caller.kill()
        caller.wait()
        gone, alive = psutil.wait_procs(workers, timeout=5)
        assert not alive
    finally:
        caller.kill()

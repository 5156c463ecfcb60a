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

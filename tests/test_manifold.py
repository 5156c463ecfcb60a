"""Pinched boundaries: a tet mesh whose solid touches itself along an edge or at a point.

The meshes are voxelised label maps (each voxel six Kuhn tets), the classic source of
such pinches; trimesh judges every boundary independently of navapp's own check.
"""

import itertools

import numpy as np
import pytest
import trimesh

from navapp.anatomy import meshing
from navapp.anatomy.manifold import boundary_defects, mend_pinches
from navapp.anatomy.meshing import MeshAttempt, TetMesh, tet_volumes


def voxel_mesh(mask, h=5.0) -> TetMesh:
    """Conforming tet mesh of the voxels of ``mask`` (edge ``h`` mm): six tets per voxel
    along its main diagonal, so that neighbouring voxels share whole faces."""
    mask = np.asarray(mask, bool)
    shape = np.array(mask.shape) + 1
    paths = []
    for perm in itertools.permutations(range(3)):
        corner, path = np.zeros(3, int), [np.zeros(3, int)]
        for axis in perm:
            corner = corner.copy()
            corner[axis] += 1
            path.append(corner)
        paths.append(np.array(path))
    vox = np.argwhere(mask)
    tets = np.concatenate([np.ravel_multi_index(tuple((vox[:, None, :] + p[None]).reshape(-1, 3).T), shape)
                           .reshape(-1, 4) for p in paths])
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3) * float(h)
    neg = tet_volumes(grid, tets) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    used = np.unique(tets)
    remap = np.full(len(grid), -1)
    remap[used] = np.arange(len(used))
    return TetMesh(grid[used], remap[tets])


def edge_pinched_ring():
    """A U of voxels, extruded 3 deep, whose two ends touch along one line (a pinched ring)."""
    pattern = np.array([[1, 1, 1, 0],
                        [1, 0, 1, 0],
                        [1, 0, 0, 1],
                        [1, 1, 1, 1]])[::-1].T  # [x, y]
    return voxel_mesh(np.repeat(pattern[:, :, None], 3, axis=2))


def vertex_pinched_loop():
    """A chain of voxels whose ends (1, 2, 0) and (2, 1, 1) share only one corner."""
    mask = np.zeros((3, 3, 2), bool)
    for v in [(0, 0, 0), (1, 0, 0), (2, 0, 0), (0, 1, 0), (0, 2, 0), (1, 2, 0), (2, 0, 1), (2, 1, 1)]:
        mask[v] = True
    return voxel_mesh(mask)


def _trimesh_boundary(mesh):
    return trimesh.Trimesh(mesh.nodes, mesh.boundary_faces(), process=True)


def test_simplex_keys_match_for_the_same_nodes_in_any_order_also_past_int64():
    from navapp.anatomy.tets import simplex_keys

    faces = np.array([[3, 1, 2], [2, 3, 1], [1, 2, 4], [4, 1, 2], [5, 6, 7]])
    k = simplex_keys(faces)
    assert k[0] == k[1] and k[2] == k[3] and len(set(k.tolist())) == 3
    # with 2²² nodes, a·base² + b·base + c wraps past 2⁶⁴: these two faces would share a key
    n = 2 ** 22
    big = np.array([[1, 2 ** 21, n - 1], [1 + 2 ** 20, 2 ** 21, n - 1], [n - 1, 2 ** 21, 1]])
    k = simplex_keys(big)
    assert k[0] != k[1] and k[0] == k[2]


def test_a_solid_block_is_a_closed_manifold():
    mask = np.ones((3, 2, 4), bool)
    mesh = voxel_mesh(mask)
    assert boundary_defects(mesh).ok
    surf = _trimesh_boundary(mesh)
    assert surf.is_watertight and surf.euler_number == 2
    assert np.isclose(tet_volumes(mesh.nodes, mesh.tets).sum(), 24 * 125.0)


def test_an_edge_pinch_is_found_where_trimesh_sees_an_open_boundary():
    mesh = edge_pinched_ring()
    assert not _trimesh_boundary(mesh).is_watertight  # four faces meet on the pinched line
    defects = boundary_defects(mesh)
    assert not defects.ok and defects.parts == 1
    # the pinch is the line x = 15, y = 10 mm, z from 0 to 15: three grid edges
    ends = mesh.nodes[defects.edges]
    assert len(defects.edges) == 3
    assert np.allclose(ends[:, :, 0], 15.0) and np.allclose(ends[:, :, 1], 10.0)


def test_a_vertex_pinch_is_found_where_trimesh_counts_the_wrong_euler_number():
    mesh = vertex_pinched_loop()
    surf = _trimesh_boundary(mesh)
    # every edge has two faces, but a ball's boundary has Euler number 2: the point contact makes it 1
    assert surf.is_watertight and surf.euler_number == 1
    defects = boundary_defects(mesh)
    assert len(defects.edges) == 0 and defects.parts == 1
    assert len(defects.vertices) == 1 and np.allclose(mesh.nodes[defects.vertices[0]], [10.0, 10.0, 5.0])


def test_separate_parts_are_reported():
    mask = np.zeros((4, 4, 4), bool)
    mask[:2, :2, :2] = mask[2:, 2:, 2:] = True
    defects = boundary_defects(voxel_mesh(mask))
    assert defects.parts == 2 and not defects.ok


@pytest.mark.parametrize("make", [edge_pinched_ring, vertex_pinched_loop])
def test_mending_opens_the_pinch_and_keeps_the_rest(make):
    mesh = make()
    mended, removed = mend_pinches(mesh)
    assert boundary_defects(mended).ok
    surf = _trimesh_boundary(mended)
    # an opened ring is a ball: closed, two-manifold, Euler number 2, one body
    assert surf.is_watertight and surf.is_winding_consistent and surf.euler_number == 2 and surf.body_count == 1
    # only tets at the contact go: a few of them, and the volume trimesh encloses is the tets'
    assert 0 < removed <= 12 and len(mended.tets) == len(mesh.tets) - removed
    assert np.isclose(surf.volume, tet_volumes(mended.nodes, mended.tets).sum())
    assert tet_volumes(mended.nodes, mended.tets).sum() > 0.9 * tet_volumes(mesh.nodes, mesh.tets).sum()


def test_the_mesh_chain_mends_a_pinched_mesh(monkeypatch):
    """A mesher returning a pinched mesh: the chain opens the pinch and says so."""
    pinched = edge_pinched_ring()
    monkeypatch.setattr(meshing, "_run_attempt", lambda *a: (pinched.nodes, pinched.tets))
    surface = trimesh.creation.box((20.0, 20.0, 15.0))
    mesh, log = meshing._mesh_with_log(surface, 5.0, 0, 60.0, (MeshAttempt("ftetwild"),))
    assert log[-1]["outcome"] == "ok" and "opened by removing" in log[-1]["mended"]
    assert _trimesh_boundary(mesh).is_watertight and boundary_defects(mesh).ok


def test_the_mesh_chain_moves_on_when_a_pinch_cannot_be_mended(monkeypatch):

    pinched, clean = edge_pinched_ring(), voxel_mesh(np.ones((2, 2, 2), bool))
    calls = iter([(pinched.nodes, pinched.tets), (clean.nodes, clean.tets)])
    monkeypatch.setattr(meshing, "_run_attempt", lambda *a: next(calls))
    # mending fails (patched where the chain looks it up: meshing imports it by name)
    monkeypatch.setattr(meshing, "mend_pinches", lambda mesh, max_rounds=20: (mesh, 0))
    surface = trimesh.creation.box((10.0, 10.0, 10.0))
    attempts = (MeshAttempt("ftetwild"), MeshAttempt("ftetwild", edge_scale=0.85))
    mesh, log = meshing._mesh_with_log(surface, 5.0, 0, 60.0, attempts)
    assert log[0]["outcome"].startswith("boundary not a closed manifold (3 pinched edges")
    assert log[1]["method"] == "ftetwild at 0.85 × edge" and log[1]["outcome"] == "ok"
    assert len(mesh.tets) == len(clean.tets)

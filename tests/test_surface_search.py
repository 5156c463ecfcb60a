"""The closest-point search of LM (a hierarchy built once, refit as the surface deforms),
checked against trimesh's closest points and the k-d tree fallback."""

import numpy as np
import pytest
import trimesh

from navapp.geometry import surface_search
from navapp.geometry.surface_search import SurfaceSearch


def _blob():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=60.0)
    v = np.asarray(mesh.vertices) * [1.3, 1.0, 0.7]  # an ellipsoid: triangles of uneven shape
    return v, np.asarray(mesh.faces)


def _deformed(v, s):
    c = v.mean(0)
    return v + s * np.sin((v - c) / 25.0)[:, [1, 2, 0]]


BACKENDS = ["kdtree"] + (["fcpw"] if surface_search.available() else [])


@pytest.mark.parametrize("backend", BACKENDS)
def test_closest_points_as_the_surface_deforms_match_trimesh(backend):
    """One search follows a surface through several deformations (each a refit of the
    hierarchy built on the undeformed one) and finds trimesh's closest points on each,
    for points near, on, deep inside and far outside the surface. The k-d tree fallback
    tests the triangles around the nearest vertices: exact near the surface only."""
    v0, faces = _blob()
    rng = np.random.default_rng(3)
    search = SurfaceSearch(faces, v0, backend=backend)
    for s in (0.0, 3.0, 8.0, 1.0):
        v = _deformed(v0, s)
        mesh = trimesh.Trimesh(v, faces, process=False)
        on = mesh.sample(300, seed=int(s))
        pts = np.vstack([on + rng.normal(0, 4.0, on.shape), on] + ([on * 0.6, on * 1.4] if backend == "fcpw" else []))
        face, bary, q = search.closest(pts, v)
        ref, dist, _ = trimesh.proximity.closest_point(mesh, pts)
        assert np.allclose(np.linalg.norm(q - pts, axis=1), dist, atol=1e-6)
        assert np.allclose(q, np.einsum("ij,ijk->ik", bary, v[faces[face]]))
        assert np.all(bary >= -1e-12) and np.allclose(bary.sum(1), 1.0)
        # the same point wherever the closest point is unique (not equidistant from two patches)
        assert np.quantile(np.linalg.norm(q - ref, axis=1), 0.99) < 1e-6


@pytest.mark.skipif(not surface_search.available(), reason="fcpw not installed")
def test_an_answer_does_not_depend_on_earlier_searches():
    """A search refit through other geometries answers bit for bit as a fresh one: the
    evaluations of a warm start must equal a fresh model's (tests/test_live_reuse.py)."""
    v0, faces = _blob()
    pts = trimesh.Trimesh(v0, faces).sample(500, seed=1) * 1.05
    used = SurfaceSearch(faces, v0)
    for s in (5.0, -4.0, 9.0):
        used.closest(pts, _deformed(v0, s))
    v = _deformed(v0, 2.0)
    a, b = used.closest(pts, v), SurfaceSearch(faces, v0).closest(pts, v)
    assert used.refits == 4
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_no_points():
    v0, faces = _blob()
    face, bary, q = SurfaceSearch(faces, v0).closest(np.zeros((0, 3)), v0)
    assert face.shape == (0,) and bary.shape == q.shape == (0, 3)

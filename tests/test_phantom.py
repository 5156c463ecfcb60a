import numpy as np
import pytest
import trimesh

from navapp.anatomy.model import REGION_NAMES
from navapp.anatomy.phantom import build_phantom, make_phantom


def test_surfaces_are_closed_manifolds(phantoms):
    for m in phantoms:
        for mesh in (m.liver, m.portal, m.hepatic):
            assert mesh.is_watertight and mesh.is_winding_consistent
            assert mesh.volume > 0  # outward normals
            assert mesh.euler_number == 2  # one sphere-like component


def test_liver_size_and_distinctness(phantoms):
    vols = []
    for m in phantoms:
        ext = m.liver.extents
        assert 150 <= ext[0] <= 225, ext  # left-right width, mm (~150–220)
        assert 90 <= ext[1] <= 170 and 90 <= ext[2] <= 170
        assert 0.9e6 < m.liver.volume < 2.2e6  # mm³: 0.9–2.2 litres
        vols.append(m.liver.volume)
    assert len({round(v) for v in vols}) == 3


def test_deterministic():
    a, b = build_phantom(1), build_phantom(1)  # built afresh twice, not the copy make_phantom keeps
    assert np.array_equal(a.liver.vertices, b.liver.vertices)
    assert np.array_equal(a.portal_centerline.points, b.portal_centerline.points)
    assert np.array_equal(a.regions, b.regions)
    # make_phantom's copy is the same phantom, and a caller changing it changes nobody else's
    kept = make_phantom(1)
    for name in ("liver", "portal", "hepatic"):
        assert np.array_equal(getattr(kept, name).vertices, getattr(a, name).vertices)
        assert np.array_equal(getattr(kept, name).faces, getattr(a, name).faces)
    assert np.array_equal(kept.regions, a.regions) and kept.meta == a.meta
    assert [t.name for t in kept.targets] == [t.name for t in a.targets]
    kept.liver.vertices += 5.0
    kept.regions[:] = 0
    kept.targets.clear()
    again = make_phantom(1)
    assert np.array_equal(again.liver.vertices, a.liver.vertices) and np.array_equal(again.regions, a.regions)
    assert len(again.targets) == len(a.targets) and again.liver is not kept.liver


def test_vessels_inside_liver(phantoms):
    rng = np.random.default_rng(0)
    for m in phantoms:
        for mesh in (m.portal, m.hepatic):
            pts = mesh.vertices[rng.choice(len(mesh.vertices), 400, replace=False)]
            depth = trimesh.proximity.signed_distance(m.liver, pts)  # positive inside
            assert depth.min() > 0.5, depth.min()


def test_vessel_trees(phantoms):
    for m in phantoms:
        for cl in (m.portal_centerline, m.hepatic_centerline):
            assert 3.0 - 1e-9 <= cl.radius.min() and cl.radius.max() <= 8.0
            assert cl.branch.max() + 1 >= 7  # at least two generations of branching
            t = cl.tangents
            assert np.allclose(np.linalg.norm(t, axis=1), 1.0)
        # the portal trunk enters at the hilum: its first point is the lowest of the trunk
        trunk = m.portal_centerline.points[m.portal_centerline.branch == 0]
        assert trunk[0, 2] < trunk[-1, 2]
        # hepatic veins converge superior-posteriorly: the confluence is their first point
        hv = m.hepatic_centerline.points
        assert hv[0, 2] > np.median(hv[:, 2]) and hv[0, 1] < np.median(hv[:, 1])


def test_region_labels(phantoms):
    for m in phantoms:
        counts = np.bincount(m.regions, minlength=len(REGION_NAMES))
        assert (counts > 0).all(), counts
        n = m.liver.vertex_normals
        assert n[m.region_mask("anterior"), 1].mean() > 0.4
        assert n[m.region_mask("posterior"), 1].mean() < 0.0
        # anterior vertices are visible from in front: a ray toward +y leaves the liver
        ant = np.flatnonzero(m.region_mask("anterior"))[::40]
        origins = m.liver.vertices[ant] + 0.5 * n[ant]
        hit = m.liver.ray.intersects_any(origins, np.tile([0.0, 1.0, 0.0], (len(ant), 1)))
        assert hit.mean() < 0.2
        # the left ridge lies left of the right ridge
        v = m.liver.vertices
        assert v[m.region_mask("ridge_left"), 0].mean() > v[m.region_mask("ridge_right"), 0].mean()


def test_bad_index():
    with pytest.raises(ValueError):
        make_phantom(-1)

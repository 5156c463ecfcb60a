"""Vessel centerlines extracted from vessel surfaces (navapp.anatomy.skeleton)."""

import numpy as np
import pytest
import trimesh
from skimage.measure import marching_cubes

from navapp.anatomy import sdf
from navapp.anatomy.model import Centerline, polyline_tangents
from navapp.anatomy.skeleton import vessel_centerline, voxelize


def _distance_to_polylines(q: np.ndarray, cl: Centerline) -> np.ndarray:
    """(n,) mm from each point of q to the nearest segment of cl."""
    seg = cl.segments()
    a, b = cl.points[seg[:, 0]], cl.points[seg[:, 1]]
    ab = b - a
    t = np.clip(np.einsum("nsk,sk->ns", q[:, None] - a, ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    return np.linalg.norm(q[:, None] - (a + t[..., None] * ab), axis=2).min(1)


def _densify(cl: Centerline, step: float = 0.5) -> np.ndarray:
    out = []
    for i, j in cl.segments():
        n = max(int(np.linalg.norm(cl.points[j] - cl.points[i]) / step), 1)
        out.append(cl.points[i] + np.linspace(0, 1, n, endpoint=False)[:, None] * (cl.points[j] - cl.points[i]))
    return np.vstack(out)


def _assert_valid(cl: Centerline):
    """What caseio.read_case demands of a centerline file, and what Centerline promises."""
    assert cl.points.shape == (len(cl.branch), 3) and cl.radius.shape == (len(cl.branch),)
    assert np.isfinite(cl.points).all() and (cl.radius > 0).all()
    _, counts = np.unique(cl.branch, return_counts=True)
    assert counts.min() >= 2
    # each branch id is one consecutive run
    runs = 1 + np.count_nonzero(cl.branch[1:] != cl.branch[:-1])
    assert runs == len(counts)
    assert (np.linalg.norm(polyline_tangents(cl.points, cl.branch), axis=1) > 0).all()


@pytest.mark.parametrize("vessel", ["portal", "hepatic"])
def test_phantom_centerlines_recovered_within_a_millimetre(phantoms, vessel):
    for model in phantoms:
        truth = model.centerline(vessel)
        cl = vessel_centerline(model.vessel(vessel))
        _assert_valid(cl)
        d = _distance_to_polylines(cl.points, truth)
        assert np.median(d) <= 1.0 and np.percentile(d, 95) <= 1.0, (model.name, np.median(d), np.percentile(d, 95))
        # coverage: the phantom's centerline is followed along (nearly) all its length
        covered = _distance_to_polylines(_densify(truth), cl) < 2.0
        assert covered.mean() >= 0.95, (model.name, covered.mean())
        # radius from the distance transform, against the radius the tube was built with
        k = np.argmin(np.linalg.norm(cl.points[:, None] - truth.points[None], axis=2), axis=1)
        assert np.median(np.abs(cl.radius - truth.radius[k])) < 0.4


def _tube(cl: Centerline, spacing: float = 0.5) -> trimesh.Trimesh:
    """Marching-cubes surface of the union of capsules along cl's segments (an analytic
    tube; vessels.tube_surface is meant for the phantoms' 2 mm segments)."""
    # offset so that no grid node lies exactly on the surface (marching cubes then makes
    # degenerate triangles and the merged mesh is not watertight)
    lo = cl.points.min(0) - cl.radius.max() - 2 * spacing + 0.0123
    hi = cl.points.max(0) + cl.radius.max() + 2 * spacing
    axes = [np.arange(a, b + spacing, spacing) for a, b in zip(lo, hi, strict=True)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    field = np.full(g.shape[:3], np.inf)
    for i, j in cl.segments():
        dist, t = sdf.capsule_distance(g, cl.points[i], cl.points[j])
        field = np.minimum(field, dist - (cl.radius[i] + (cl.radius[j] - cl.radius[i]) * t))
    verts, faces, _, _ = marching_cubes(field, 0.0, spacing=(spacing,) * 3)
    mesh = trimesh.Trimesh(verts + lo, faces[:, ::-1], process=True)
    mesh.fix_normals()
    assert mesh.is_watertight
    return mesh


def test_straight_tube_gives_one_branch_on_its_axis_with_its_radius():
    a, b, r = np.array([-20.0, 5.0, 3.0]), np.array([25.0, -10.0, 30.0]), 4.0
    cl = vessel_centerline(_tube(Centerline(np.array([a, b]), np.zeros(2, int), np.array([r, r]))))
    _assert_valid(cl)
    assert len(np.unique(cl.branch)) == 1
    axis = (b - a) / np.linalg.norm(b - a)
    off = cl.points - a - np.outer((cl.points - a) @ axis, axis)
    assert np.linalg.norm(off, axis=1).max() < 0.5
    # the capsule's medial axis is the segment a-b: the ends are found to within a voxel or two
    t = (cl.points - a) @ axis
    assert t.min() < 1.5 and t.max() > np.linalg.norm(b - a) - 1.5
    assert abs(np.median(cl.radius) - r) < 0.3
    # ~1.5 mm spacing along the branch
    step = np.linalg.norm(np.diff(cl.points, axis=0), axis=1)
    assert 1.0 < step.mean() < 2.0


def test_flat_ended_cylinder_has_no_spurs():
    mesh = trimesh.creation.cylinder(radius=5.0, height=50.0, sections=64)
    cl = vessel_centerline(mesh)
    _assert_valid(cl)
    assert len(np.unique(cl.branch)) == 1
    assert np.abs(cl.points[:, :2]).max() < 0.5


def test_y_shaped_tube_gives_three_branches_meeting_at_the_fork():
    fork = np.array([0.0, 0.0, 0.0])
    ends = np.array([[0.0, 0.0, -40.0], [25.0, 3.0, 30.0], [-24.0, -2.0, 32.0]])
    pts = np.vstack([[ends[0], fork], [fork, ends[1]], [fork, ends[2]]])
    truth = Centerline(pts, np.repeat([0, 1, 2], 2), np.array([5.0, 5.0, 3.5, 3.5, 3.5, 3.5]))
    cl = vessel_centerline(_tube(truth))
    _assert_valid(cl)
    assert len(np.unique(cl.branch)) == 3
    d = _distance_to_polylines(cl.points, truth)
    assert np.percentile(d, 95) < 1.0
    # all three branches share one end point, near the fork
    branch_ends = np.array([cl.points[cl.branch == k][[0, -1]] for k in range(3)]).reshape(-1, 3)
    near = branch_ends[np.linalg.norm(branch_ends - fork, axis=1) < 5.0]
    assert len(near) == 3 and np.ptp(near, axis=0).max() < 1e-9
    assert np.linalg.norm(near[0] - fork) < 1.5


def test_voxelize_matches_the_analytic_volume():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=10.0)
    inside, origin = voxelize(sphere, 0.5)
    assert abs(inside.sum() * 0.125 - sphere.volume) / sphere.volume < 0.02
    centre = np.round((np.zeros(3) - origin) / 0.5).astype(int)
    assert inside[tuple(centre)]


def test_empty_volume_is_an_error():
    tiny = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    with pytest.raises(ValueError):
        vessel_centerline(tiny, voxel=0.5)


def test_extracted_centerline_survives_a_case_folder(phantoms, tmp_path):
    from navapp.anatomy.caseio import read_case, write_preop
    from navapp.anatomy.model import PreopModel

    model = phantoms[1]
    cl = vessel_centerline(model.portal)
    write_preop(PreopModel(liver=model.liver, portal=model.portal, portal_centerline=cl), tmp_path)
    back = read_case(tmp_path).preop.portal_centerline
    assert np.allclose(back.points, cl.points, atol=1e-3) and (back.branch == cl.branch).all()

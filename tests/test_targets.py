"""Tumour targets: reading, phantoms, registration, and the live-view distances."""

import numpy as np
import pytest
import trimesh

from navapp.anatomy.caseio import read_case, write_preop
from navapp.anatomy.model import PreopModel
from navapp.anatomy.phantom import irregular_ellipsoid
from navapp.anatomy.targets import Target, from_surface, map_targets, read_targets, sphere, target_points
from navapp.cli import main
from navapp.errors import InputError
from navapp.geometry.targets_distance import (
    ImagePlane,
    plane_distances,
    plane_sections,
    rectangle_distance,
    section_polylines,
    signed_distance,
    tip_distances,
)


def ellipsoid_liver():
    liver = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    liver.apply_scale([90.0, 60.0, 50.0])
    return trimesh.Trimesh(liver.vertices, liver.faces, process=False)


def lumpy(centre=(3.0, -2.0, 1.0), radii=(12.0, 9.0, 7.0), seed=0):
    return irregular_ellipsoid(centre, radii, np.random.default_rng(seed))


def plane(origin, u, v, width=64.0, depth=80.0):
    u = np.asarray(u, float) / np.linalg.norm(u)
    v = np.asarray(v, float) - (np.asarray(v, float) @ u) * u
    return ImagePlane(np.asarray(origin, float), u, v / np.linalg.norm(v), width, depth)


def random_plane(rng, centre, spread=30.0):
    """A random rectangle whose middle lies about ``spread`` mm from ``centre``."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    depth = rng.uniform(20, 80)
    middle = centre + rng.normal(size=3) * spread
    return plane(middle - q[:, 1] * depth / 2, q[:, 0], q[:, 1], rng.uniform(20, 64), depth)


# ---------------------------------------------------------------- distances against brute force

def test_tip_signed_distance_matches_trimesh():
    m = lumpy()
    rng = np.random.default_rng(1)
    pts = m.centroid + rng.normal(size=(300, 3)) * 10.0  # inside, near and outside
    ours = signed_distance(pts, m.vertices, m.faces)
    theirs = -trimesh.proximity.signed_distance(m, pts)  # trimesh: positive inside
    assert (ours < 0).sum() > 30 and (ours > 0).sum() > 30
    np.testing.assert_allclose(ours, theirs, atol=1e-6)
    t = from_surface("t", m)
    assert tip_distances(pts[0], [t])[0] == pytest.approx(ours[0])


def test_point_target_distances_are_to_the_point():
    t = Target("p", np.array([1.0, 2.0, 3.0]))
    assert tip_distances([4.0, 6.0, 3.0], [t])[0] == pytest.approx(5.0)
    P = plane([1.0, 2.0, 10.0], [1, 0, 0], [0, 0, 1])  # the point is 7 mm above the top edge
    assert plane_distances(P, [t])[0] == pytest.approx(7.0)
    assert plane_sections(P, [t]) == [[]]


def brute_rectangle_distance(P: ImagePlane, mesh, n=40000):
    """Min over dense surface samples (and the vertices) of the closed-form point–rectangle distance."""
    pts = np.vstack([mesh.vertices, trimesh.sample.sample_surface_even(mesh, n, seed=3)[0]])
    loc = P.to_plane(pts)
    du = loc[:, 0] - np.clip(loc[:, 0], -P.width_mm / 2, P.width_mm / 2)
    dv = loc[:, 1] - np.clip(loc[:, 1], 0, P.depth_mm)
    return float(np.sqrt(du ** 2 + dv ** 2 + loc[:, 2] ** 2).min())


def test_plane_distance_matches_dense_sampling():
    m = lumpy()
    rng = np.random.default_rng(2)
    seen_zero = seen_far = 0
    for i in range(30):
        P = random_plane(rng, m.centroid, spread=(5.0, 20.0, 40.0)[i % 3])
        ours = rectangle_distance(P, m.vertices, m.faces)
        brute = brute_rectangle_distance(P, m)
        # samples can only overestimate the distance; they come within a sample spacing (~0.3 mm)
        assert ours <= brute + 1e-9
        assert brute - ours < 0.35, (ours, brute)
        seen_zero += ours == 0.0
        seen_far += ours > 2.0
    assert seen_zero >= 3 and seen_far >= 3  # both cases exercised


def test_plane_distance_edge_and_inside_cases():
    s = sphere("s", [0.0, 0.0, 0.0], 10.0).surface
    r = np.linalg.norm(s.vertices, axis=1).min()  # the icosphere's faces sit a little inside 10 mm
    # the rectangle's top edge runs 5 mm above the sphere, its plane cuts it: distance via the edge
    P = plane([0.0, 0.0, 15.0], [1, 0, 0], [0, 0, 1])
    d = rectangle_distance(P, s.vertices, s.faces)
    assert d == pytest.approx(brute_rectangle_distance(P, s), abs=0.3) and 4.5 < d < 5.5
    # a small image wholly inside a large target: 0 (the image shows only target)
    big = sphere("b", [0.0, 0.0, 0.0], 60.0).surface
    Q = plane([0.0, 0.0, -10.0], [1, 0, 0], [0, 0, 1], width=10.0, depth=10.0)
    assert rectangle_distance(Q, big.vertices, big.faces) == 0.0
    assert r > 9.0


# ---------------------------------------------------------------- the plane section

def _segments_2d(P, mesh):
    seg = trimesh.intersections.mesh_plane(mesh, P.normal, P.origin)
    return np.stack([(seg - P.origin) @ P.u, (seg - P.origin) @ P.v], axis=-1)


@pytest.mark.parametrize("which", ["lumpy", "torus"])
def test_section_polylines_match_trimesh(which):
    if which == "lumpy":
        m = lumpy()
        P = plane(m.centroid + [0.5, 0.3, 0.2], [1, 0.2, 0], [0, 0.1, 1])
        loops = 1
    else:  # a torus cut through its hole: two separate loops
        m = trimesh.creation.torus(major_radius=20.0, minor_radius=6.0, major_sections=48, minor_sections=24)
        P = plane([0.0, 0.37, 0.11], [1, 0, 0], [0, 0.3, 1])
        loops = 2
    lines = section_polylines(P, m.vertices, m.faces)
    ref = _segments_2d(P, m)
    assert len(lines) == loops
    for ln in lines:
        assert np.allclose(ln[0], ln[-1])  # closed
    ours_len = sum(np.linalg.norm(np.diff(ln, axis=0), axis=1).sum() for ln in lines)
    ref_len = np.linalg.norm(ref[:, 1] - ref[:, 0], axis=1).sum()
    assert ours_len == pytest.approx(ref_len, rel=1e-9)
    # every polyline point is an end of one of trimesh's segments, and every segment is an edge of a polyline
    ends = ref.reshape(-1, 2)
    pts = np.vstack(lines)
    assert np.abs(pts[:, None] - ends[None]).sum(-1).min(1).max() < 1e-9
    ours_edges = np.vstack([np.stack([ln[:-1], ln[1:]], 1) for ln in lines])
    assert len(ours_edges) == len(ref)
    # the loops are trimesh's section's loops: as many, enclosing the same areas
    sec = m.section(plane_origin=P.origin, plane_normal=P.normal)
    theirs = [np.stack([(d - P.origin) @ P.u, (d - P.origin) @ P.v], -1) for d in sec.discrete]
    assert len(theirs) == loops

    def area(ln):
        return 0.5 * abs(np.dot(ln[:-1, 0], ln[1:, 1]) - np.dot(ln[1:, 0], ln[:-1, 1]))

    assert sorted(area(ln) for ln in lines) == pytest.approx(sorted(area(ln) for ln in theirs), rel=1e-6)


def test_section_through_vertices_still_chains():
    """A plane through mesh vertices (the torus's equator) gives the same closed loops."""
    m = trimesh.creation.torus(major_radius=20.0, minor_radius=6.0, major_sections=48, minor_sections=24)
    P = plane([0.0, 0.0, 0.0], [1, 0, 0], [0, 0.3, 1])
    lines = section_polylines(P, m.vertices, m.faces)
    assert len(lines) == 2 and all(np.allclose(ln[0], ln[-1]) for ln in lines)
    ref = _segments_2d(P, m)
    total = sum(np.linalg.norm(np.diff(ln, axis=0), axis=1).sum() for ln in lines)
    assert total == pytest.approx(np.linalg.norm(ref[:, 1] - ref[:, 0], axis=1).sum(), rel=1e-9)


def test_section_misses_give_no_polylines():
    m = lumpy()
    P = plane(m.centroid + [0, 0, 40.0], [1, 0, 0], [0, 1, 0])
    assert section_polylines(P, m.vertices, m.faces) == []


# ---------------------------------------------------------------- reading targets

def test_targets_from_files_navapp_did_not_make(tmp_path):
    liver = ellipsoid_liver()
    write_preop(PreopModel(liver=liver), tmp_path)
    tdir = tmp_path / "preop" / "targets"
    tdir.mkdir()
    ico = trimesh.creation.icosphere(subdivisions=3, radius=8.0)
    ico.apply_translation([20.0, -10.0, 5.0])
    ico.export(tdir / "lesion A.stl")  # STL: triangle soup, float32, duplicates to merge
    (tdir / "marks.csv").write_text("name,x,y,z,radius_mm\nT2,-30,5,0,6.5\nP1,10,10,-10,\n")
    case = read_case(tmp_path)
    by = {t.name: t for t in case.preop.targets}
    assert sorted(by) == ["P1", "T2", "lesion A"]
    a = by["lesion A"]
    assert len(a.surface.vertices) == 642  # duplicates merged
    np.testing.assert_allclose(a.centre, [20.0, -10.0, 5.0], atol=0.05)
    assert a.diameter_mm == pytest.approx(16.0, abs=0.01)
    assert by["T2"].diameter_mm == pytest.approx(13.0, abs=0.01)
    np.testing.assert_allclose(by["T2"].centre, [-30, 5, 0])
    assert by["P1"].surface is None and by["P1"].diameter_mm == 0.0
    # written by navapp and read again: the same targets
    out = tmp_path / "again"
    write_preop(case.preop, out)
    again = {t.name: t for t in read_case(out).preop.targets}
    assert sorted(again) == sorted(by)
    np.testing.assert_allclose(again["lesion A"].surface.vertices, a.surface.vertices, atol=1e-5)
    np.testing.assert_allclose(again["P1"].centre, by["P1"].centre)


def _bad(tmp_path, name, writer):
    liver = ellipsoid_liver()
    case = tmp_path / "case"
    write_preop(PreopModel(liver=liver), case)
    (case / "intraop").mkdir()
    (case / "intraop" / "anterior.csv").write_text("x,y,z\n0,60,0\n10,59,0\n0,59,10\n")
    tdir = case / "preop" / "targets"
    tdir.mkdir()
    writer(tdir / name)
    return case, tdir / name


def _open(p):
    m = trimesh.creation.icosphere(subdivisions=2, radius=8.0)
    trimesh.Trimesh(m.vertices, m.faces[:-3], process=False).export(p)


def _nonmanifold(p):
    """Two tetrahedra sharing one edge (four triangles on it): closed but not a manifold."""
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [0, -10, 0], [0, 0, -10.0]])
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [0, 1, 4], [0, 5, 1], [0, 4, 5], [1, 5, 4]])
    trimesh.Trimesh(v, f, process=False).export(p)


def _outside(p):
    m = trimesh.creation.icosphere(subdivisions=2, radius=8.0)
    m.apply_translation([200.0, 0.0, 0.0])
    m.export(p)


@pytest.mark.parametrize("name, writer, words", [
    ("open.stl", _open, "holes"),
    ("bowtie.ply", _nonmanifold, "it must be one piece"),
    ("far.obj", _outside, "outside the liver"),
    ("pts.csv", lambda p: p.write_text("name,x,y,z\nA,0,0,0\nB,0,zero,0\n"), "not numeric"),
    ("pts.csv", lambda p: p.write_text("id,x,y,z\nA,0,0,0\n"), "header"),
    ("pts.csv", lambda p: p.write_text("name,x,y,z,radius_mm\nA,0,0,0,-2\n"), "radius_mm must be positive"),
])
def test_bad_target_files_give_one_line(tmp_path, capsys, name, writer, words):
    case, path = _bad(tmp_path, name, writer)
    with pytest.raises(InputError) as exc:
        read_case(case)
    assert words in str(exc.value) and str(path) in str(exc.value) and "\n" not in str(exc.value)
    assert main(["--quiet", "register", str(case)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and name in err[0]


def test_import_takes_targets(tmp_path):
    from navapp.anatomy.importer import import_case

    liver = ellipsoid_liver()
    liver.export(tmp_path / "liver.stl")
    ico = trimesh.creation.icosphere(subdivisions=3, radius=7.0)
    ico.apply_translation([15.0, 10.0, 5.0])
    ico.export(tmp_path / "t1.stl")
    (tmp_path / "pts.csv").write_text("name,x,y,z,radius_mm\nT2,-20,5,0,5\n")
    import_case(tmp_path / "case", liver=tmp_path / "liver.stl", frame="LPS",
                targets=[tmp_path / "t1.stl", tmp_path / "pts.csv"])
    by = {t.name: t for t in read_case(tmp_path / "case").preop.targets}
    # LPS → navapp's LAS flips y
    np.testing.assert_allclose(by["t1"].centre, [15.0, -10.0, 5.0], atol=0.05)
    np.testing.assert_allclose(by["T2"].centre, [-20.0, -5.0, 0.0], atol=1e-6)
    assert by["t1"].surface.volume > 0  # still facing outward after the mirroring frame change


# ---------------------------------------------------------------- phantoms

def _lower_bound_distance(mesh, points):
    """A lower bound on each point's distance to ``mesh``'s surface: nearest-vertex distance
    less the longest edge (every surface point lies within an edge of a vertex); where that
    bound is too small to tell, the exact distance (trimesh)."""
    from scipy.spatial import cKDTree

    edge = float(mesh.edges_unique_length.max())
    d = cKDTree(mesh.vertices).query(points)[0] - edge
    near = d < 10.0
    if near.any():
        d[near] = trimesh.proximity.closest_point(mesh, points[near])[1]
    return d


def test_phantom_tumours_inside_liver(phantoms):
    from navapp.geometry.targets_distance import winding_numbers

    for p in phantoms:
        assert 1 <= len(p.targets) <= 2
        for t in p.targets:
            s = t.surface
            assert s.is_watertight and s.is_winding_consistent and s.volume > 0
            assert 10.0 <= t.diameter_mm <= 30.0
            assert winding_numbers(t.centre, p.liver.vertices, p.liver.faces)[0] > 0.5  # inside the liver
            # every tumour vertex 8 mm from the liver surface (its triangles are far shorter than 8 mm,
            # so the tumour cannot cross it)
            assert float(s.edges_unique_length.max()) < 4.0
            assert _lower_bound_distance(p.liver, s.vertices).min() >= 8.0, (p.name, t.name)
            for v in (p.portal, p.hepatic):
                assert _lower_bound_distance(v, s.vertices).min() > 1.0
        if len(p.targets) == 2:
            a, b = p.targets
            assert np.linalg.norm(a.centre - b.centre) > (a.diameter_mm + b.diameter_mm) / 2


def test_phantom_tumours_leave_the_anatomy_alone(phantoms, monkeypatch):
    """The tumours come from their own random stream: the liver, vessels and labels (and so
    every cache key) are the same bytes whether tumours are made or not. (A hard-coded key
    of the bytes stood here; it changed with the libraries' versions, not with tumours.)"""
    from navapp.anatomy import phantom
    from navapp.cache import content_key

    def key(m):
        return content_key(m.liver.vertices, m.liver.faces, m.portal.vertices, m.portal.faces, m.hepatic.vertices,
                           m.hepatic.faces, m.regions, m.portal_centerline.points, m.hepatic_centerline.points)

    assert phantoms[0].targets
    monkeypatch.setattr(phantom, "make_tumours", lambda *a, **k: [])
    bare = phantom.build_phantom(0)  # built afresh: make_phantom keeps the one with tumours
    assert not bare.targets and key(bare) == key(phantoms[0])


# ---------------------------------------------------------------- carried through registration

def _registration(model, R=None, t=None, beta=None):
    from navapp.registration.libr import LibrResult
    from navapp.registration.pipeline import Registration
    from navapp.registration.rigid import RigidResult

    libr = None if beta is None else LibrResult(beta, 0.0, 0, "test", [], [], {}, 0.0, {})
    R = np.eye(3) if R is None else np.asarray(R, float)
    t = np.zeros(3) if t is None else np.asarray(t, float)
    return Registration(model, RigidResult(R, t, 0, 0.0), libr, {})


def _phantom_targets(phantoms):
    return phantoms[0].targets + [Target("pt", phantoms[0].targets[0].centre + [1.0, 2.0, 0.0])]


def test_identity_registration_leaves_targets(small_model, phantoms):
    from navapp.registration.targets import registered_targets, target_errors, target_interpolation

    targets = _phantom_targets(phantoms)
    beta = np.zeros(3 * small_model.basis.k + 6)
    reg = _registration(small_model, beta=beta)
    B = target_interpolation(reg, targets)
    for moved in (registered_targets(reg, targets), registered_targets(reg, targets, beta, B)):
        for a, b in zip(targets, moved, strict=True):
            assert a.name == b.name
            np.testing.assert_allclose(b.centre, a.centre, atol=1e-9)
            if a.surface is not None:
                np.testing.assert_allclose(b.surface.vertices, a.surface.vertices, atol=1e-9)
                np.testing.assert_array_equal(b.surface.faces, a.surface.faces)
                assert target_errors(b, a)["centroid_mm"] < 1e-6


def test_rigid_registration_moves_targets_rigidly(small_model, phantoms):
    from scipy.spatial.transform import Rotation

    from navapp.registration.targets import registered_targets, target_errors

    targets = _phantom_targets(phantoms)
    R = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
    t = np.array([5.0, -12.0, 30.0])
    for reg, kw in ((_registration(small_model, R, t), {}),
                    (_registration(small_model, R, t, beta=np.ones(3 * small_model.basis.k + 6)), {"rigid": True})):
        moved = registered_targets(reg, targets, **kw)
        for a, b in zip(targets, moved, strict=True):
            np.testing.assert_allclose(b.centre, a.centre @ R.T + t, atol=1e-9)
            if a.surface is not None:
                np.testing.assert_allclose(b.surface.vertices, a.surface.vertices @ R.T + t, atol=1e-9)
                assert b.diameter_mm == pytest.approx(a.diameter_mm)
                assert b.volume_ml == pytest.approx(a.volume_ml)
                np.testing.assert_allclose(b.surface.center_mass, a.surface.center_mass @ R.T + t, atol=1e-9)
                shifted = map_targets([a], lambda p: p @ R.T + t + [3.0, 4.0, 0.0])[0]
                assert target_errors(b, shifted)["centroid_mm"] == pytest.approx(5.0)
                assert target_errors(b, shifted)["mean_vertex_mm"] == pytest.approx(5.0)


def test_deformation_moves_targets_like_the_vessels(small_model, phantoms):
    """A non-zero β moves the targets by ``pipeline.deform_points`` (eq. 8), the map of every
    other model point: not by a copy of it."""
    from navapp.registration.pipeline import deform_points
    from navapp.registration.targets import registered_targets

    targets = phantoms[0].targets
    k = small_model.basis.k
    beta = np.zeros(3 * k + 6)
    beta[: 3 * k] = np.random.default_rng(4).normal(size=3 * k) * 0.3
    moved = registered_targets(_registration(small_model, beta=beta), targets)
    expect = deform_points(small_model.basis, small_model.centroid, beta, target_points(targets))
    got = target_points(moved)
    assert np.abs(got - target_points(targets)).max() > 0.05  # it did deform them
    np.testing.assert_allclose(got, expect, atol=1e-9)


def test_true_targets(tmp_path, small_basis, phantoms):
    from navapp.anatomy.targets import write_targets
    from navapp.anatomy.truth import TruthField, TruthPoints, true_targets

    targets = phantoms[0].targets
    shift = np.array([1.0, -2.0, 0.5])
    field = TruthField(small_basis.nodes, small_basis.tets, np.tile(shift, (len(small_basis.nodes), 1)), np.eye(4))
    truth, source = true_targets(tmp_path, targets, field)  # the field asked at the targets' points
    assert source == "truth/field.npz"
    for a, b in zip(targets, truth, strict=True):
        np.testing.assert_allclose(b.surface.vertices, a.surface.vertices + shift, atol=1e-9)
    # measured points know nothing between them
    points = TruthPoints(small_basis.nodes, small_basis.nodes + shift)
    assert true_targets(tmp_path, targets, points)[0] is None
    write_targets(map_targets(targets, lambda p: p + 2 * shift), tmp_path / "truth" / "targets")
    truth, source = true_targets(tmp_path, targets, field)  # the simulator's files win
    assert source == "truth/targets/"
    for a, b in zip(targets, truth, strict=True):
        np.testing.assert_allclose(b.surface.vertices, a.surface.vertices + 2 * shift, atol=1e-4)
    assert true_targets(tmp_path / "none", targets, None)[0] is None


def test_register_cli_writes_targets(tmp_path, capsys):
    import json

    from navapp.anatomy.targets import write_targets

    case = tmp_path / "c"
    liver = ellipsoid_liver()
    write_preop(PreopModel(liver=liver), case)
    v = liver.vertices
    # 6 mm: a given pose whose trimmed fit moves the data less than 4 mm RMS is kept as
    # aligned (registration/pose.py), so a smaller shift is not an ICP case any more
    shift = np.array([6.0, 0.0, 0.0])
    (case / "intraop").mkdir()
    (case / "intraop/anterior.csv").write_text(
        "x,y,z\n" + "\n".join(",".join(repr(float(x)) for x in r) for r in v[v[:, 1] > 20][::3] + shift) + "\n")
    write_targets([sphere("t1", [10.0, 5.0, 0.0], 8.0), Target("p", np.array([-20.0, 0.0, 0.0]))],
                  case / "preop/targets")
    (case / "truth" / "targets").mkdir(parents=True)
    write_targets([sphere("t1", np.array([10.0, 5.0, 0.0]) + shift, 8.0),
                   Target("p", np.array([-20.0, 0.0, 0.0]) + shift)], case / "truth/targets")
    assert main(["--quiet", "register", str(case), "--edge", "15", "--k", "10", "--no-deform", "--json"]) in (0, None)
    capsys.readouterr()
    result = json.loads((case / "registration/result.json").read_text())
    rows = {r["name"]: r for r in result["targets"]}
    assert rows["t1"]["file"] == "targets/t1.ply"
    assert rows["t1"]["tre"]["truth"] == "truth/targets/"
    assert rows["t1"]["tre"]["rigid"]["centroid_mm"] < 1.0  # a pure shift is found by ICP
    np.testing.assert_allclose(rows["p"]["centre_registered_mm"], [-14.0, 0.0, 0.0], atol=1.0)
    moved = read_targets(case / "registration" / "targets")
    assert {t.name for t in moved} == {"t1", "p"}

import json

import numpy as np
import pytest
import trimesh

from navapp.errors import InputError
from navapp.simulation import effects as fx
from navapp.simulation.levels import data_level
from navapp.simulation.scene import load_scene, parse_scene, scene_dir, study_scenes
from navapp.simulation.simulate import simulate

SCENES = scene_dir()


def small_scene(**over):
    data = {"name": "t", "anatomy": {"phantom": 0},
            "deformation": {"release": "L", "mesh_edge_mm": 10.0, "truth_E_pa": 5000.0},
            "stylus": {"coverage": 0.2}, "ius": {"planes": 0}}
    for k, v in over.items():
        if isinstance(v, dict):
            data.setdefault(k, {}).update(v)
        else:
            data[k] = v
    return parse_scene(data)


def test_builtin_demo_scene_equals_the_shipped_file():
    import tomllib

    from navapp.simulation.scene import DEMO_SCENE

    assert tomllib.loads((SCENES / "demo.toml").read_text()) == DEMO_SCENE


def test_shipped_scenes_parse():
    names = sorted(p.stem for p in SCENES.glob("*.toml"))
    # demo, nine direct-gravity, nine transposed (lap) and 24 local-load (tool) scenes, and the
    # laparoscopic case with the laparoscope's depth points (scope0-L, in no study set)
    assert "demo" in names and "scope0-L" in names and len(names) == 1 + 9 + 9 + 24 + 1
    assert [len(study_scenes(s)) for s in ("direct", "lap", "tool")] == [9, 9, 24]
    for p in SCENES.glob("*.toml"):
        s = load_scene(p)
        assert s.planes == 16 and s.release in "LNR"


@pytest.mark.parametrize("data,key", [
    ({"colour": 1}, "colour"),
    ({"deformation": {"release": "X"}}, "deformation.release"),
    ({"deformation": {"large": "yes"}}, "deformation.large"),
    ({"ius": {"planes": 17}}, "ius.planes"),
    ({"stylus": {"coverage": 0}}, "stylus.coverage"),
    ({"stylus": {"density": 2}}, "stylus.density"),
    ({"effects": [{"kind": "blur"}]}, "effects[0].kind"),
    ({"effects": [{"kind": "dropout"}]}, "fraction"),
    ({"effects": [{"kind": "dropout", "fraction": 0.1, "seed": 3}]}, "effects[0].seed"),
])
def test_scene_errors_name_the_key(data, key):
    with pytest.raises(InputError) as err:
        parse_scene(data, "x.toml")
    assert key in str(err.value) and "\n" not in str(err.value)


def test_effects_each_do_what_they_say():
    rng = np.random.default_rng(0)
    led = fx.Ledger()
    p = np.zeros((20000, 3))
    assert np.isclose(fx.tracking_noise(p, rng, led, sd_mm=0.5).std(), 0.5, rtol=0.02)
    assert abs(len(fx.dropout(p, rng, led, fraction=0.3)) / len(p) - 0.7) < 0.02
    c, r = fx.contour_jitter(np.zeros(20000), np.zeros(20000), rng, led, sd_px=2.0)
    assert np.isclose(np.std(c), 2.0, rtol=0.03) and np.isclose(np.std(r), 2.0, rtol=0.03)
    T = np.eye(4)
    M = fx.calibration_error(T, rng, led, rotation_deg=3.0, translation_mm=1.5)
    assert np.isclose(np.degrees(np.arccos((np.trace(M[:3, :3]) - 1) / 2)), 3.0)
    assert np.isclose(np.linalg.norm(M[:3, 3]), 1.5)
    pts = np.array([[0.0, 0, 0], [0, 0, 10], [30, 0, 0]])
    moved = fx.probe_compression(pts, np.zeros(3), np.array([0.0, 0, 1]), led, depth_mm=4.0, radius_mm=10.0)
    d = np.linalg.norm(moved - pts, axis=1)
    assert np.isclose(d[0], 4.0) and d[1] < d[0] and d[2] < 0.01
    assert led.ran == ["tracking_noise", "dropout", "contour_jitter", "calibration_error", "probe_compression"]


@pytest.fixture(scope="module")
def plain_case(tmp_path_factory, cache_root):
    out = tmp_path_factory.mktemp("sim") / "plain"
    report = simulate(small_scene(), out, cache_root)
    return out, report


def test_undeclared_effects_never_run(plain_case):
    _, report = plain_case
    assert report["ran"] == ["linear_solve", "stylus"]  # no planes, no images, no noise, no Newton


def test_stylus_points_sit_on_the_deformed_surface(plain_case):
    out, report = plain_case
    liver = trimesh.load(out / "truth/liver.ply")
    pts = np.loadtxt(out / "intraop/anterior.csv", delimiter=",", skiprows=1)
    assert np.abs(trimesh.proximity.signed_distance(liver, pts)).max() < 1e-4  # float32 PLY
    assert 0.2 <= report["stylus"]["coverage_of_anterior"] < 0.3
    d = report["displacement_mm"]
    assert d["mean"] > 1.0 and d["max"] > d["mean"]


@pytest.fixture(scope="module")
def plane_case(tmp_path_factory, cache_root):
    out = tmp_path_factory.mktemp("sim") / "planes"
    scene = small_scene(ius={"planes": 4}, effects=[{"kind": "tracking_noise", "sd_mm": 0.2}])
    return out, simulate(scene, out, cache_root)


def test_planes_give_contours_on_the_deformed_vessels(plane_case):
    out, report = plane_case
    assert {"ius_section", "bmode_image", "tracking_noise", "linear_solve"} <= set(report["ran"])
    assert "nonlinear_solve" not in report["ran"]
    meta = json.loads((out / "intraop/us/planes.json").read_text())
    assert len(meta["planes"]) == 4 and [p["orientation"] for p in meta["planes"]] == ["vertical"] * 2 + ["lateral"] * 2
    portal = trimesh.load(out / "truth/portal.ply")
    found = 0
    for p in meta["planes"]:
        f = out / "intraop/us" / f"plane_{p['index']:02d}" / "portal_contour.csv"
        if f.exists():
            pts = np.loadtxt(f, delimiter=",", skiprows=1)
            # pixel rounding (0.25 mm pixels) plus 0.2 mm tracking noise
            assert np.median(np.abs(trimesh.proximity.signed_distance(portal, pts))) < 0.5
            found += 1
    assert found >= 1
    img = (out / "intraop/us/plane_00.png")
    assert img.exists()


def test_data_levels(plane_case):
    out, _ = plane_case
    s = data_level(out, "S")
    assert set(s) <= {"anterior", "falciform", "ridge_left", "ridge_right"} and "anterior" in s
    sp = data_level(out, "S+planes", planes=[0, 1, 2, 3])
    assert sum(map(len, sp.values())) > sum(map(len, s.values()))
    ct = data_level(out, "iCT")
    assert {"anterior", "posterior", "portal_contour", "hepatic_centerline"} <= set(ct)
    with pytest.raises(InputError):
        data_level(out, "S+planes", planes=[9])


def test_every_declared_effect_runs(tmp_path, cache_root):
    effects = [{"kind": "tracking_noise", "sd_mm": 0.2},
               {"kind": "calibration_error", "rotation_deg": 1.0, "translation_mm": 0.5},
               {"kind": "probe_compression", "depth_mm": 3.0, "radius_mm": 15.0},
               {"kind": "contour_jitter", "sd_px": 1.0},
               {"kind": "dropout", "fraction": 0.1}]
    report = simulate(small_scene(ius={"planes": 2}, effects=effects), tmp_path / "fx", cache_root)
    assert {e["kind"] for e in effects} <= set(report["ran"])
    # and a scene with the same planes but no effects runs none of them
    plain = simulate(small_scene(ius={"planes": 2}), tmp_path / "nofx", cache_root)
    assert not ({e["kind"] for e in effects} & set(plain["ran"]))


@pytest.fixture(scope="module")
def offset_case(tmp_path_factory, cache_root):
    out = tmp_path_factory.mktemp("sim") / "offset"
    scene = small_scene(effects=[{"kind": "tracker_offset", "rotation_deg": 20.0, "translation_mm": 40.0}])
    return out, simulate(scene, out, cache_root)


def test_the_truth_is_a_field_apart_from_any_registration_mesh(offset_case, cache_root):
    """The simulator writes its truth as a field on its own mesh (10 mm here), builds no
    registration mesh, and the field answers at any preoperative point: linear in each
    truth tet, then the tracker offset."""
    from navapp.anatomy.caseio import read_case
    from navapp.anatomy.meshing import cached_tetmesh
    from navapp.anatomy.truth import TruthField

    out, report = offset_case
    assert not (out / "truth" / "targets.csv").exists()
    case = read_case(out)
    truth = case.need_truth()
    assert isinstance(truth, TruthField)
    mesh, _ = cached_tetmesh(case.preop.liver, 10.0, cache_root)
    assert np.array_equal(truth.nodes, mesh.nodes) and np.array_equal(truth.tets, mesh.tets)
    T = np.array(report["tracker_offset"])
    assert not np.allclose(T, np.eye(4)) and np.allclose(truth.offset, T, atol=1e-6)

    def offset(p):
        return p @ truth.offset[:3, :3].T + truth.offset[:3, 3]

    # inside a tet, at arbitrary barycentric weights: the same weights of the nodes' truth
    rng = np.random.default_rng(1)
    tets = rng.choice(len(truth.tets), 50, replace=False)
    w = rng.dirichlet(np.ones(4), 50)
    corners = truth.nodes[truth.tets[tets]]  # (50, 4, 3)
    p = np.einsum("pk,pkj->pj", w, corners)
    want = offset(p + np.einsum("pk,pkj->pj", w, truth.u[truth.tets[tets]]))
    np.testing.assert_allclose(truth.at(p), want, atol=1e-9)
    # the true deformed liver the simulator wrote is the field at the preoperative surface
    liver = trimesh.load(out / "truth/liver.ply", process=False)
    np.testing.assert_allclose(truth.at(case.preop.liver.vertices), liver.vertices, atol=1e-3)  # float32 PLY
    # a registration mesh of another size is asked, not matched: its nodes' truth is the field's
    reg_mesh, _ = cached_tetmesh(case.preop.liver, 12.0, cache_root)
    x0, x1 = truth.tre_points(reg_mesh.nodes)
    assert x0 is not None and len(x0) == len(reg_mesh.nodes) != len(truth.nodes)
    np.testing.assert_array_equal(x1, truth.at(reg_mesh.nodes))
    # the report's displacement is the field's, at its own nodes
    assert report["displacement_mm"]["max"] == round(float(np.linalg.norm(truth.u, axis=1).max()), 2)


def test_a_truth_field_file_reads_back_bit_for_bit_and_refuses_damage(offset_case, tmp_path):
    from navapp.anatomy.caseio import read_truth
    from navapp.anatomy.truth import read_field

    out, _ = offset_case
    truth = read_truth(out)
    truth.write(tmp_path)
    again = read_truth(tmp_path)
    for k in ("nodes", "tets", "u", "offset"):
        assert np.array_equal(getattr(again, k), getattr(truth, k)), k
    # the same field gives the same bytes (a viewer session compares them)
    assert (tmp_path / "truth/field.npz").read_bytes() == (out / "truth/field.npz").read_bytes()
    bad = tmp_path / "truth/field.npz"
    np.savez(bad, nodes=truth.nodes, tets=truth.tets + len(truth.nodes), u=truth.u, offset=truth.offset)
    with pytest.raises(InputError, match="tets index"):
        read_field(bad)
    bad.write_text("not a zip")
    with pytest.raises(InputError, match="not a truth field"):
        read_field(bad)


def test_measured_truth_answers_only_at_its_own_points(tmp_path):
    from navapp.anatomy.caseio import read_truth
    from navapp.anatomy.truth import TruthPoints

    (tmp_path / "truth").mkdir()
    (tmp_path / "truth/targets.csv").write_text("x0,y0,z0,x1,y1,z1\n1,2,3,4,5,6\n7,8,9,10,11,12\n")
    truth = read_truth(tmp_path)
    assert isinstance(truth, TruthPoints)
    x0, x1 = truth.tre_points(np.zeros((5, 3)))  # whatever the registration mesh: its own points
    np.testing.assert_array_equal(x0, [[1, 2, 3], [7, 8, 9]])
    np.testing.assert_array_equal(x1, [[4, 5, 6], [10, 11, 12]])
    with pytest.raises(InputError, match="regenerate the case"):
        truth.at(x0)

"""The tracked laparoscope's sparse depth points (``simulation/sources/laparoscope.py``),
a data source on the source protocol (``simulation/sources``)."""

import json
import shutil
import tomllib

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from navapp.anatomy.caseio import read_case
from navapp.cli import main
from navapp.errors import InputError
from navapp.evaluation.table2 import read_results
from navapp.features import STYLUS
from navapp.geometry.transforms import apply, inverse, kabsch
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import case_source_levels, data_level, study_data
from navapp.simulation.scene import SCENE_SETS, load_scene, parse_scene, scene_dir, study_scenes
from navapp.simulation.simulate import simulate
from navapp.simulation.sources import features_of, registered
from navapp.simulation.sources.laparoscope import (
    MARKERS,
    LaparoscopeSpec,
    cylinder_entry,
    depth_sd,
    first_hits,
    look_at,
    sense,
    tracked,
)


def trimesh_first_hits(mesh, origin, d):
    """trimesh's own (pure numpy) ray caster's first hit per ray: distance, inf for none."""
    loc, ray, _ = trimesh.ray.ray_triangle.RayMeshIntersector(mesh).intersects_location(
        np.repeat(np.asarray(origin, float)[None], len(d), 0), d, multiple_hits=False)
    t = np.full(len(d), np.inf)
    t[ray] = np.linalg.norm(loc - origin, axis=1)
    return t


def two_spheres():
    """A small sphere in front of a large one, seen from the origin along +y: the small one
    hides part of the large one."""
    front = trimesh.creation.icosphere(subdivisions=3, radius=15.0)
    front.apply_translation([5.0, 80.0, 0.0])
    back = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    back.apply_translation([0.0, 160.0, 0.0])
    return front, back, trimesh.util.concatenate([front, back])


def test_first_hits_agree_with_trimesh_on_the_liver_phantom(phantoms):
    liver = trimesh.Trimesh(phantoms[0].liver.vertices, phantoms[0].liver.faces, process=False)
    target = liver.vertices.mean(0)
    cam = look_at(target + [20.0, 140.0, -50.0], target, fov_deg=80.0)
    t, tri = first_hits(cam, 12, liver.vertices, liver.faces)
    _, d = cam.grid(12)
    ref = trimesh_first_hits(liver, cam.centre, d)
    assert 20 < np.isfinite(ref).sum() < len(d)  # some rays miss the liver, many hit it
    np.testing.assert_array_equal(np.isfinite(t), np.isfinite(ref))
    hit = np.isfinite(t)
    np.testing.assert_allclose(t[hit], ref[hit], atol=1e-6)
    assert (tri[hit] >= 0).all() and (tri[~hit] == -1).all()


def test_first_hits_agree_with_trimesh_where_one_surface_hides_another():
    front, back, both = two_spheres()
    cam = look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], fov_deg=40.0)
    t, _ = first_hits(cam, 24, both.vertices, both.faces)
    _, d = cam.grid(24)
    ref = trimesh_first_hits(both, cam.centre, d)
    np.testing.assert_array_equal(np.isfinite(t), np.isfinite(ref))
    hit = np.isfinite(t)
    np.testing.assert_allclose(t[hit], ref[hit], atol=1e-6)


def _segment_distance(a, b, p):
    """Distance of point ``p`` (3,) from the segments a → b (P, 3) each, by projection."""
    ab = b - a
    s = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    return np.linalg.norm(a + s[:, None] * ab - p, axis=1)


def test_a_hidden_surface_gives_no_points():
    front, back, both = two_spheres()
    cam = look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], fov_deg=40.0)
    spec = LaparoscopeSpec(rays=48, keep=1.0, sd_mm=0.0, sd_growth_mm=0.0, max_incidence_deg=90.0)
    pts = sense(cam, spec, both, np.random.default_rng(0)).points["laparoscope"]
    on_back = np.abs(np.linalg.norm(pts - [0.0, 160.0, 0.0], axis=1) - 40.0) < 0.5
    assert on_back.sum() > 100 and (~on_back).sum() > 20
    # the line of sight to every point on the large sphere misses the small one (whose
    # triangles lie within its radius, outside 0.98 of it)
    sight = _segment_distance(np.repeat(cam.centre[None], on_back.sum(), 0), pts[on_back], np.array([5.0, 80.0, 0.0]))
    assert sight.min() > 15.0 * 0.98
    # and the large sphere's far side is never seen
    assert (pts[on_back, 1] < 160.0 + 1e-6).all()


def test_the_instrument_hides_what_is_behind_it(phantoms):
    liver = trimesh.Trimesh(phantoms[0].liver.vertices, phantoms[0].liver.faces, process=False)
    target = liver.vertices.mean(0)
    cam = look_at(target + [0.0, 150.0, -40.0], target, fov_deg=70.0)
    base = LaparoscopeSpec(rays=40, keep=1.0, sd_mm=0.0, sd_growth_mm=0.0, max_incidence_deg=90.0)
    spec = LaparoscopeSpec(rays=40, keep=1.0, sd_mm=0.0, sd_growth_mm=0.0, max_incidence_deg=90.0,
                           instrument_radius_mm=8.0, instrument_at=(0.1, 0.05))
    free = sense(cam, base, liver, np.random.default_rng(0))
    got = sense(cam, spec, liver, np.random.default_rng(0))
    tip, port = (np.array(got.report["instrument"][k]) for k in ("tip_mm", "port_mm"))
    pts, all_pts = got.points["laparoscope"], free.points["laparoscope"]
    assert got.report["instrument"]["hidden_rays"] > 10
    assert len(all_pts) - len(pts) == got.report["instrument"]["hidden_rays"]
    # no kept point's line of sight passes through the instrument: sampled along each line,
    # a sample between its two ends stays farther from its axis than its radius (the
    # report's tip and port are rounded to 0.01 mm)
    s = np.linspace(0.0, 1.0, 400)[:, None, None]
    along = (cam.centre + s * (pts - cam.centre)).reshape(-1, 3)
    axis = port - tip
    w = (along - tip) @ axis / (axis @ axis)
    between = (w > 0) & (w < 1)
    dist = np.linalg.norm(along[between] - (tip + w[between, None] * axis), axis=1)
    assert between.sum() > 1000 and dist.min() > 8.0 - 0.05
    # the analytic entry agrees with sampling on the rays it hides
    d = (all_pts - cam.centre) / np.linalg.norm(all_pts - cam.centre, axis=1, keepdims=True)
    entry = cylinder_entry(cam.centre, d, tip, port, 8.0)
    hidden = np.isfinite(entry)
    assert hidden.sum() >= got.report["instrument"]["hidden_rays"]
    p = cam.centre + entry[hidden, None] * d[hidden]
    w = np.clip((p - tip) @ axis / (axis @ axis), 0.0, 1.0)
    np.testing.assert_allclose(np.linalg.norm(p - (tip + w[:, None] * axis), axis=1), 8.0, atol=1e-6)


def test_depth_noise_grows_with_depth_as_stated():
    # a floor seen obliquely: depths from about 60 to 260 mm
    floor = trimesh.creation.box(extents=[800.0, 800.0, 2.0])
    cam = look_at([0.0, 0.0, 60.0], [0.0, 200.0, 1.0], fov_deg=90.0)
    spec = LaparoscopeSpec(rays=200, keep=1.0, sd_mm=0.2, sd_growth_mm=0.8, far_mm=2000.0, max_incidence_deg=90.0)
    pts = sense(cam, spec, floor, np.random.default_rng(3)).points["laparoscope"]
    # the true depth of each noisy point: its ray meets the floor's top (z = 1)
    d = pts - cam.centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    true_pts = cam.centre + d * ((1.0 - cam.centre[2]) / d[:, 2])[:, None]
    z_true = (true_pts - cam.centre) @ cam.forward
    err = (pts - cam.centre) @ cam.forward - z_true
    near, far = (z_true > 60) & (z_true < 90), (z_true > 180) & (z_true < 260)
    assert near.sum() > 500 and far.sum() > 500
    for band in (near, far):
        # the sample sd of the errors, normalised by the model's sd at each point: 1 ± 8 %
        assert abs(np.std(err[band] / depth_sd(z_true[band], spec)) - 1.0) < 0.08
        assert abs(np.mean(err[band] / depth_sd(z_true[band], spec))) < 0.1
    assert np.std(err[far]) > 3 * np.std(err[near])  # the growth is seen, not only modelled


SCENE = {"name": "lap", "seed": 0, "anatomy": {"phantom": 0},
         "deformation": {"release": "L", "mesh_edge_mm": 10.0, "truth_E_pa": 5000.0},
         "stylus": {"coverage": 0.05}, "ius": {"planes": 0},
         "laparoscope": {"instrument_radius_mm": 6.0}}


@pytest.mark.parametrize("table, words", [
    ({"rays": 0}, "laparoscope.rays = 0 is out of range"),
    ({"rays": 8.5}, "laparoscope.rays must be an int"),
    ({"fov_deg": "wide"}, "laparoscope.fov_deg must be a float"),
    ({"sd_growth_mm": -1.0}, "laparoscope.sd_growth_mm = -1.0 is out of range"),
    ({"keep": 0.0}, "laparoscope.keep = 0.0 is out of range"),
    ({"distance_mm": float("nan")}, "laparoscope.distance_mm = nan is out of range"),
    ({"zoom": 2}, "unknown key laparoscope.zoom"),
    ({"instrument_at": [2.0, 0.0]}, "laparoscope.instrument_at must be two image coordinates"),
    ({"instrument_at": "left"}, "laparoscope.instrument_at must be two image coordinates"),
    (3, "[laparoscope] must be a table"),
])
def test_a_bad_laparoscope_table_is_one_line(table, words):
    with pytest.raises(InputError, match=None) as e:
        parse_scene({**SCENE, "laparoscope": table})
    assert words in str(e.value) and "\n" not in str(e.value)


def test_a_bad_laparoscope_table_on_the_command_line_is_one_line(tmp_path, capsys):
    scene = tmp_path / "bad.toml"
    scene.write_text('name = "bad"\n[anatomy]\nphantom = 0\n[laparoscope]\nfov_deg = 500.0\n')
    assert main(["simulate", str(scene), "--out", str(tmp_path / "out")]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "laparoscope.fov_deg = 500.0 is out of range" in err
    assert "Traceback" not in err and "bad.toml" in err


def test_the_laparoscope_is_a_registered_source_of_one_feature():
    assert "laparoscope" in registered() and features_of("laparoscope") == ("laparoscope",)


@pytest.fixture(scope="module")
def lap_case(tmp_path_factory, cache_root):
    out = tmp_path_factory.mktemp("lap") / "case"
    return out, simulate(parse_scene(SCENE), out, cache_root)


def test_only_a_scene_with_a_laparoscope_simulates_one(lap_case, cache_root, tmp_path):
    out, report = lap_case
    assert "laparoscope" in report["ran"] and "laparoscope_instrument" in report["ran"]
    plain = simulate(parse_scene({k: v for k, v in SCENE.items() if k != "laparoscope"}), tmp_path / "p", cache_root)
    assert "laparoscope" not in plain["ran"] and "laparoscope" not in plain
    assert not (tmp_path / "p" / "intraop" / "laparoscope.csv").exists()
    # its own random stream: the stylus data are drawn as without it (to rounding: the two
    # truths' solves may sum in another order; another draw would move them millimetres)
    a, b = read_case(out).intraop, read_case(tmp_path / "p").intraop
    np.testing.assert_allclose(a["anterior"], b["anterior"], rtol=0, atol=1e-9)


def test_laparoscope_points_lie_on_the_deformed_surface_within_their_noise(lap_case):
    out, report = lap_case
    pts = read_case(out).intraop["laparoscope"]
    assert len(pts) == report["laparoscope"]["points"] > 50
    liver = trimesh.load(out / "truth" / "liver.ply", process=False)
    off = np.abs(trimesh.proximity.signed_distance(liver, pts))
    spec = LaparoscopeSpec(instrument_radius_mm=6.0)
    assert off.max() < 5 * depth_sd(report["laparoscope"]["depth_mm"]["max"], spec)
    assert np.median(off) > 0.01  # noisy, not on the surface exactly


def test_a_views_points_share_one_rigid_tracking_error(cache_root, tmp_path):
    """The tracker reports the camera's pose once per view: its error is one rigid motion of
    all the view's points, not a separate error on each (as on the stylus's tip). With the
    depth noise off, the view with tracking noise is the view without it moved rigidly: a
    Kabsch fit leaves nothing (a separate error per point would leave ~sd)."""
    quiet = {**SCENE, "laparoscope": {**SCENE["laparoscope"], "sd_mm": 0.0, "sd_growth_mm": 0.0}}
    noisy = {**quiet, "effects": [{"kind": "tracking_noise", "sd_mm": 0.5}]}
    exact = simulate(parse_scene(quiet), tmp_path / "exact", cache_root)
    report = simulate(parse_scene(noisy), tmp_path / "noisy", cache_root)
    p = read_case(tmp_path / "exact").intraop["laparoscope"]
    q = read_case(tmp_path / "noisy").intraop["laparoscope"]
    assert len(p) == len(q) == report["laparoscope"]["kept"]["laparoscope"] > 50  # the same rays kept
    R, t = kabsch(p, q)
    assert np.abs(p @ R.T + t - q).max() < 1e-6  # one rigid error (the truths agree to rounding)
    moved = np.linalg.norm(q - p, axis=1)
    assert moved.mean() > 0.3  # and an error there is
    # the report states the view's error: its rotation, and the camera centre's shift
    centre = np.array(exact["laparoscope"]["camera_mm"])
    tracking = report["laparoscope"]["tracking"]
    assert tracking["rotation_deg"] == pytest.approx(np.degrees(Rotation.from_matrix(R).magnitude()), abs=2e-3)
    np.testing.assert_allclose(tracking["camera_shift_mm"], R @ centre + t - centre, atol=0.02)
    assert "tracking" not in exact["laparoscope"]
    # what the camera measured is the same in both: the points in its own frame; the tracker's
    # reported pose (``tool_to_tracker``) is what differs, and it places them where they are
    seen = [apply(inverse(np.array(r["laparoscope"]["tool_to_tracker"])), x) for r, x in ((exact, p), (report, q))]
    np.testing.assert_allclose(seen[0], seen[1], atol=1e-6)
    assert np.all(seen[0][:, 2] > 50.0)  # in front of the camera, along its z


def test_the_cameras_pose_error_has_the_size_its_markers_give():
    """The pose error of a ring of n markers of radius r, each measured with sd σ, fitted by
    Kabsch: to first order rotations of sd σ/(r√(n/2)) across the shaft and σ/(r√n) about
    it, a shift of σ/√n per axis at the ring's centre, carried to the camera centre by the
    lever arm L across the shaft."""
    cam = look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    spec = LaparoscopeSpec(marker_offset_mm=300.0, marker_radius_mm=40.0)
    sd, n, r, L = 0.3, MARKERS, 40.0, 300.0
    rng = np.random.default_rng(5)
    errors = [tracked(cam, spec, sd, rng) for _ in range(4000)]
    w = np.array([Rotation.from_matrix(e[:3, :3]).as_rotvec() for e in errors])
    shift = np.array([e[:3, :3] @ cam.centre + e[:3, 3] - cam.centre for e in errors])
    across, about = sd / (r * np.sqrt(n / 2)), sd / (r * np.sqrt(n))
    for axis, want in ((cam.right, across), (cam.up, across), (cam.forward, about)):
        assert np.std(w @ axis) == pytest.approx(want, rel=0.06)
    lever = np.sqrt(sd ** 2 / n + (L * across) ** 2)
    for axis, want in ((cam.right, lever), (cam.up, lever), (cam.forward, sd / np.sqrt(n))):
        assert np.std(shift @ axis) == pytest.approx(want, rel=0.06)
    assert 1.5 < lever < 1.7  # 1.6 mm at the camera centre from 0.3 mm markers (the module's text)


def _register(case, capsys) -> dict:
    assert main(["--quiet", "register", str(case), "--edge", "12", "--k", "12", "--json"]) == 0
    capsys.readouterr()
    return json.loads((case / "registration" / "result.json").read_text())


def test_a_scene_with_a_laparoscope_registers_and_corrects_the_deformation(lap_case, capsys, tmp_path):
    out, report = lap_case
    result = _register(out, capsys)
    assert "laparoscope" in result["features"] and result["answer"] == "deformable"
    uncorrected = report["displacement_mm"]["mean"]  # the preoperative model left where it was
    tre = result["tre_deformable"]["mean_mm"]
    assert tre < 0.6 * uncorrected and tre < result["tre_rigid"]["mean_mm"]
    # the same case without the camera's points: the few stylus points alone do not correct it
    shutil.copytree(out, tmp_path / "stylus", ignore=shutil.ignore_patterns("registration"))
    (tmp_path / "stylus" / "intraop" / "laparoscope.csv").unlink()
    alone = _register(tmp_path / "stylus", capsys)["tre_deformable"]["mean_mm"]
    assert tre < alone - 2.0


def test_live_laparoscope_points_arrive_as_a_point_message():
    import socket
    import time

    import pyigtl
    from conftest import wait_until

    from navapp.tracking.client import TrackingClient
    from navapp.tracking.config import TrackingConfig
    from navapp.tracking.events import Skipped, SourcePoints

    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(5.0)
    events: list = []
    client = TrackingClient(TrackingConfig(port=listener.getsockname()[1], reconnect_s=0.05),
                            on_event=events.append).start()
    sent = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.5], [-7.0, 8.0, 9.25]])
    try:
        conn, _ = listener.accept()
        stamp = time.time()
        conn.sendall(pyigtl.PointMessage(positions=sent, device_name="laparoscope", timestamp=stamp).pack()
                     # another device's points (a fiducial list from Slicer) are not a source's
                     + pyigtl.PointMessage(positions=sent, device_name="F", timestamp=stamp).pack()
                     + pyigtl.PointMessage(positions=[[np.nan, 0.0, 0.0]], device_name="laparoscope",
                                           timestamp=stamp + 1).pack()
                     + pyigtl.PointMessage(positions=sent[:1] + 1, device_name="laparoscope",
                                           timestamp=stamp + 2).pack())
        wait_until(lambda: sum(isinstance(e, SourcePoints) for e in events) >= 2)
    finally:
        client.stop()
        listener.close()
    got = [e for e in events if isinstance(e, SourcePoints)]
    assert [e.feature for e in got] == ["laparoscope", "laparoscope"]
    np.testing.assert_array_equal(got[0].points, sent)
    np.testing.assert_array_equal(got[1].points, sent[:1] + 1)
    assert [e.kind for e in events if isinstance(e, Skipped)] == ["malformed"]
    assert client.counts["ignored:POINT"] == 1
    conn.close()


def test_the_session_keeps_and_draws_the_laparoscope_points(cache_root, tmp_path):
    from navapp.app.palette import FEATURE_COLOURS
    from navapp.app.session import Session, open_session
    from navapp.simulation.scenedata import load_scene_data, scene_key

    sd = load_scene_data(parse_scene(SCENE), cache_root, edge=14.0)
    pts = sd.case.intraop["laparoscope"]
    np.testing.assert_array_equal(sd.sourced["laparoscope"], pts)
    s = Session(tmp_path / "s", scene_key(sd.scene, 14.0))
    s.live_points.append([1.0, 2.0, 3.0, "laparoscope"])  # a live POINT message's point
    data = s.data(sd, {})
    assert set(data) == {"laparoscope"}  # no stylus sweep yet: the camera's points are there at once
    np.testing.assert_array_equal(data["laparoscope"], np.vstack([pts, [[1.0, 2.0, 3.0]]]))
    s.save(sd, {})
    again, _ = open_session(tmp_path / "s", sd)
    assert again.live_points == s.live_points
    assert FEATURE_COLOURS["laparoscope"] == (255, 120, 200)  # drawn in its own colour, as every feature


def test_the_viewer_takes_live_laparoscope_points_into_its_session(cache_root, tmp_path):
    """``navapp serve --igtl`` against a server that sends a POINT message named ``laparoscope``:
    the points join the session's data beside the simulated camera's."""
    import time

    import pyigtl
    from conftest import free_port, wait_until

    from navapp.app.server import App
    from navapp.tracking.config import TrackingConfig
    from navapp.tracking.replay import quiet_server

    server = quiet_server(0)
    server.start()
    app = App(parse_scene(SCENE), port=free_port(), session_dir=tmp_path / "s", edge=12.0, k=12,
              cache_root=cache_root, tracking=TrackingConfig(port=server.server_address[1]))
    sent = np.array([[10.0, 20.0, 30.0], [11.0, 21.0, 31.5]])
    try:
        assert app.start().wait(600) and app.core.failed is None, app.core.failed
        wait_until(server.is_connected)
        server.send_message(pyigtl.PointMessage(positions=sent, device_name="laparoscope", timestamp=time.time()),
                            wait=True)
        wait_until(lambda: len(app.core.session.live_points) >= 2)
        assert [p[3] for p in app.core.session.live_points] == ["laparoscope", "laparoscope"]
        data = app.core.data()["laparoscope"]
        simulated = app.core.sd.sourced["laparoscope"]
        np.testing.assert_array_equal(data, np.vstack([simulated, sent]))
    finally:
        app.live.stop()
        app.server.stop()
        app.view2d.stop()
        server.stop()


def test_a_replayed_laparoscope_reaches_the_viewers_session_and_its_registration(cache_root, tmp_path):
    """``navapp replay`` of a scene with a laparoscope plays its recorded depth points (a POINT
    message named by the feature, once to the client, as the stylus's tip plays); ``navapp
    serve --igtl`` on the same anatomy with no simulated camera takes them into its session
    (``Session.live_points``), and a registration runs on exactly them."""
    from conftest import free_port, run_to_end, wait_until

    from navapp.app.server import App
    from navapp.app.state import RunKind
    from navapp.tracking.config import TrackingConfig
    from navapp.tracking.replay import ReplayServer, script_from_scene

    script = script_from_scene(parse_scene(SCENE), cache_root=cache_root, edge=12.0)
    recorded = script.points["laparoscope"]
    assert set(script.points) == {"laparoscope"} and len(recorded) > 50 and not script.probe_stops
    viewer = parse_scene({k: v for k, v in SCENE.items() if k != "laparoscope"})
    replay = ReplayServer(script, port=0).start()
    app = App(viewer, port=free_port(), session_dir=tmp_path / "s", edge=12.0, k=12, cache_root=cache_root,
              tracking=TrackingConfig(port=replay.port))
    try:
        assert app.start().wait(600) and app.core.failed is None, app.core.failed
        assert app.core.sd.sourced == {}  # the viewer simulates no camera: every camera point is the replay's
        live_points = app.core.session.live_points
        wait_until(lambda: len(live_points) >= len(recorded))
        ticks = replay.ticks
        wait_until(lambda: replay.ticks >= ticks + 10)  # 0.4 s more of playing: no second copy
        assert len(live_points) == len(recorded) and replay.points_sent == 1
        assert {p[3] for p in live_points} == {"laparoscope"}
        np.testing.assert_allclose([p[:3] for p in live_points], recorded, atol=1e-4)  # float32 on the wire
        run_to_end(app, RunKind.ALL)
        reg = app.core.last_reg
        assert reg is not None and set(reg.data_model_frame) == {"laparoscope"}
        np.testing.assert_allclose(reg.rigid.apply(reg.data_model_frame["laparoscope"]), recorded, atol=1e-3)
        assert app.core.session.log[-1].points == len(recorded)
    finally:
        app.live.stop()
        app.server.stop()
        app.view2d.stop()
        replay.stop()


def test_a_tracked_laparoscope_is_replayed_in_its_camera_frame_with_its_pose(cache_root):
    """With ``[tools.laparoscope] pose`` in the tracking config, ``navapp replay`` sends the
    camera's pose as the tracker reported it and the points in the camera's frame: a client
    with the same config places them where they were recorded; one without it takes the
    camera-frame numbers as Reference (far off). Each client that connects gets them once."""
    from conftest import wait_until

    from navapp.tracking.client import TrackingClient
    from navapp.tracking.config import TrackingConfig
    from navapp.tracking.events import SourcePoints, TransformSample
    from navapp.tracking.receivers.points import PointsSettings
    from navapp.tracking.replay import ReplayServer, script_from_scene

    script = script_from_scene(parse_scene(SCENE), cache_root=cache_root, edge=12.0)
    recorded = script.points["laparoscope"]
    tracked = (PointsSettings("laparoscope", "CameraToReference"),)
    with ReplayServer(script, port=0, names=TrackingConfig(tools=tracked)) as replay:
        got = {}
        for name, config in (("plain", TrackingConfig(port=replay.port)),
                             ("tracked", TrackingConfig(port=replay.port, tools=tracked))):
            events: list = []
            client = TrackingClient(config, on_event=events.append).start()
            try:
                assert wait_until(lambda ev=events: any(isinstance(e, SourcePoints) for e in ev)), name
            finally:
                client.stop()
            assert wait_until(lambda: not replay.connected)
            got[name] = [e for e in events if isinstance(e, SourcePoints)]
            assert any(isinstance(e, TransformSample) and e.name == "CameraToReference" for e in events)
        assert replay.points_sent == 2  # once to each client
    assert [len(v) for v in got.values()] == [1, 1]
    np.testing.assert_allclose(got["tracked"][0].points, recorded, atol=1e-3)  # float32 on the wire
    assert np.linalg.norm(got["plain"][0].points - recorded, axis=1).min() > 50.0


def test_a_replay_refuses_a_tracked_source_whose_pose_the_scene_does_not_record():
    from navapp.tracking.config import TrackingConfig
    from navapp.tracking.receivers.points import PointsSettings
    from navapp.tracking.replay import ReplayScript, ReplayServer

    script = ReplayScript(np.zeros((2, 3)), [], [], 0.0, points={"laparoscope": np.ones((3, 3))})
    with pytest.raises(InputError, match="records no pose of the laparoscope"):
        ReplayServer(script, port=0, names=TrackingConfig(tools=(PointsSettings("laparoscope", "CamToReference"),)))


def test_replay_reads_its_tracking_file_and_refuses_a_bad_one_in_one_line(tmp_path, capsys):
    """``navapp replay --igtl-config FILE`` reads the viewer's tracking file (the names it sends
    under): a bad one is one line naming the file, before anything is simulated."""
    bad = tmp_path / "tracking.toml"
    bad.write_text('[tools.laparoscope]\npose = 3\n')
    assert main(["replay", "--igtl-config", str(bad), "--seconds", "1"]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "tracking.toml" in err and "tools.laparoscope.pose" in err, err


SCANNER = '''"""A throwaway point source: a structured-light scanner's points on the anterior liver."""

from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from ...features import STYLUS
from . import Acquired, SimulatedSource


@dataclass(frozen=True)
class ScannerSpec:
    fraction: float = 0.2


def parse(table, path):
    if not isinstance(table, dict) or set(table) - {"fraction"}:
        raise InputError("[scanner] takes fraction only", path)
    return ScannerSpec(**table)


def acquire(spec, sight, rng):
    sight.ledger.mark("scanner")
    face = np.any([sight.preop.region_mask(n) for n in STYLUS], axis=0)
    v = sight.liver.vertices[face]
    pts = v[rng.random(len(v)) < spec.fraction]
    return Acquired({"scanner": pts}, {"points": int(len(pts))})


SOURCE = SimulatedSource("scanner", always=False, parse=parse, acquire=acquire)
'''

SCANNER_CHECK = '''
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pyigtl

from navapp.app.session import Session
from navapp.app.sources import PointsShown, build as shown
from navapp.app.sources.base import Wiring
from navapp.features import RIGID, SEEN, SOURCED
from navapp.simulation.levels import case_source_levels, study_data
from navapp.simulation.scene import parse_scene
from navapp.simulation.scenedata import load_scene_data
from navapp.simulation.sources import registered
from navapp.tracking import receivers
from navapp.tracking.client import TrackingClient
from navapp.tracking.config import TrackingConfig
from navapp.tracking.events import SourcePoints
from navapp.tracking.receivers.base import Message, Shared
from navapp.tracking.digitiser import Digitiser
from navapp.tracking.replay import script_from_scene

cache, tmp = Path(sys.argv[1]), Path(sys.argv[2])
assert "scanner" in SOURCED and "scanner" in SEEN and "scanner" in RIGID and "scanner" in registered()
scene = parse_scene({"name": "scan", "seed": 0, "anatomy": {"phantom": 0},
                     "deformation": {"release": "L", "mesh_edge_mm": 10.0, "truth_E_pa": 5000.0},
                     "stylus": {"coverage": 0.05}, "ius": {"planes": 0}, "scanner": {"fraction": 0.3}})
sd = load_scene_data(scene, cache, edge=12.0)  # simulated: its own random stream, its own report entry
pts = sd.sourced["scanner"]
assert set(sd.sourced) == {"scanner"} and len(pts) > 50
report = __import__("json").loads((sd.case_dir / "truth" / "report.json").read_text())
assert report["scanner"]["kept"] == {"scanner": len(pts)} and "scanner" in report["ran"]
data = Session(tmp / "s", "key").data(sd, {})  # kept: session data at once
np.testing.assert_array_equal(data["scanner"], pts)
assert case_source_levels(sd.case_dir) == ("S+scanner",)  # in the studies: its level
assert set(study_data(sd.case_dir, "S+scanner")) == {"anterior", "falciform", "ridge_left", "ridge_right", "scanner"}
got = receivers.build([t for t in TrackingConfig().tools if t.source == "scanner"], Shared(Digitiser(), 1.0))
rx, = got  # received: POINT messages named by its feature
assert rx.takes("POINT", "scanner")
body = pyigtl.PointMessage(positions=pts[:3], device_name="scanner")
event = rx.receive(Message("POINT", "scanner", 0.0, 0.0, body))
assert isinstance(event, SourcePoints) and np.allclose(event.points, pts[:3], atol=1e-4)
wiring = Wiring(TrackingClient(TrackingConfig()), TrackingConfig(), SimpleNamespace(), lambda: None)
assert [s.source for s in shown(wiring) if isinstance(s, PointsShown)] == ["laparoscope", "scanner"]  # shown
assert set(script_from_scene(scene, cache_root=cache, edge=12.0).points) == {"scanner"}  # replayed
print("a new point source: all rooms")
'''


def test_a_second_point_source_is_one_module_and_one_row(cache_root, tmp_path):
    """A throwaway point source (a structured-light scanner): the package copied, its module
    added to ``simulation/sources`` and its row to ``features.TABLE`` — no other file — and it
    is simulated, kept in the session, given its study level, received, shown and replayed."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    import navapp

    tree = tmp_path / "tree"
    shutil.copytree(Path(navapp.__file__).parent, tree / "navapp", ignore=shutil.ignore_patterns("__pycache__"))
    (tree / "navapp" / "simulation" / "sources" / "scanner.py").write_text(SCANNER)
    features = tree / "navapp" / "features.py"
    row = '''            "the laparoscope's depth points"),\n'''
    text = features.read_text()
    assert text.count(row) == 1
    scanner = '''    Feature("scanner", "surface", "liver", 1.0, "scanner", (120, 200, 255), 1.0, "its points"),\n'''
    features.write_text(text.replace(row, row + scanner))
    out = subprocess.run([sys.executable, "-c", SCANNER_CHECK, str(cache_root), str(tmp_path)], cwd=tmp_path,
                         env={**os.environ, "PYTHONPATH": str(tree)}, capture_output=True, text=True,
                         timeout=900)
    assert out.returncode == 0 and "all rooms" in out.stdout, out.stdout + out.stderr


def test_a_laparoscope_point_far_off_is_named_by_its_source():
    from navapp.app.contours import Origin, OriginKind
    from navapp.app.runs import worst_points
    from navapp.registration.objective import Weights
    from navapp.registration.residuals import PointResidual

    data = {"laparoscope": np.zeros((2, 3)), "anterior": np.ones((1, 3))}
    origins = {"laparoscope": [Origin(OriginKind.SOURCE), Origin(OriginKind.LIVE)],
               "anterior": [Origin(OriginKind.LIVE)]}
    residuals = [PointResidual("laparoscope", 0, 30.0, True), PointResidual("laparoscope", 1, 20.0, True),
                 PointResidual("anterior", 0, 10.0, True)]
    worst = worst_points(None, data, origins, Weights(), n=3, residuals=residuals)  # type: ignore[arg-type]
    assert [w.where for w in worst] == ["the laparoscope's depth points, simulated laparoscope",
                                        "the laparoscope's depth points, live laparoscope",
                                        "the anterior surface, tracked stylus"]


def _shipped_scene_small():
    """The shipped laparoscopic case (``navapp/scenes/scope0-L.toml``) as shipped, but for
    its truth (gravity on phantom 0's own 10 mm mesh, linear, instead of the transposed
    neo-Hookean insufflation) and no iUS planes: its stylus, camera and effects are the file's."""
    table = tomllib.loads((scene_dir() / "scope0-L.toml").read_text())
    table["deformation"] = {"release": "L", "mesh_edge_mm": 10.0, "truth_E_pa": 5000.0}
    table["ius"] = {"planes": 0}
    return parse_scene(table, "scope0-L.toml")


def test_the_shipped_laparoscopic_case_uses_the_laparoscope_and_joins_no_study_set():
    path = scene_dir() / "scope0-L.toml"
    scene = load_scene(path)
    assert scene.sources["laparoscope"].instrument_radius_mm > 0 and scene.sources["stylus"].coverage <= 0.05
    assert scene.transpose_from is not None and scene.pressure_pa > 0  # insufflated, as the lap* cases
    # the default study sets (and so Table II's and the other studies' defaults) stay as they were
    assert all(path not in study_scenes(which) for which in SCENE_SETS)


@pytest.fixture(scope="module")
def scope_case(tmp_path_factory, cache_root):
    out = tmp_path_factory.mktemp("scope") / "scope0-L"
    simulate(_shipped_scene_small(), out, cache_root)
    return out


def test_table2_has_a_laparoscope_row_that_measures_what_it_adds(scope_case, tmp_path, capsys):
    csv, report = tmp_path / "t2.csv", tmp_path / "report"
    assert main(["--quiet", "study", "table2", "--cases", str(scope_case), "--quick", "--edge", "12", "--k", "12",
                 "--workers", "1", "--results", str(csv), "--report", str(report)]) == 0
    capsys.readouterr()
    rows = read_results(csv)
    tre = {r["level"]: float(r["tre_mean_mm"]) for r in rows}
    # no planes in this case: no plane level; its source's level beside S
    assert sorted(tre) == sorted(["rigid", "S", "S+laparoscope", "CBCT", "iCT"]) and len(rows) == 5
    assert tre["S+laparoscope"] < tre["S"] - 2.0  # the few stylus swaths alone do not correct it
    head = (report / "table2.md").read_text().splitlines()[2]
    assert "| S+laparoscope |" in head
    # the row is the registration of S and the camera's points, as `register` gives it alone
    case = read_case(scope_case)
    model, _ = prepare(case, 12.0, 12)
    data = study_data(scope_case, "S+laparoscope", case=case)
    assert set(data) == set(STYLUS) | {"laparoscope"}
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    alone = mean_tre(register(model, data).transform(x0), x1)
    assert alone == pytest.approx(tre["S+laparoscope"], abs=1e-4)


def test_a_case_without_the_camera_has_no_laparoscope_level(lap_case, tmp_path):
    out, _ = lap_case
    assert case_source_levels(out) == ("S+laparoscope",)
    plain = tmp_path / "plain"
    shutil.copytree(out, plain, ignore=shutil.ignore_patterns("registration"))
    (plain / "intraop" / "laparoscope.csv").unlink()
    assert case_source_levels(plain) == ()
    with pytest.raises(InputError, match="no laparoscope points in this case"):
        data_level(plain, "S+laparoscope")

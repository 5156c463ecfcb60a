"""The viewer's actions without a browser: the App driven through its methods on a small
scene (coarse mesh, k = 12), checking what reaches the session and the scene."""

import json
import time

import numpy as np
import pytest
from conftest import free_port

from navapp.simulation.scene import parse_scene

pytest.importorskip("viser")


@pytest.fixture(scope="module")
def app(cache_root, tmp_path_factory):
    from navapp.app.server import App

    scene = parse_scene({"name": "apptest", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
                         "stylus": {"coverage": 0.2}, "ius": {"planes": 2}})
    a = App(scene, port=free_port(), session_dir=tmp_path_factory.mktemp("sess"), edge=12.0, k=12, cache_root=cache_root)
    t0 = time.time()
    while a.worker is None and time.time() - t0 < 300:
        assert "Error" not in a.status.content, a.status.content
        time.sleep(0.2)
    assert a.worker is not None
    yield a
    a.server.stop()


def wait_idle(app):
    app.worker.join(120)
    assert not app.worker.busy


def test_register_refuses_without_data_then_runs(app):
    assert app.register("all") is False  # nothing collected yet: refused with a notification
    app.collect_stylus_now()
    assert app.session.stylus_count == len(app.sd.stylus_path)
    assert app.register("rigid")
    wait_idle(app)
    assert app.register("surface")
    assert app.register("all") is False  # one run at a time
    wait_idle(app)
    log = app.session.log
    assert [e["run"] for e in log[-2:]] == ["rigid", "deformable, surface"]
    assert log[-1]["error_mean_mm"] < log[-2]["error_mean_mm"]
    assert log[-1]["updates_streamed"] >= 1
    saved = json.loads((app.session.folder / "session.json").read_text())
    assert saved["log"] == log


def test_plane_contour_and_free_probe_reach_the_data(app):
    app.show_plane(0)
    app.auto_segment()
    assert 0 in app.session.planes_added
    T = app.planes[1].probe_to_tracker.copy()
    T[:3, 3] += T[:3, 0] * 5.0  # slide the probe 5 mm sideways
    app.place_probe(T)
    free = max(app.planes)
    assert free >= 100 and app.current_plane == free
    assert np.allclose(app.session.free_planes[-1]["pose"], T)
    app.cb_draw.value = True
    app.draw_feature.value = "HV contour"

    class Click:  # a click ray straight onto pixels of the free plane
        def __init__(self, c, r):
            from navapp.simulation.probe import pixels_to_tracker

            p = pixels_to_tracker(app.sd.probe, T, [c], [r])[0]
            self.ray_origin, self.ray_direction = p + 50 * T[:3, 1], -T[:3, 1]

    for c, r in ((100, 100), (140, 100), (140, 150)):
        app._image_clicked(Click(c, r))
    app._contour_command("Close")
    c = app.session.contours[-1]
    assert c.closed and c.plane == free and c.vertices == [(100, 100), (140, 100), (140, 150)]
    data = app._data("all")
    assert "hepatic_contour" in data and "hepatic_centerline" in data
    app._contour_command("Undo")  # reopens the last contour and removes its last vertex
    assert app.session.contours[-1].vertices == [(100, 100), (140, 100)] and not app.session.contours[-1].closed
    app._contour_command("Clear plane")
    assert all(x.plane != free for x in app.session.contours)


def test_warm_rerun_sweep_and_export(app):
    assert app.register("warm")
    wait_idle(app)
    assert app.session.log[-1]["run"].endswith("(warm)")
    app.sweep()
    wait_idle(app)
    assert "★" in app.cost_md.content and "rigid" in app.cost_md.content
    app.export()
    out = app.session.folder / "export"
    assert (out / "registered_liver.vtk").exists() and (out / "registered_portal.ply").exists()
    assert (out / "data_anterior.csv").exists()


def test_a_restarted_server_restores_the_session(app, cache_root):
    from navapp.app.server import App

    app.worker.join(60)
    again = App(app.scene, port=free_port(), session_dir=app.session.folder, edge=12.0, k=12, cache_root=cache_root)
    try:
        t0 = time.time()
        while again.worker is None or "contours drawn" not in again.plane_md.content:  # start-up finished
            assert time.time() - t0 < 120 and "Error" not in again.status.content, again.status.content
            time.sleep(0.2)
        assert again.session.to_json() == app.session.to_json()
        assert "mean error" in again.log_md.content
        assert set(again.planes) == set(app.planes)  # free planes re-simulated from their poses
    finally:
        again.server.stop()

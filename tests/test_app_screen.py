"""What the surgeon sees on the screen, headless: the guide moves on from 'Register with
ultrasound' when the earlier steps were skipped, and a reloaded or new tab does not restart it
at step 1; every run's tumour errors are kept for the run table; a Rigid press does not lose a
good deformable result (any finished run can be put back on show)."""

import numpy as np
import pytest
from conftest import BUSY_WAIT_S, run_to_end, start_app, stop_app

from navapp.app.guide import STEPS, first_open_step
from navapp.app.state import RunKind

SCENE = {"name": "screen", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.2}, "ius": {"planes": 2}}
REGISTER_ALL = next(i for i, s in enumerate(STEPS) if s.title == "Register with ultrasound")


@pytest.fixture(scope="module")
def app(cache_root, tmp_path_factory):
    a = start_app(SCENE, cache_root, tmp_path_factory.mktemp("sess"))
    yield a
    stop_app(a)


def test_the_guide_goes_on_after_skipped_steps_and_survives_a_reload(app):
    cs = app.core.new_client_state()
    assert first_open_step(app, cs) == 0  # nothing done yet: the first step
    app.stylus.collect_now()
    cs.guide_step = REGISTER_ALL  # every step before skipped: no result to warm-start from
    step = STEPS[REGISTER_ALL]
    assert step.blocked(app, cs) is None
    assert step.action(app, cs) is None  # a fresh fit on all data
    app.core.worker.join(BUSY_WAIT_S)
    app.core.settle()
    assert app.core.session.log[-1].kind is RunKind.ALL
    assert step.done(app, cs)  # the guide moves on (it waited for a warm run before)

    # a reload is the same tab: its guide step comes with it
    app.core.park(cs.token)
    again = app.core.new_client_state()
    assert app.core.resume(again, cs.token) is None
    assert again.guide_step == REGISTER_ALL
    # a new tab on a session with a sweep and a fit starts past them
    assert first_open_step(app, app.core.new_client_state()) >= REGISTER_ALL


def test_rigid_keeps_the_deformable_result_within_reach_and_tumour_errors_are_logged(app):
    app.stylus.collect_now()
    deformable = run_to_end(app, RunKind.ALL)
    good, good_reg = app.core.result, app.core.last_reg
    names = {t.name for t in app.core.preop.targets}
    assert deformable.targets_mm is not None and set(deformable.targets_mm) == names
    assert all(v >= 0 for v in deformable.targets_mm.values())
    row = len(app.core.session.log) - 1
    rigid = run_to_end(app, RunKind.RIGID)
    assert rigid.targets_mm is not None and app.core.result is not good  # the rigid pose is on show
    assert app.runs.show(row) is None  # and the deformable result can be put back
    assert app.core.result is good and app.core.last_reg is good_reg and app.core.worker.last is good_reg
    assert app.core.session.result["run"] == good.run and app.core.session.result["beta"] is not None
    assert run_to_end(app, RunKind.WARM).run == RunKind.WARM.label  # a warm start continues from it
    assert "not kept" in app.runs.show(10_000)
    saved = app.core.session.log[row].to_json()
    assert saved["targets_mm"] == deformable.targets_mm  # the column survives a restart


def _rgb(c) -> np.ndarray:
    if isinstance(c, str):
        return np.array([int(c[i:i + 2], 16) for i in (1, 3, 5)], float)
    return np.array(c, float)


def test_drawn_contours_are_not_the_registered_livers_yellow():

    import colorsys

    from navapp.app.palette import DRAWN_COLOURS, FEATURE_COLOURS, IN_PROGRESS, OVERLAY_STYLE, REGISTERED

    def hs(c):
        h, _, s = colorsys.rgb_to_hls(*(_rgb(c) / 255))
        return 360 * h, s

    registered = [hs(REGISTERED), hs(OVERLAY_STYLE["liver"][1])]  # 3D and 2D
    for c in [*DRAWN_COLOURS.values(), IN_PROGRESS, FEATURE_COLOURS["posterior"]]:
        h, s = hs(c)
        for rh, rs in registered:  # another hue, or no hue (white) beside a saturated yellow
            assert abs(h - rh) >= 10 or abs(s - rs) > 0.5, (c, h, rh)


@pytest.mark.parametrize("size", [(1366, 768), (1600, 1000)])
def test_the_home_view_shows_the_whole_liver_between_the_panels(size, phantoms):
    from navapp.app.framing import Screen, dock_width, frame, project
    from navapp.app.panels.layers import HOME_VIEW_MM

    w, h = size
    screen = Screen(w - dock_width(w), h)  # the canvas: the window less the docked 2D view
    liver = phantoms[0].liver.vertices
    fov = np.deg2rad(75.0)  # viser's default camera
    position, target = frame(liver[::5], HOME_VIEW_MM, (0.0, 0.0, 1.0), fov, screen)
    x, y = project(liver, position, target, np.array([0.0, 0.0, 1.0]), fov, screen)
    assert x.min() >= screen.left_px and x.max() <= screen.width_px - screen.right_px, (x.min(), x.max())
    assert y.min() >= 0 and y.max() <= h
    assert x.max() - x.min() > 0.6 * screen.free_px  # and not a speck
    assert screen.free_px > 500  # the 2D view docks at 1× on a narrow window: the 3D view is no strip


@pytest.mark.parametrize("size", [(1366, 768), (1600, 1000)])
def test_every_view_shows_the_whole_liver_between_the_panels(size, phantoms):
    """The plane view ("Show plane 1") looked at the plane's centre from a fixed 330 mm:
    mid-canvas, so at 1600 × 1000 the demo liver's far side was behind the control panel (seen
    walking the demo). Framed like the home view, it and the standard views swung from side to
    side (and Left/Right past the panel) until the centring was damped and the camera kept
    outside the organ."""
    from navapp.app.framing import Screen, dock_width, frame, plane_view, project
    from navapp.app.panels.layers import STANDARD_VIEWS

    w, h = size
    screen = Screen(w - dock_width(w), h)
    fov = np.deg2rad(75.0)
    up = np.array([0.0, 0.0, 1.0])
    # the demo's plane 1: probe face, depth axis (z) and plane normal (y), as its panel prints them
    z, y = np.array([0.82, -0.58, -0.02]), np.array([-0.58, -0.82, 0.0])
    z /= np.linalg.norm(z)
    y -= (y @ z) * z
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = np.cross(y, z), y, z, (-83.7, 27.8, 8.0)
    for phantom in phantoms:
        liver = phantom.liver.vertices
        views = {"plane": plane_view(T, liver[::5], fov, screen, probe_mm=(50.0, 12.0, 25.0))}
        views.update({name: frame(liver[::5], d, up, fov, screen) for name, d in STANDARD_VIEWS.items()})
        for name, (position, target) in views.items():
            x, y_px = project(liver, position, target, up, fov, screen)
            assert x.min() >= screen.left_px and x.max() <= screen.width_px - screen.right_px, (name, x.min(), x.max())
            assert y_px.min() >= 0 and y_px.max() <= h, (name, y_px.min(), y_px.max())
        x, y_px = project(liver, *views["plane"], up, fov, screen)
        assert x.max() - x.min() > 0.6 * screen.free_px or y_px.max() - y_px.min() > 0.6 * h  # not a speck


def test_the_viewer_draws_without_shadows_or_image_based_lighting(app):
    """What a browser is sent on connecting: the default lights without shadows and no
    environment map. Drawn in software (no GPU), the idle viewer's shadows and image-based
    lighting cost more than a core (docs/decisions/viewer.md, "The viewer's lighting")."""
    import time

    import viser
    from conftest import viser_messages
    from websockets.sync.client import connect

    seen = {}
    port = app.server.get_port()
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                 max_size=None, open_timeout=BUSY_WAIT_S) as ws:
        end = time.monotonic() + BUSY_WAIT_S
        while "ReplayDoneMessage" not in seen and time.monotonic() < end:  # the scene so far, all of it
            for m in viser_messages(ws.recv(timeout=end - time.monotonic())):
                seen[m.get("type")] = m
    assert "EnableLightsMessage" in seen and "EnvironmentMapMessage" in seen, sorted(seen)
    assert seen["EnableLightsMessage"]["enabled"] and not seen["EnableLightsMessage"]["cast_shadow"]
    assert seen["EnvironmentMapMessage"]["hdri_data"] is None


def test_a_tabs_first_reports_made_while_its_view_is_built_are_read(app, monkeypatch):
    """The flaky HiDPI browser test (issue 48): viser builds a tab's view on a worker thread
    after the tab's first camera report and runs its camera callbacks at once, before the view
    has registered its own; the 2D page's first pixel-ratio report can come while the view is
    built too, and found no view to lay out again (later reports of the same ratio are no
    change). Nothing more came, and the 2D view stayed docked 610 px wide in a 1366 px window
    at 2×. The order is forced here: the only camera report (the canvas in device pixels) comes
    first, the page's ratio right after the view is built and before it is registered."""
    import time

    import msgspec
    import viser
    from websockets.sync.client import connect

    from navapp.app.framing import DOCK_2D_PX
    from navapp.app.panels import ClientView

    built = []
    build = ClientView.__init__

    def build_then_report(view, *a, **kw):
        build(view, *a, **kw)
        app.view2d_state.view_pixel_ratio(view.cs.token, 2.0)  # the 2D page's first poll
        built.append(view)

    monkeypatch.setattr(ClientView, "__init__", build_then_report)
    css_w, css_h = 1366 - DOCK_2D_PX[0], 768  # the canvas beside the wide dock, CSS pixels
    camera = {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, 500.0),
              "fov": 1.3, "near": 1.0, "far": 5000.0, "image_height": 2 * css_h, "image_width": 2 * css_w,
              "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, 0.0, 1.0)}
    with connect(f"ws://127.0.0.1:{app.server.get_port()}", subprotocols=[f"viser-v{viser.__version__}"],
                 max_size=None, open_timeout=BUSY_WAIT_S) as ws:
        ws.send(msgspec.msgpack.encode(camera))
        end = time.monotonic() + BUSY_WAIT_S
        while not (built and built[0] in list(app.core.views.values())) and time.monotonic() < end:
            try:
                ws.recv(timeout=0.2)  # keep the scene flowing in
            except TimeoutError:
                pass
        assert built, "no view was built"
        view = built[0]
        end = time.monotonic() + 10.0  # the view is registered: laid out within moments, or never
        while view._dock != DOCK_2D_PX[1] and time.monotonic() < end:
            try:
                ws.recv(timeout=0.2)
            except TimeoutError:
                pass
        assert view.cs.pixel_ratio == 2.0
        assert view._dock == DOCK_2D_PX[1], f"the 2D view docked {view._dock} px wide in a 1366 px window"
        assert view.screen is not None and (view.screen.width_px, view.screen.height_px) == (css_w, css_h)

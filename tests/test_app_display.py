"""What a tab draws (issue 50, item 7): every tab redraws its scene in software on a machine
without a GPU, once a second and on every change, so the preoperative and true surfaces are
drawn decimated (a liver to ``DISPLAY_FACES`` triangles, a vessel tree to ``DISPLAY_VESSEL_FACES``),
close to the surfaces themselves; the registration keeps the surfaces whole."""

import contextlib
import threading
import time

import numpy as np
import pytest
import trimesh
from conftest import BUSY_WAIT_S, run_to_end, start_app, stop_app

from navapp.app.display import DisplaySurfaces
from navapp.app.state import RunKind
from navapp.defaults import DISPLAY_FACES, DISPLAY_VESSEL_FACES

SCENE = {"name": "display", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.2}, "ius": {"planes": 2}}


def test_a_drawn_surface_is_small_and_stays_on_the_surface(phantoms):
    shown = DisplaySurfaces()
    for p in phantoms[:2]:
        for mesh, vessel in ((p.liver, False), (p.portal, True), (p.hepatic, True)):
            v, f = shown.of(mesh, vessel=vessel)
            assert len(f) <= (DISPLAY_VESSEL_FACES if vessel else DISPLAY_FACES) < len(mesh.faces)
            drawn = trimesh.Trimesh(v, f, process=False)
            # both ways, by trimesh's own closest points: the drawn vertices lie on the surface,
            # and the surface's vertices on what is drawn, within 0.3 mm (about a pixel at the
            # home view; the vessels' and the fit's errors are millimetres)
            _, out, _ = trimesh.proximity.closest_point(mesh, v)
            _, back, _ = trimesh.proximity.closest_point(drawn, np.asarray(mesh.vertices)[::5])
            assert out.max() < 0.3 and back.max() < 0.3, (p.name, out.max(), back.max())
            assert abs(drawn.volume - mesh.volume) / mesh.volume < 0.015
            assert shown.of(mesh, vessel=vessel)[0] is v  # made once, for every tab
    small = trimesh.creation.icosphere(2)
    v, f = shown.of(small)  # a surface within the budget is drawn as it is
    assert np.array_equal(v, small.vertices.astype(np.float32)) and np.array_equal(f, small.faces)


@pytest.fixture(scope="module")
def app(cache_root, tmp_path_factory):
    a = start_app(SCENE, cache_root, tmp_path_factory.mktemp("sess"))
    yield a
    stop_app(a)


@contextlib.contextmanager
def headless_tab(app):
    """A websocket speaking viser's protocol, as a tab does, held open until its view is built;
    yields ``(frames, view)``: every websocket frame the server has sent it, ``(time.monotonic(),
    bytes)``, the list growing as frames come."""
    import msgspec
    import viser
    from websockets.sync.client import connect

    # viser builds a tab's view after the tab's first camera report
    camera = {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, 500.0),
              "fov": 1.3, "near": 1.0, "far": 5000.0, "image_height": 768, "image_width": 1000,
              "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, 0.0, 1.0)}
    before = set(app.core.views)
    with connect(f"ws://127.0.0.1:{app.server.get_port()}", subprotocols=[f"viser-v{viser.__version__}"],
                 max_size=None, open_timeout=BUSY_WAIT_S) as ws:
        frames: list[tuple[float, bytes]] = []

        def drain():  # keep reading, or viser's sends to this tab would wait on a full socket
            try:
                while True:
                    frames.append((time.monotonic(), ws.recv()))
            except Exception:  # closed at the end of the test
                pass

        threading.Thread(target=drain, daemon=True).start()
        ws.send(msgspec.msgpack.encode(camera))
        end = time.monotonic() + BUSY_WAIT_S
        view = None
        while (view is None or not view.layers.nodes["True deformed liver (ghost)"]) and time.monotonic() < end:
            new = [v for k, v in app.core.views.items() if k not in before]
            view = new[0] if new else None
            time.sleep(0.2)
        assert view is not None, "the tab's view was not built"
        yield frames, view


def kinds(frame: bytes) -> list[str]:
    """The message types in one of viser's websocket frames (its wire format, viser.infra:
    two little-endian sizes, then the zstd-compressed msgpack of the batch)."""
    import msgspec
    import zstandard

    size, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(frame[16:16 + packed], max_output_size=size)
    return [m["type"] for m in msgspec.msgpack.decode(inner)["messages"]]


def test_a_tab_is_sent_the_drawn_surfaces_and_the_fit_keeps_the_whole_ones(app):
    with headless_tab(app) as (_, view):
        nodes = view.layers.nodes
        drawn = [*nodes["Preoperative liver"], *nodes["True deformed liver (ghost)"],
                 *[n for n in nodes["Preoperative vessels"] if hasattr(n, "faces")]]
        assert len(drawn) == 4  # the liver, its true deformed ghost, two vessel trees
        assert all(len(n.faces) <= DISPLAY_FACES for n in drawn[:2])
        assert all(len(n.faces) <= DISPLAY_VESSEL_FACES for n in drawn[2:])
        # an idle frame's cost in software follows the triangles drawn: a tenth of the surfaces'
        assert sum(len(n.faces) for n in drawn) < 0.1 * (2 * len(app.core.preop.liver.faces)
                                                         + len(app.core.preop.portal.faces)
                                                         + len(app.core.preop.hepatic.faces))


def test_an_idle_tab_is_sent_nothing(app):
    """A tab redraws its 3D scene for every message batch that touches the scene and, in
    viser's client, once a second besides (its heartbeat, which navapp cannot turn off). With
    several tabs on a machine without a GPU every redraw costs (docs/decisions/viewer.md, "What makes
    an idle tab redraw"): navapp must send nothing while nothing changes, no clock, no 'seen N s ago', no
    progress it already sent. Counts the frames of 6 s once the tab's first picture is sent."""
    with headless_tab(app) as (frames, _):
        assert app.core.settle()
        # the rest of the view's first picture: until the tab has heard nothing for 5 s (a
        # sender that never stops is caught below, not waited for)
        end = time.monotonic() + 120.0
        while time.monotonic() < end and (not frames or time.monotonic() - frames[-1][0] < 5.0):
            time.sleep(0.2)
        start = len(frames)
        time.sleep(6.0)
        sent = frames[start:]
        assert len(sent) == 0, f"an idle server sent this tab {len(sent)} frames: {[kinds(f) for _, f in sent]}"


def test_the_translucent_livers_are_drawn_one_sided_and_face_out(app):
    """One-sided, a liver is drawn from its outer faces only: right only where those faces wind
    outward (a face wound inward would be a hole). Checked on what a tab is sent: the decimated
    preoperative liver against the surface's own normals, and the registered liver (the mesh's
    boundary) after a rigid fit."""
    with headless_tab(app) as (_, view):
        app.stylus.collect_now()
        run_to_end(app, RunKind.RIGID)
        assert app.core.settle()
        (preop,), (registered,) = view.layers.nodes["Preoperative liver"], view.layers.nodes["Registered liver"]
        assert preop.side == registered.side == "front"
        liver = app.core.preop.liver
        drawn = trimesh.Trimesh(preop.vertices, preop.faces, process=False)
        _, _, nearest = trimesh.proximity.closest_point(liver, drawn.triangles_center)
        agree = np.einsum("ij,ij->i", drawn.face_normals, liver.face_normals[nearest]) > 0
        assert agree.mean() > 0.999, agree.mean()
        assert drawn.volume > 0
        reg = trimesh.Trimesh(registered.vertices, registered.faces, process=False)
        assert reg.is_winding_consistent and reg.volume > 0


def test_the_legend_names_only_the_layers_that_draw_something(app):
    """The legend's ghost line is there with a truth, and its supports line only while supports
    are stated (before, it listed "held at the stated supports" over an empty layer)."""
    from navapp.app.panels.registration import HELD
    from navapp.app.state import StatedSupports

    with headless_tab(app) as (_, view):
        def legend():
            return view.layers.legend.content

        assert "true liver (ghost)" in legend() and "held at the stated supports" not in legend()
        bed = HELD["A posterior bed"]
        try:
            app.runs.set_supports(bed)
            end = time.monotonic() + BUSY_WAIT_S
            while not view.layers.nodes["Stated supports"] and time.monotonic() < end:
                time.sleep(0.2)
            assert view.layers.nodes["Stated supports"], "the stated supports were not drawn"
            assert "held at the stated supports" in legend()
        finally:
            app.runs.set_supports(StatedSupports())
        end = time.monotonic() + BUSY_WAIT_S
        while view.layers.nodes["Stated supports"] and time.monotonic() < end:
            time.sleep(0.2)
        assert "held at the stated supports" not in legend()

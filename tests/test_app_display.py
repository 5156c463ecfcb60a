"""What a tab draws (issue 50, item 7): every tab redraws its scene in software on a machine
without a GPU, once a second and on every change, so the preoperative and true surfaces are
drawn decimated to ``DISPLAY_FACES`` triangles each, close to the surfaces themselves; the
registration keeps the surfaces whole."""

import time

import numpy as np
import pytest
import trimesh
from conftest import BUSY_WAIT_S, start_app, stop_app

from navapp.app.display import DisplaySurfaces
from navapp.defaults import DISPLAY_FACES

SCENE = {"name": "display", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.2}, "ius": {"planes": 2}}


def test_a_drawn_surface_is_small_and_stays_on_the_surface(phantoms):
    shown = DisplaySurfaces()
    for p in phantoms[:2]:
        for mesh in (p.liver, p.portal, p.hepatic):
            v, f = shown.of(mesh)
            assert len(f) <= DISPLAY_FACES < len(mesh.faces)
            drawn = trimesh.Trimesh(v, f, process=False)
            # both ways, by trimesh's own closest points: the drawn vertices lie on the surface,
            # and the surface's vertices on what is drawn, within a fifth of a millimetre
            _, out, _ = trimesh.proximity.closest_point(mesh, v)
            _, back, _ = trimesh.proximity.closest_point(drawn, np.asarray(mesh.vertices)[::5])
            assert out.max() < 0.2 and back.max() < 0.2, (p.name, out.max(), back.max())
            assert abs(drawn.volume - mesh.volume) / mesh.volume < 0.01
            assert shown.of(mesh)[0] is v  # made once, for every tab
    small = trimesh.creation.icosphere(2)
    v, f = shown.of(small)  # a surface within the budget is drawn as it is
    assert np.array_equal(v, small.vertices.astype(np.float32)) and np.array_equal(f, small.faces)


@pytest.fixture(scope="module")
def app(cache_root, tmp_path_factory):
    a = start_app(SCENE, cache_root, tmp_path_factory.mktemp("sess"))
    yield a
    stop_app(a)


def test_a_tab_is_sent_the_drawn_surfaces_and_the_fit_keeps_the_whole_ones(app):
    import msgspec
    import viser
    from websockets.sync.client import connect

    # viser builds a tab's view after the tab's first camera report
    camera = {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, 500.0),
              "fov": 1.3, "near": 1.0, "far": 5000.0, "image_height": 768, "image_width": 1000,
              "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, 0.0, 1.0)}
    with connect(f"ws://127.0.0.1:{app.server.get_port()}", subprotocols=[f"viser-v{viser.__version__}"],
                 max_size=None, open_timeout=BUSY_WAIT_S) as ws:
        ws.send(msgspec.msgpack.encode(camera))
        end = time.monotonic() + BUSY_WAIT_S
        while not (app.core.views and next(iter(app.core.views.values())).layers.nodes["True deformed liver (ghost)"]) \
                and time.monotonic() < end:
            try:
                ws.recv(timeout=0.2)
            except TimeoutError:
                pass
        view = next(iter(app.core.views.values()))
        nodes = view.layers.nodes
        drawn = [*nodes["Preoperative liver"], *nodes["True deformed liver (ghost)"],
                 *[n for n in nodes["Preoperative vessels"] if hasattr(n, "faces")]]
        assert len(drawn) == 4  # the liver, its true deformed ghost, two vessel trees
        assert all(len(n.faces) <= DISPLAY_FACES for n in drawn)
        assert sum(len(n.faces) for n in drawn) < 0.4 * (2 * len(app.core.preop.liver.faces)
                                                         + len(app.core.preop.portal.faces)
                                                         + len(app.core.preop.hepatic.faces))

"""Shared fixtures: small meshes so that the suite stays fast on a 2-core machine."""

import os
import tempfile
import time
from pathlib import Path

# Each of the two xdist workers holds its BLAS / OpenMP pools at one thread: two workers on
# two cores already fill the machine, and a pool of two threads per worker only added waits
# (OpenBLAS's threads spin after each call; tests ran with more CPU seconds than wall seconds
# beside the other worker). Set before NumPy loads; children (CLI runs, Dask workers) inherit
# it. A single-process run (-n 0) keeps the installed pools.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest

# keep the suite's cache entries out of the user's ~/.cache/navapp
os.environ["NAVAPP_CACHE"] = tempfile.mkdtemp(prefix="navapp-test-cache-")

from navapp import progress  # noqa: E402

progress.QUIET = True


# The suite runs on two workers (pytest-xdist, ``-n 2`` in pyproject.toml): a 2-core CI machine
# sat about half idle through the single-threaded tests. A module's tests stay on one worker
# (its module fixtures are built once); the modules that drive Chromium share one worker, so
# that two software-drawn browsers never compete for the two cores. (xdist's own
# ``--dist loadgroup`` does not group under pytest 9: it renames the test ids, which pytest 9
# no longer reads back; the scheduler below groups by module name instead.) A module drives
# Chromium when its source names Playwright: a list of names missed two modules added later
# (the run table's, the access tokens'), whose browsers then ran beside the others'.
TESTS = Path(__file__).parent
BROWSER = "browser"


def drives_chromium(module: str) -> bool:
    """Whether the test module ``module`` (a path from the test ids) launches Chromium."""
    path = TESTS / Path(module).name
    return path.suffix == ".py" and path.is_file() and "playwright" in path.read_text(encoding="utf-8")


@pytest.hookimpl(optionalhook=True)  # an xdist hook: absent without it
def pytest_xdist_make_scheduler(config, log):
    from functools import cache

    from xdist.scheduler import LoadScopeScheduling

    browser = cache(drives_chromium)

    class ByModule(LoadScopeScheduling):
        def _split_scope(self, nodeid):
            module = nodeid.split("::", 1)[0]
            return BROWSER if browser(module) else module

        def _assign_work_unit(self, node):
            # the browser scope first: it is the suite's longest chain (one Chromium at a time),
            # and queued by its test count it started a third of the way through
            if BROWSER in self.workqueue:
                self.workqueue.move_to_end(BROWSER, last=False)
            super()._assign_work_unit(node)

    return ByModule(config, log)


def compile_once():
    """Compile navapp's Numba kernels into their on-disk cache (``cache=True``), with the
    argument types registration gives them (a real registration's signatures: C-contiguous
    float64 and int64 arrays, SciPy's int32 CSR index arrays). In a fresh clone every
    process compiled them for itself until one had written the cache: both workers at once
    (13.8 CPU s in one worker's first registration), and CLI children started meanwhile;
    done once here, before the workers start, each of them loads the cache instead. Types
    missed here only mean that a process compiles what is missing, as before."""
    try:
        import numba  # noqa: F401
    except ImportError:  # pragma: no cover - only without numba
        return
    import trimesh

    from navapp.geometry.bvh import SurfaceHierarchy
    from navapp.geometry.closest import closest_on_surface, incidence, surface_normals
    from navapp.registration.jacobian_compiled import alpha_columns, apply, carried, pose_columns

    ball = trimesh.creation.icosphere(subdivisions=1)
    v = np.ascontiguousarray(ball.vertices, dtype=float)
    f = np.ascontiguousarray(ball.faces, dtype=np.int64)
    p = v[:5] * 1.1
    h = SurfaceHierarchy(v, f)
    h.closest(p, v, h.refit(v))
    face, bary, _ = closest_on_surface(p, v, f, incidence(len(v), f))
    surface_normals(p, v, f, face, bary)
    n = 2
    alpha_columns(np.array([0, 1], np.int32), np.array([0], np.int32), np.ones(1), np.zeros((1, 3, n)),
                  np.zeros((1, 3)), np.zeros(1, np.int64), np.zeros((1, 3, n), np.float32), np.zeros((1, 3 * n + 6)),
                  np.ones(1), np.zeros((1, 3 * n + 6)))
    pose_columns(np.array([0, 1], np.int32), np.array([0], np.int32), np.ones(1), np.zeros((1, 3)),
                 np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((3, 3, 3)), np.zeros(1, np.int64), np.zeros((1, 3)),
                 np.zeros((1, 3 * n + 6)), np.ones(1), np.zeros((1, 3 * n + 6)))
    carried(np.zeros((1, 3, n), np.float32), np.zeros(n), np.zeros((1, 3)))
    apply(np.array([0, 1], np.int32), np.array([0], np.int32), np.ones(1), np.zeros((1, 3)), np.zeros((1, 3)))
    from navapp.registration.deform_compiled import place

    place(np.zeros((1, 3)), np.zeros(3, np.float32), np.zeros(3), np.eye(3), np.zeros(3), np.zeros((1, 3)),
          np.zeros((1, 3)))


def pytest_configure(config):
    # the two-worker run's controller compiles the Numba kernels once for both workers
    if not hasattr(config, "workerinput") and config.pluginmanager.hasplugin("xdist") and \
            getattr(config.option, "numprocesses", None):
        compile_once()
    # NAVAPP_TIMELINE=PREFIX: each test's wall and CPU seconds per worker (``timeline``)
    if os.environ.get("NAVAPP_TIMELINE"):
        from timeline import Recorder

        config.pluginmanager.register(Recorder(os.environ["NAVAPP_TIMELINE"]), "navapp-timeline")


@pytest.fixture(scope="session")
def phantoms():
    from navapp.anatomy.phantom import make_phantom

    return [make_phantom(i) for i in range(3)]


@pytest.fixture(scope="session")
def cache_root(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="session")
def coarse_mesh(phantoms, cache_root):
    """Phantom 0 meshed at 12 mm (≈1k nodes)."""
    from navapp.anatomy.meshing import cached_tetmesh

    mesh, _ = cached_tetmesh(phantoms[0].liver, 12.0, cache_root)
    return mesh


@pytest.fixture(scope="session")
def small_basis(coarse_mesh, cache_root):
    from navapp.mechanics.basis import BasisSettings, load_or_compute_basis

    basis, _ = load_or_compute_basis(coarse_mesh, BasisSettings(k=12), cache_root=cache_root)
    return basis


@pytest.fixture(scope="session")
def small_model(small_basis, phantoms):
    from navapp.registration.model import build_model

    rng = np.random.default_rng(5)
    fid = small_basis.nodes[rng.choice(small_basis.M, 6, replace=False)]
    return build_model(small_basis, phantoms[0], fiducials=fid)


def free_port() -> int:
    """A TCP port nobody is listening on (for the viewer's tests)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def viser_messages(frame) -> list:
    """The messages of one viser websocket frame (8-byte msgpack size, 8-byte compressed
    size, zstd msgpack, binary buffers); [] for anything else."""
    import msgspec
    import zstandard

    if not isinstance(frame, bytes) or len(frame) < 16:
        return []
    n = int.from_bytes(frame[8:16], "little")
    return list(msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16:16 + n])).get("messages", ()))


# The longest any test waits for work that takes seconds on a quiet machine: a bound, not a
# time target (issue 25: the suite must pass beside a CPU hog; a 120 s join failed at load 14)
BUSY_WAIT_S = 900.0


def refused_in_one_line(read, path, text: str, problem: str):
    """``read(path)`` of a file holding ``text`` raises one InputError line that names the file
    first and says ``problem``."""
    from navapp.errors import InputError

    path.write_text(text)
    with pytest.raises(InputError) as err:
        read(path)
    msg = str(err.value)
    assert msg.startswith(str(path)) and problem in msg and "\n" not in msg, msg


def wait_until(cond, timeout=BUSY_WAIT_S, step=0.01) -> bool:
    """Poll ``cond()`` until true or ``timeout`` s have passed (then its last answer): a test
    waiting on another thread or process returns as soon as it is done, and on a loaded machine
    waits the whole bound rather than failing early."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step)
    return cond()


def start_app(scene: dict, cache_root, folder):
    """The viewer's App on a small scene (``scene``: a scene TOML as a dict), registration mesh
    12 mm and k = 12, started headless; the test fixtures' one way to make one."""
    from navapp.app.server import App
    from navapp.simulation.scene import parse_scene

    a = App(parse_scene(scene), port=free_port(), session_dir=folder, edge=12.0, k=12, cache_root=cache_root)
    assert a.start().wait(600), "start-up did not finish"
    assert a.core.failed is None, a.core.failed
    return a


def stop_app(a):
    a.server.stop()
    a.view2d.stop()


def run_to_end(app, kind):
    """Start a registration of ``kind`` and wait for its row in the run table."""
    assert app.runs.start(kind) is None
    app.core.worker.join(BUSY_WAIT_S)
    assert not app.core.worker.busy
    return app.core.session.log[-1]


def noisy_feature_data(model, rng):
    """Noisy points of a surface, a vessel surface and a centerline off the undeformed model,
    moved by a small pose (the LM-reuse and fold tests' data)."""
    out = {}
    for name, feat, count in (("anterior", "liver", 150), ("portal_contour", "portal", 60),
                              ("portal_centerline", "portal_centerline", 20)):
        X = model.features[feat].rest
        out[name] = X[rng.choice(len(X), count, replace=False)] + rng.normal(size=(count, 3)) + [2.0, -1.0, 1.5]
    return out

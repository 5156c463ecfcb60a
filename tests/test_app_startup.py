"""``navapp serve``'s terminal (issue 25, item 6): every start-up stage on a line of its
own, "Ready." when ready, a failed start-up ending the process with exit 2 and one line
(the viewer does not stay up with a dead app), and no traceback when a tab closes."""

import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import urllib.request

import tomli_w
from conftest import free_port

SCENE = {"name": "apptest", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.2}, "ius": {"planes": 2}}
BUDGET_S = 600  # a cold start of the small scene on a busy 2-core machine; never reached when it works


def serve(tmp_path, *args, env=None, code=None):
    """``navapp serve`` on the small scene in a subprocess, stdout and stderr in one pipe
    (what a terminal shows); with ``code``, run that Python first (fault injection)."""
    scene = tmp_path / "scene.toml"
    scene.write_text(tomli_w.dumps(SCENE))
    argv = ["serve", "--port", str(free_port()), "--session", str(tmp_path / "session"), "--edge", "12",
            "--k", "12", str(scene), *args]
    prog = f"import sys\n{code or ''}\nfrom navapp.cli import main\nsys.exit(main({argv!r}))"
    # Ctrl+C as a terminal sends it: a suite started in the background (nohup, `cmd &`) hands its
    # children SIGINT ignored, and a Python started so never raises KeyboardInterrupt
    return subprocess.Popen([sys.executable, "-c", prog], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def shown(raw: bytes) -> list[str]:
    """The terminal's lines as a person reads them: a progress bar redraws its line after a
    carriage return, so each line is what follows its last one."""
    return [line.rsplit("\r", 1)[-1].rstrip() for line in raw.decode(errors="replace").split("\n")]


def finished(proc) -> tuple[int, list[str]]:
    try:
        out, _ = proc.communicate(timeout=BUDGET_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError("navapp serve was still running after its start-up failed:\n"
                             + "\n".join(shown(out)[-20:])) from None
    return proc.returncode, shown(out)


def test_each_stage_and_ready_reach_the_terminal_on_lines_of_their_own(tmp_path, cache_root):
    # a session whose first save an earlier navapp had cut short: its repair is one of the lines
    (tmp_path / "session").mkdir()
    (tmp_path / "session" / "case.toml").write_text('name = "session-apptest"\n')
    # the cache the viewer tests fill, so that a full run of the suite pays for one cold start
    # with --slicer PORT (README: Slicer's OpenIGTLinkIF connector in client mode connects to it)
    slicer_port = free_port()
    proc = serve(tmp_path, "--slicer", str(slicer_port), env={"NAVAPP_CACHE": str(cache_root)})
    lines = []
    slicer_listens = None
    budget = threading.Timer(BUDGET_S, proc.kill)  # ends the read below if "Ready." never comes
    budget.start()
    try:
        for raw in iter(proc.stdout.readline, b""):  # the bars are drawn: no --quiet
            lines += shown(raw)
            if any(line.startswith("navapp: Ready.") for line in lines):
                with socket.socket() as probe:  # where Slicer would connect
                    slicer_listens = probe.connect_ex(("127.0.0.1", slicer_port)) == 0
                break
    finally:
        budget.cancel()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=600)  # a budget: stopping waits for the running step
    lines += shown(out)
    said = [line for line in lines if line.startswith("navapp: ")]
    assert any(line.startswith("navapp: Simulating the intraoperative scene") for line in said), lines
    assert any(line.startswith("navapp: Building the registration model") for line in said), lines
    assert f"navapp: {tmp_path / 'session'}: its first save had been cut short" in "\n".join(said), lines
    ready = [line for line in said if line.startswith("navapp: Ready.")]
    assert len(ready) == 1 and "nodes, k = 12" in ready[0] and str(tmp_path / "session") in ready[0], lines
    assert not any("Traceback" in line for line in lines), lines
    assert (f"navapp: registrations go to 3D Slicer over OpenIGTLink on 127.0.0.1:{slicer_port} (Slicer connects)"
            in said), lines
    assert slicer_listens, lines


def refused(tmp_path, memory_mb: str) -> tuple[str, list[str]]:
    """``navapp serve`` under a pretended memory budget: its one error line and the terminal's
    lines, after checking that it ended with exit 2, one error line and no traceback."""
    proc = serve(tmp_path, env={"NAVAPP_CACHE": str(tmp_path / "cache"), "NAVAPP_MEMORY_MB": memory_mb})
    code, lines = finished(proc)
    errors = [line for line in lines if "error" in line.lower()]
    assert code == 2 and len(errors) == 1, lines
    assert not any("Traceback" in line for line in lines), lines
    return errors[0], lines


def test_a_scene_that_cannot_load_ends_serve_with_exit_2_and_one_line(tmp_path):
    # the scene's simulation needs a truth mesh (10 mm: ~1,160 nodes, ~452 MB) that this (pretended)
    # memory cannot hold, while the registration mesh (--edge 12: ~670 nodes, ~430 MB) fits, so the
    # viewer starts and its start-up fails; a --edge too fine is refused before it starts (below)
    error, lines = refused(tmp_path, "440")
    assert error.startswith("navapp: error: the viewer could not start: "), lines
    assert "a mesh at 10 mm" in error and "set deformation.mesh_edge_mm = " in error, lines


def test_a_registration_mesh_too_fine_for_memory_ends_serve_before_the_viewer_starts(tmp_path):
    error, lines = refused(tmp_path, "420")
    assert error.startswith("navapp: error: a mesh at 12 mm would have about "), lines
    assert "need about 430 MB, more than the 420 MB" in error and "use --edge " in error, lines
    assert not any("Simulating" in line for line in lines), lines


def test_a_failing_start_up_step_ends_serve_with_one_line_naming_its_traceback(tmp_path):
    # a bug (not an input error) in a start-up step, here the scene's loading: one line, the traceback kept in a file
    boom = ("import navapp.app.core as core\n"
            "def boom(*a, **k):\n"
            "    raise RuntimeError('the mesher crashed')\n"
            "core.load_scene_data = boom")
    code, lines = finished(serve(tmp_path, env={"NAVAPP_CACHE": str(tmp_path / "cache")}, code=boom))
    assert code == 2, lines
    errors = [line for line in lines if "error" in line.lower()]
    assert len(errors) == 1, lines
    assert errors[0].startswith("navapp: error: the viewer could not start: RuntimeError: the mesher crashed"), lines
    assert not any("Traceback" in line for line in lines), lines
    path = errors[0].rsplit("the traceback is in ", 1)[1].rstrip(")")
    try:
        assert "RuntimeError: the mesher crashed" in open(path).read()
    finally:
        os.unlink(path)


class SlowImage:
    """A 2D view provider whose frame is sent only once the test's client has gone (a tab
    closed while its image was on the way)."""

    def __init__(self):
        self.asked, self.gone = threading.Event(), threading.Event()

    def view_known(self, token):
        return True

    def view_image(self, token):
        self.asked.set()
        self.gone.wait(60)
        return b"\x89PNG" + bytes(8 << 20)  # larger than any socket buffer: the write meets the reset


def test_a_tab_closing_mid_response_leaves_no_traceback(capfd, caplog):
    from navapp.app.view2d.http import View2DServer

    provider = SlowImage()
    server = View2DServer(provider)
    before = set(threading.enumerate())
    try:
        client = socket.create_connection(("127.0.0.1", server.port))
        client.sendall(b"GET /us/image?c=tab HTTP/1.1\r\nHost: x\r\n\r\n")
        assert provider.asked.wait(60)
        # closed with a reset, as a browser drops a closed tab's connections
        client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        client.close()
        provider.gone.set()
        for t in set(threading.enumerate()) - before:  # the request's handler thread
            t.join(60)
        ok = urllib.request.urlopen(f"http://127.0.0.1:{server.port}/us/page.js", timeout=60)
        assert ok.status == 200  # still serving
    finally:
        server.stop()
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Error" not in err, err
    # nor through the log (its last-resort handler prints to the terminal when nothing is configured)
    assert not [r for r in caplog.records if r.exc_info], caplog.text


def test_work_aside_is_heard_only_once_the_main_task_waits_for_it(capsys):
    """A basis made ahead reports nothing while the simulation it runs beside holds the one
    status line (its steps flipped with the other's), and its steps once the start-up waits
    for it; its bars never reach the terminal."""
    from navapp import progress

    heard_of, heard, first_done = [], threading.Event(), threading.Event()
    listener = progress.add_listener(lambda desc, fraction: heard_of.append(desc))
    try:
        def ahead():
            with progress.aside(heard):
                with progress.bar(3, "before the wait") as bar, progress.stage("staged before"):
                    bar.update(3)
                first_done.set()
                heard.wait()
                with progress.bar(2, "after the wait") as bar:
                    bar.update(2)

        thread = threading.Thread(target=ahead)
        thread.start()
        first_done.wait(BUDGET_S)
        with progress.bar(2, "the main task") as bar:
            bar.update(2)
        heard.set()
        thread.join()
    finally:
        progress.remove_listener(listener)
    assert "the main task" in heard_of and "after the wait" in heard_of, heard_of
    assert "before the wait" not in heard_of and "staged before" not in heard_of, heard_of
    err = capsys.readouterr().err
    assert "before the wait" not in err and "after the wait" not in err


def test_a_first_start_builds_the_registration_model_beside_the_simulation(tmp_path, phantoms, monkeypatch):
    """From an empty cache, the registration mesh and basis are made on their own thread while
    the scene is simulated, from the very surface and settings ``prepare`` asks for (so it
    finds both cached); a second start, the scene cached, makes nothing ahead."""
    from navapp.anatomy import meshing
    from navapp.app import core
    from navapp.registration import pipeline
    from navapp.simulation.scene import parse_scene

    made = []
    mesh_liver, load_basis = meshing.mesh_liver, pipeline.load_or_compute_basis

    def meshed(surface, edge, **kw):
        made.append(("mesh", edge, threading.current_thread().name))
        return mesh_liver(surface, edge, **kw)

    def based(mesh, settings, **kw):
        basis, cached = load_basis(mesh, settings, **kw)
        made.append(("basis", cached, threading.current_thread().name))
        return basis, cached

    monkeypatch.setattr(meshing, "mesh_liver", meshed)
    monkeypatch.setattr(pipeline, "load_or_compute_basis", based)
    scene = parse_scene(SCENE)
    for start in (1, 2):
        c = core.Core(scene, phantoms[0], 12.0, 12, cache_root=tmp_path / "cache", session_dir=tmp_path / "s")
        assert c.start(lambda loaded: None, lambda ready: None).wait(BUDGET_S) and c.failed is None, c.failed
        if start == 1:
            assert made.count(("mesh", 12.0, "navapp-model-ahead")) == 1, made  # ahead, and only there
            assert ("mesh", 10.0, "navapp-startup") in made, made  # the scene's truth mesh, in the start-up
            assert ("basis", False, "navapp-model-ahead") in made, made  # computed ahead ...
            assert ("basis", True, "navapp-startup") in made, made  # ... and found by prepare
            assert len(made) == 4, made
            made.clear()
    assert made == [("basis", True, "navapp-startup")], made  # a second start: nothing ahead

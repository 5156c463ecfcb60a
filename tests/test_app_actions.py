"""The session's action log: every change to shared data with time, tab and role, append-only
in actions.jsonl; it survives kill -9 and a restart, and is exported with the session. The
guided demo is walked headless through its own step actions."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import BUSY_WAIT_S, start_app, stop_app

from navapp.app.access import Role
from navapp.app.actions import FILE, Act, ActionLog
from navapp.app.guide import STEPS
from navapp.app.state import RunKind

SCENE = {"name": "actionstest", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.2}, "ius": {"planes": 2}}


def lines(folder):
    return [json.loads(x) for x in (folder / FILE).read_text().splitlines()]


def test_log_appends_keeps_and_cuts_a_torn_line(tmp_path):
    log = ActionLog(tmp_path / "s")
    log.append("tab 0", Role.EDITOR, Act.PLANE, "plane 1")
    log.append("tab 1", Role.OBSERVER, Act.RUN, "rigid")
    got = lines(tmp_path / "s")
    assert [(x["tab"], x["role"], x["action"]) for x in got] == [("tab 0", "editor", "plane added"),
                                                                 ("tab 1", "observer", "run started")]
    assert got[0]["time"].endswith("Z") and got[0]["time"] <= got[1]["time"]
    with open(tmp_path / "s" / FILE, "ab") as f:  # a kill in the middle of a line
        f.write(b'{"time": "2026-01-01T00:00:00.000Z", "tab": "ta')
    again = ActionLog(tmp_path / "s")
    assert [e.act for e in again.entries()] == [Act.PLANE, Act.RUN]
    assert (tmp_path / "s" / FILE).read_bytes().endswith(b"\n")  # the torn line is cut, the next one whole
    again.append("tab 2", Role.EDITOR, Act.EXPORT)
    assert [x["action"] for x in lines(tmp_path / "s")] == ["plane added", "run started", "exported"]


WRITER = """
import sys
from navapp.app.access import Role
from navapp.app.actions import Act, ActionLog
log = ActionLog(sys.argv[1])
for i in range(100000):
    log.append("tab 7", Role.EDITOR, Act.VERTEX, f"vertex {i}")
    print(i, flush=True)  # acknowledged: written and fsync'd
"""


def test_every_acknowledged_line_survives_kill_9(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    acked = -1
    t0 = time.monotonic()
    while acked < 200 and time.monotonic() - t0 < 120:
        acked = int(proc.stdout.readline())
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(30)
    log = ActionLog(tmp_path)
    details = [e.detail for e in log.entries()]
    assert len(details) >= acked + 1 and details[: acked + 1] == [f"vertex {i}" for i in range(acked + 1)]


@pytest.fixture(scope="module")
def app(cache_root, tmp_path_factory):
    a = start_app(SCENE, cache_root, tmp_path_factory.mktemp("sess"))
    yield a
    stop_app(a)


def wait(cond, what, timeout=BUSY_WAIT_S):
    t0 = time.monotonic()
    while not cond():
        assert time.monotonic() - t0 < timeout, what
        time.sleep(0.05)


def test_guided_demo_is_logged_with_its_tab_and_survives_a_restart(app, cache_root):
    core = app.core
    cs = core.new_client_state(3)
    other = core.new_client_state(4)
    for step in STEPS:
        wait(lambda st=step: st.blocked(app, cs) is None, f"{step.title}: {step.blocked(app, cs)}")
        if step.title == "Stylus digitisation":  # the guide's own sweep at the panel's 20×
            assert app.stylus.start(lambda: 20.0, cs)
        elif step.title == "Draw contours":
            assert step.action(app, cs) is None
            for col, row in ((100, 100), (140, 100), (140, 140), (100, 140)):
                assert app.drawing.click(cs, col, row) is None
            assert app.drawing.command(cs, "Close") is None
        else:
            assert step.action(app, cs) is None, step.title
        if step.done is not None:
            wait(lambda st=step: st.done(app, cs), step.title)
        core.worker.join(BUSY_WAIT_S)
    assert app.drawing.command(other, "Undo") == "Nothing of yours to undo."  # nothing changed: nothing logged
    assert app.imaging.show(other, 1) and app.imaging.add(other) is None
    assert app.drawing.command(other, "Undo") is None  # the plane added by tab 4 is taken back
    assert app.runs.show(len(core.session.log) - 2, cs) is None
    out, _ = app.export(cs)
    got = lines(core.session.folder)
    seen = [(x["tab"], x["action"]) for x in got]
    want = [("tab 3", "stylus sweep"), ("tab 3", "points digitised"), ("tab 3", "run started"),
            ("server", "run finished"), ("tab 3", "run started"), ("server", "run finished"),
            *[("tab 3", "contour vertex")] * 4, ("tab 3", "contour committed"), ("tab 3", "run started"),
            ("server", "run finished"), ("tab 4", "plane added"), ("tab 4", "undone"), ("tab 3", "run chosen"),
            ("tab 3", "exported")]
    assert seen == want, seen
    assert all(x["role"] == "editor" for x in got if x["tab"] != "server")
    assert got[2]["detail"].startswith("rigid") and "deformable" in got[4]["detail"]
    assert got[14]["detail"] == "plane added"
    # exported with the session, its own export line last
    assert (out / FILE).read_text() == (core.session.folder / FILE).read_text()
    # a restart on the same session folder shows it all and appends after it
    again = start_app(SCENE, cache_root, core.session.folder)
    try:
        assert [(e.tab, e.act.value) for e in again.core.actions.entries()] == want
        assert again.runs.start(RunKind.RIGID, again.core.new_client_state(0)) is None
        again.core.worker.join(BUSY_WAIT_S)
        assert [x["action"] for x in lines(core.session.folder)][-2:] == ["run started", "run finished"]
    finally:
        stop_app(again)


def test_an_observer_tab_changes_nothing_and_logs_nothing(app):
    core = app.core
    obs = core.new_client_state(9, Role.OBSERVER)
    before = (core.actions.path.read_bytes(), json.dumps(core.session.to_json()))
    assert app.imaging.show(obs, 0)  # its own view: allowed
    assert "Observer link" in app.view2d_state.view_click(obs.token, 10, 10, "PV contour", 0)
    assert "Observer link" in app.view2d_state.view_command(obs.token, "Clear plane", "PV contour", 0)
    assert (core.actions.path.read_bytes(), json.dumps(core.session.to_json())) == before


def test_a_failed_run_is_logged_as_finished_with_its_reason(app):
    from navapp.errors import NavappError

    app.runs.on_error(NavappError("the data are degenerate"))
    last = lines(app.core.session.folder)[-1]
    assert (last["tab"], last["action"], last["detail"]) == ("server", "run finished",
                                                             "failed: the data are degenerate")


KILLED_MID_RUN = """
import sys, time
from pathlib import Path
sys.path.insert(0, {tests!r})
from conftest import start_app
from navapp.app.state import RunKind
app = start_app({scene!r}, Path({cache!r}), Path({folder!r}))
cs = app.core.new_client_state(1)
app.stylus.collect_now()
assert app.runs.start(RunKind.ALL, cs) is None
while app.core.run is None or app.core.run.streamed < 1:
    time.sleep(0.01)
print("running", flush=True)
time.sleep(600)
"""


def test_a_run_the_server_was_killed_in_leaves_an_interrupted_row(cache_root, tmp_path):
    """Issue 50, item 5: kill -9 of the server while a run went left no row and no message."""
    from pathlib import Path

    folder = tmp_path / "sess"
    script = KILLED_MID_RUN.format(tests=str(Path(__file__).parent), scene=SCENE, cache=str(cache_root),
                                   folder=str(folder))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        for line in proc.stdout:  # viser's banner comes first
            if line.strip() == "running":
                break
        else:
            pytest.fail("the server never ran the registration")
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    said = []
    again = start_app(SCENE, cache_root, folder)
    try:
        last = again.core.session.log[-1]
        assert last.run == "deformable, all data" and last.stop == "interrupted" and last.cancelled, last
        assert last.points > 100
        assert [x["action"] for x in lines(folder)][-2:] == ["run started", "run finished"]
        assert lines(folder)[-1]["detail"].startswith("interrupted")
        again.core.notify = lambda title, body, error=False: said.append(body)
    finally:
        stop_app(again)
    # a second restart adds nothing more: the run has its end now
    third = start_app(SCENE, cache_root, folder)
    try:
        assert [e.stop for e in third.core.session.log].count("interrupted") == 1
    finally:
        stop_app(third)


def test_back_on_a_plane_left_mid_contour_the_next_click_continues_it(app):
    """Issue 50, item 5: coming back to a plane with an unfinished contour started a new contour
    and left the old one as an open line."""
    cs = app.core.new_client_state(7)
    assert app.imaging.show(cs, 0)
    for col, row in ((60, 60), (90, 60)):
        assert app.drawing.click(cs, col, row, "HV contour") is None
    c = cs.drawing
    assert app.imaging.show(cs, 1) and cs.drawing is None
    assert app.imaging.show(cs, 0) and cs.drawing is c
    assert app.drawing.click(cs, 90, 90, "HV contour") is None
    assert app.drawing.command(cs, "Close") is None
    mine = [x for x in app.core.session.contours if x.plane == 0 and x.feature == "hepatic_contour"]
    assert mine == [c] and c.vertices == [(60, 60), (90, 60), (90, 90)] and c.closed
    assert app.drawing.command(cs, "Clear plane") is None  # leaves the module's scene as it was


def test_a_tab_gets_its_plane_contour_and_undo_back_after_a_restart(app, cache_root):
    """Issue 50, item 5: after a kill -9 and a restart the open tab fell back to plane 1 and lost
    its unfinished contour and its undo history (they were in memory only). They are written
    into the session folder (``tabs.json``, atomically) with every change; here a second server
    opens the folder while the first still runs, as a kill -9 leaves it."""
    core = app.core
    cs = core.new_client_state(11)
    assert app.imaging.show(cs, 1)
    for col, row in ((50, 200), (80, 200), (80, 230)):
        assert app.drawing.click(cs, col, row, "PV contour") is None
    assert app.drawing.command(cs, "Close") is None
    for col, row in ((150, 200), (180, 200)):
        assert app.drawing.click(cs, col, row, "HV contour") is None
    again = start_app(SCENE, cache_root, core.session.folder)
    try:
        back = again.core.new_client_state(12)
        assert again.core.resume(back, cs.token) is None  # the page names the tab it was
        assert back.plane == 1 and back.feature == "HV contour"
        assert back.drawing is not None and back.drawing.vertices == [(150, 200), (180, 200)]
        assert again.drawing.click(back, 180, 230) is None and back.drawing.vertices[-1] == (180, 230)
        assert len([c for c in again.core.session.contours if c.plane == 1]) == 2  # continued, not a third
        for _ in range(4):  # the new vertex, the two before the restart, then the close
            assert again.drawing.command(back, "Undo") is None
        pv = next(c for c in again.core.session.contours if c.feature == "portal_contour" and c.plane == 1)
        assert not pv.closed and pv.vertices == [(50, 200), (80, 200), (80, 230)]
    finally:
        stop_app(again)
    assert app.drawing.command(cs, "Clear plane") is None  # leaves the module's scene as it was


def test_a_sweep_is_logged_before_it_is_seen_over(app):
    """CI: the guide's next run was logged before the sweep's points, which were written just
    after the sweep reported itself over. A slow log line makes that order certain."""
    core = app.core
    cs = core.new_client_state(5)
    with core.lock:
        core.session.stylus_count = 0
    log = core.actions
    append = log.append

    def slow_points(tab, role, act, detail=""):
        if act is Act.POINTS:
            time.sleep(0.5)
        append(tab, role, act, detail)

    log.append = slow_points
    try:
        n = len(log.entries())
        assert app.stylus.start(lambda: 100.0, cs)
        wait(lambda: not app.stylus.sweeping and core.session.stylus_count >= len(core.sd.stylus_path), "sweep")
        assert [e.act for e in log.entries()[n:]] == [Act.SWEEP, Act.POINTS]
    finally:
        log.append = append

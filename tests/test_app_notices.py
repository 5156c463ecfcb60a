"""What the viewer says after a deformable run whose answer is its rigid pose (issue 22,
"never silent", walked in Chromium on the held-out tool case tooltest2-a): the red box over
the 3D view was the whole warning text, clipped at 200 px with its title and both ends
hidden, and one more box piled up per run; the panel and the run table called the answer
"deformable" while the pose alone was on show."""

import types

import numpy as np
from test_local_loads import _dented_scan

from navapp.app.panels import ClientView
from navapp.app.panels.registration import POSE_ONLY, RegistrationPanel
from navapp.app.runs import fit_notice
from navapp.app.state import RegisteredState, Run, RunEntry, RunKind
from navapp.fitwarning import FitWarning, WarningKind


def test_a_deformable_run_answered_with_its_pose_says_so_in_a_short_box(small_model, phantoms):
    from navapp.registration.pipeline import register

    data, _ = _dented_scan(phantoms[0].liver.vertices, small_model, 30.0, 15.0, far_mm=50.0)
    reg = register(small_model, data)
    assert not reg.deformed and reg.warnings  # the pose alone, warned (test_local_loads)
    entry = RunEntry.of(RunKind.SURFACE, reg, len(data["anterior"]), 1.0)
    assert entry.pose_only and RunEntry.from_json(entry.to_json()).pose_only
    assert not RunEntry.of(RunKind.RIGID, reg, 10, 1.0).pose_only  # a rigid run asked for no deformation

    notice = fit_notice(reg.warnings, entry.pose_only)
    whole = "; ".join(w.text for w in reg.warnings)
    assert notice.startswith("⚠ ") and "; deformation not determined by the data." in notice, notice
    assert "Shown: the pose alone" in notice and len(notice) < 300 < len(whole), (notice, whole)

    # the panel: the last run and the result on show name the pose alone
    result = RegisteredState(entry.run, reg.rigid, None)
    core = types.SimpleNamespace(session=types.SimpleNamespace(log=[entry]), result=result, shown_runs={})
    panel = types.SimpleNamespace(core=core, md=types.SimpleNamespace(content=""), _stated_supports=lambda: None)
    RegistrationPanel._summary(panel)
    assert panel.md.content.count(POSE_ONLY) == 2 and whole in panel.md.content, panel.md.content


def test_the_next_red_box_of_a_kind_replaces_the_last():
    shown = []

    class Box:
        def __init__(self, title, body):
            self.title, self.body = title, body
            shown.append(self)

        def remove(self):
            shown.remove(self)

    client = types.SimpleNamespace(add_notification=lambda title, body, **kw: Box(title, body))
    view = types.SimpleNamespace(client=client, _errors={})
    for i in range(3):
        ClientView.notify(view, "Registration: check the fit", f"run {i}", error=True)
    ClientView.notify(view, "On show", "That run's result is not kept", error=True)
    ClientView.notify(view, "Registration", "Cancelled: the previous result is kept.")
    assert [(b.title, b.body) for b in shown] == [("Registration: check the fit", "run 2"),
                                                   ("On show", "That run's result is not kept"),
                                                   ("Registration", "Cancelled: the previous result is kept.")]


def test_the_last_run_and_the_result_on_show_read_the_same_mean_error():
    """The same result read "mean error 3.92 mm" in "Last" and "3.91" in "On show" (walking the
    demo): the run table keeps 0.001 mm, and the one line formatted the unrounded mean."""
    from navapp.registration.rigid import RigidResult

    err = np.array([3.91496, 3.91496])
    rigid = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
    entry = RunEntry(RunKind.ALL.label, 100, 1.0, 3, "converged", 0, False, [], None)
    entry.error_mean_mm, entry.error_max_mm = round(float(err.mean()), 3), round(float(err.max()), 3)
    result = RegisteredState(entry.run, rigid, np.zeros(3), err)
    core = types.SimpleNamespace(session=types.SimpleNamespace(log=[entry]), result=result, shown_runs={})
    panel = types.SimpleNamespace(core=core, md=types.SimpleNamespace(content=""), _stated_supports=lambda: None)
    RegistrationPanel._summary(panel)
    assert "mean error 3.92 mm, max" in panel.md.content and "(mean error 3.92 mm)" in panel.md.content, \
        panel.md.content


def test_the_on_show_dropdown_is_held_while_a_run_goes_and_says_nothing_unasked():
    """A tab reloaded during a registration got a red "On show — A registration is already
    running" though nobody touched the dropdown: the browser settling its value reached
    ``show``. While a run (or the sweep) goes the dropdown is disabled, and a value arriving
    then is put back quietly."""
    from navapp.registration.rigid import RigidResult

    rigid = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
    entries = [RunEntry(RunKind.ALL.label, 100, 1.0, 3, "converged", 0, False, [], None) for _ in range(2)]
    first, second = (RegisteredState(e.run, rigid, np.zeros(3)) for e in entries)
    asked, said = [], []
    core = types.SimpleNamespace(session=types.SimpleNamespace(log=entries), result=second,
                                 shown_runs={0: (first, None, []), 1: (second, None, [])},
                                 run=Run(RunKind.ALL, 100, 0.0), sweeping=False)
    dropdown = types.SimpleNamespace(options=(), value=None, disabled=False)
    panel = types.SimpleNamespace(core=core, on_show=dropdown, _choices={},
                                  app=types.SimpleNamespace(runs=types.SimpleNamespace(
                                      show=lambda row, cs=None: asked.append(row))),
                                  view=types.SimpleNamespace(notify=lambda *a, **k: said.append(a), cs=None))
    panel._on_show = lambda: RegistrationPanel._on_show(panel)
    panel._on_show()
    assert dropdown.disabled and dropdown.value.startswith("2.")
    dropdown.value = dropdown.options[0]  # the browser's value, not the surgeon's
    RegistrationPanel.show(panel)
    assert not asked and not said and dropdown.value.startswith("2.")
    core.run = None
    panel._on_show()
    assert not dropdown.disabled
    dropdown.value = dropdown.options[0]  # idle: a pick is carried out
    RegistrationPanel.show(panel)
    assert asked == [0]


def test_a_tab_that_connects_while_the_server_loads_is_placed_when_the_model_is_ready(monkeypatch):
    """After a restart, two tabs that reconnected before the session was loaded went from step
    9 of the guide to step 1 (a reload kept it): a new tab's step is chosen again once the
    model is ready, unless the surgeon has moved it meanwhile."""
    import navapp.app.panels.guide as guide_panel
    from navapp.app.panels.guide import GuidePanel

    step = types.SimpleNamespace(title="t", text="", button="b", done=None, blocked=lambda app, cs: None)
    monkeypatch.setattr(guide_panel, "STEPS", (step,) * 9)
    core = types.SimpleNamespace(worker=None)
    monkeypatch.setattr(guide_panel, "first_open_step", lambda app, cs: 8 if core.worker is not None else 0)

    def panel():
        p = object.__new__(GuidePanel)
        p.app, p.cs = types.SimpleNamespace(core=core), types.SimpleNamespace(guide_step=0)
        p.md, p.btn, p.why, p.extra = (types.SimpleNamespace(content="", label="", disabled=False) for _ in range(4))
        p._placing = True
        p._place()
        return p

    early, moved = panel(), panel()
    assert early.cs.guide_step == moved.cs.guide_step == 0
    moved.move(1)  # the surgeon's own step
    core.worker = object()  # the model is ready, the stored result restored
    for p in (early, moved):
        p.refresh(None)
    assert early.cs.guide_step == 8 and "Step 9 of 9" in early.md.content
    assert moved.cs.guide_step == 1
    late = panel()
    assert late.cs.guide_step == 8 and not late._placing


def test_a_result_restored_after_a_restart_is_named_in_the_on_show_dropdown():
    """After a restart the dropdown read "—" beside "On show: deformable, all data (warm)": the
    runs before the restart are not kept, so the restored result had no row."""
    from navapp.registration.rigid import RigidResult

    rigid = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
    restored = RegisteredState("deformable, all data (warm)", rigid, np.zeros(3), restored=True)
    core = types.SimpleNamespace(session=types.SimpleNamespace(log=[]), result=restored, shown_runs={}, run=None,
                                 sweeping=False)
    dropdown = types.SimpleNamespace(options=(), value=None, disabled=False)
    panel = types.SimpleNamespace(core=core, on_show=dropdown, _choices={})
    RegistrationPanel._on_show(panel)
    assert dropdown.value == "deformable, all data (warm) (restored after a restart)" == dropdown.options[0]
    core.result = None
    RegistrationPanel._on_show(panel)
    assert dropdown.value == "—"


def test_the_error_curve_is_the_run_on_show():
    """With a rigid result picked under On show, the plot still drew the last deformable run's
    error against time (walking the demo)."""
    from navapp.registration.rigid import RigidResult

    rigid = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
    entries = [RunEntry(label, 100, 1.0, 3, "converged", 0, False, trace, None)
               for label, trace in ((RunKind.RIGID.label, []), (RunKind.ALL.label, [(0.0, 6.0), (0.5, 3.0)]))]
    states = [RegisteredState(e.run, rigid, None if i == 0 else np.zeros(3)) for i, e in enumerate(entries)]
    core = types.SimpleNamespace(session=types.SimpleNamespace(log=entries), result=states[1],
                                 shown_runs={0: (states[0], None, []), 1: (states[1], None, [])})
    panel = types.SimpleNamespace(core=core, plot=types.SimpleNamespace(data=None))
    RegistrationPanel._plot_shown(panel)
    assert list(panel.plot.data[1]) == [6.0, 3.0]
    core.result = states[0]
    RegistrationPanel._plot_shown(panel)
    assert list(panel.plot.data[1]) == [0.0]


def test_a_clean_run_takes_down_the_red_box_of_a_warned_one():
    """Issue 50, item 3: "Registration: check the fit … 1 data point was left out" stayed over the
    3D view after a clean re-run whose row had no ⚠."""
    from navapp.app.core import Core
    from navapp.app.runs import CHECK_THE_FIT, tell

    shown = []

    class Box:
        def __init__(self, title, body, **kw):
            self.title, self.body, self.red = title, body, kw.get("color") == "red"
            shown.append(self)

        def remove(self):
            shown.remove(self)

    view = ClientView.__new__(ClientView)
    view.client, view._errors = types.SimpleNamespace(add_notification=Box), {}
    core = Core.__new__(Core)
    core.each_view = lambda fn: fn(view)
    warned = types.SimpleNamespace(cancelled=False, warning="poor fit: posterior 6.1 mm RMS", pose_only=False)
    clean = types.SimpleNamespace(cancelled=False, warning=None, pose_only=False)
    tell(core, warned, [], [FitWarning(WarningKind.POOR_FIT, "poor fit: posterior 6.1 mm RMS (expected ≤ 3.0)")], [])
    assert [b.title for b in shown if b.red] == [CHECK_THE_FIT]
    tell(core, types.SimpleNamespace(cancelled=True), [], [], [])  # the warned result stays on show
    assert [b.title for b in shown if b.red] == [CHECK_THE_FIT]
    tell(core, clean, [], [], [])
    assert not [b for b in shown if b.red], [(b.title, b.body) for b in shown]


def test_the_stylus_distances_go_with_the_stylus():
    """Walking the demo in Chromium: when the sweep ended the stylus was no longer drawn, but
    "tumour1: 87.2 mm from the stylus tip" stayed in the Stylus panel (a tab opened since
    showed no distance at all)."""
    from navapp.app.panels.stylus import StylusPanel

    panel = StylusPanel.__new__(StylusPanel)
    panel.btn, panel.dist = types.SimpleNamespace(label=""), types.SimpleNamespace(content="")
    panel.app = types.SimpleNamespace(shown=types.SimpleNamespace(
        target_distance_lines=lambda tip: ["**tumour1**: 87.2 mm from the stylus tip"]))
    panel.show_tip(np.zeros(3))
    assert "87.2 mm from the stylus tip" in panel.dist.content and panel.btn.label == "Stop digitising"
    panel.show_tip(None)  # the sweep is over: the tool is gone, and its distances with it
    assert panel.dist.content == "" and panel.btn.label == "Digitise the anterior surface"


def test_a_tab_open_during_start_up_loses_its_progress_bar_when_ready(cache_root, tmp_path):
    """A tab open while the server started (a reload across a restart) kept the progress bar,
    full, under "Ready." for good: the status was sent before start-up counted as over."""
    import threading
    import time

    from conftest import free_port, stop_app
    from test_app_server import SCENE

    from navapp.app.server import App
    from navapp.app.state import Change
    from navapp.simulation.scene import parse_scene

    app = App(parse_scene(SCENE), port=free_port(), session_dir=tmp_path / "session", edge=12.0, k=12,
              cache_root=cache_root)
    view = ClientView.__new__(ClientView)
    view.core, view.lock = app.core, threading.RLock()
    view.status = types.SimpleNamespace(content="")
    view.bar = types.SimpleNamespace(visible=True, animated=True, value=0.0)
    view.refresh = lambda what: ClientView._refresh(view, what) if what is Change.STATUS else None
    app.core.views[-1] = view  # connected before start-up
    try:
        assert app.start().wait(600) and app.core.failed is None
        end = time.monotonic() + 10.0
        while view.bar.visible and time.monotonic() < end:
            time.sleep(0.05)
        assert view.status.content.startswith("**Ready.") and not view.bar.visible, (view.status, view.bar)
    finally:
        stop_app(app)


def test_the_data_points_are_counted_in_words():
    """The Ultrasound panel read "Data points: anterior 853, falciform 30, portal_centerline 1,
    portal_contour 67, ridge_left 12, ridge_right 98": the program's keys, not words."""
    from navapp.app.palette import data_counts

    data = {k: np.zeros((n, 3)) for k, n in (("ridge_left", 12), ("portal_centerline", 1), ("anterior", 1853),
                                             ("falciform", 30), ("posterior", 0))}
    said = data_counts(data)
    assert said == "anterior surface 1,853, falciform ligament 30, left inferior ridge 12, portal-vein centres 1", said
    assert "_" not in said and data_counts({}) == "none yet"


def test_the_pinned_pose_warning_fits_its_box():
    """Live re-registration on 102 stylus points (Chromium, ``navapp replay``): the pose
    warning pinned over the 3D view held both doubts whole, 420 characters; viser cuts the box
    at 200 px, centred, and the surgeon read its middle, the title "Registered pose not to be
    believed" scrolled out of it. The banner above the panels keeps the whole text."""
    whole = ("the data cover 4 % of the liver surface (within 10 mm), less than the 10 % a pose needs: the pose may "
             "be grossly wrong — do not rely on it; digitise more of the surface; the pose is not determined by the "
             "data: a rotation about left–right axis (tilted, [-0.85, 0.4, 0.35]) leaves every surface distance "
             "unchanged (the data cover too little or too regular a surface) — add data elsewhere")
    pinned = []
    view = ClientView.__new__(ClientView)
    view.core = types.SimpleNamespace(result=types.SimpleNamespace(run="live (every frame)", pose_warning=whole))
    view.pose_alert = types.SimpleNamespace(content="", visible=False)
    view._pinned = {}
    view.client = types.SimpleNamespace(add_notification=lambda title, body, **kw: pinned.append((title, body)) or
                                        types.SimpleNamespace(title=title, body=body))
    view._pose_alert()
    (title, body), = pinned
    assert title.startswith("⚠ Registered pose not to be believed")
    assert len(title) + len(body) <= 280 and body.startswith("the data cover 4 % of the liver surface"), body
    assert "at the top of the panel" in body
    assert whole in view.pose_alert.content and view.pose_alert.visible  # the banner: every word


def test_a_warned_result_put_back_on_show_says_its_warning():
    """Walking the demo: a deformable run warned "the declared supports are not borne out by
    the data", a rigid run came after it, and the deformable result was put back on show (On
    show): the panel said "Last: rigid …" and "On show: deformable, all data …" with no word of
    that result's warning, a bare ⚠ in its row of the run table."""
    from navapp.registration.rigid import RigidResult

    rigid = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
    warned = RunEntry(RunKind.ALL.label, 100, 1.0, 2, "converged", 0, False, [],
                      "the declared supports are not borne out by the data: check where the organ is held")
    clean = RunEntry(RunKind.RIGID.label, 100, 0.8, 0, "rigid", 0, False, [], None)
    states = [RegisteredState(warned.run, rigid, np.zeros(3)), RegisteredState(clean.run, rigid, None)]
    core = types.SimpleNamespace(session=types.SimpleNamespace(log=[warned, clean]), result=states[1],
                                 shown_runs={0: (states[0], None, []), 1: (states[1], None, [])})
    panel = types.SimpleNamespace(core=core, md=types.SimpleNamespace(content=""), _stated_supports=lambda: None)
    RegistrationPanel._summary(panel)
    assert "⚠" not in panel.md.content, panel.md.content  # the clean rigid result on show
    core.result = states[0]  # the warned one put back on show
    RegistrationPanel._summary(panel)
    on_show = panel.md.content.split("On show:", 1)[1]
    assert "⚠ the declared supports are not borne out by the data" in on_show, panel.md.content


def test_no_worst_point_on_a_pose_not_to_be_believed_is_no_reassurance():
    """In Chromium at 1366 × 768, one plane's wall alone registered rigidly 33.5 mm off under the red
    banner "Registered pose not to be believed", and the panel below said "Worst data points: none
    beyond its noise — every point lies on the model"."""
    from navapp.registration.rigid import RigidResult

    rigid = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
    result = RegisteredState("rigid", rigid, None, pose_warning="the data cover 0 % of the liver surface")
    panel = types.SimpleNamespace(core=types.SimpleNamespace(result=result, worst=[]),
                                  app=types.SimpleNamespace(drawing=types.SimpleNamespace(gone=lambda w: False)),
                                  worst_md=types.SimpleNamespace(content=""), btn_worst=[])
    RegistrationPanel._worst(panel)
    assert "every point lies on the model" not in panel.worst_md.content
    assert "not to be believed" in panel.worst_md.content, panel.worst_md.content
    result.pose_warning = None  # a believable pose: the reassurance holds
    RegistrationPanel._worst(panel)
    assert "every point lies on the model" in panel.worst_md.content


def test_the_worst_points_of_a_rigid_answer_are_said_to_be_mostly_its_deformation():
    """Walking the demo: after a rigid fit, Worst data points listed 7 mm stylus-sweep points
    with "remove a wrong one" — the deformation a rigid fit cannot follow, good data a surgeon
    would be invited to remove. A deformable answer's list keeps the plain invitation."""
    from navapp.app.state import WorstPoint
    from navapp.registration.rigid import RigidResult

    rigid = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
    point = WorstPoint("anterior", 7.1, False, None, (0.0, 0.0, 0.0), "anterior surface, stylus sweep", None)
    result = RegisteredState("rigid", rigid, None)
    panel = types.SimpleNamespace(core=types.SimpleNamespace(result=result, worst=[point]),
                                  app=types.SimpleNamespace(drawing=types.SimpleNamespace(gone=lambda w: False)),
                                  worst_md=types.SimpleNamespace(content=""),
                                  btn_worst=[types.SimpleNamespace(visible=False, disabled=False, label="")])
    RegistrationPanel._worst(panel)
    assert "register deformably before removing any" in panel.worst_md.content, panel.worst_md.content
    assert "remove a wrong one" not in panel.worst_md.content
    result.beta = np.zeros(3)  # a deformable answer: a point still this far off may be a wrong one
    RegistrationPanel._worst(panel)
    assert "remove a wrong one" in panel.worst_md.content and "deformably" not in panel.worst_md.content

"""A gross rigid pose is never accepted silently: data from a small patch (live 'Digitise as:
anterior' for a few seconds) or one plane's wall alone give a pose nobody should believe; the
result on show carries a red pose warning (panel banner), Slicer's NavappStatus carries it, and
neither Re-register nor live re-registration continues from it. Headless, small scene."""

import types

import numpy as np
import pytest
from conftest import run_to_end, start_app, stop_app

from navapp.app.state import RunKind

SCENE = {"name": "grosspose", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.2}, "ius": {"planes": 4}}


@pytest.fixture(scope="module")
def app(cache_root, tmp_path_factory):
    a = start_app(SCENE, cache_root, tmp_path_factory.mktemp("sess"))
    yield a
    stop_app(a)


def only(app, live_points=(), planes=()):
    session = app.core.session
    session.stylus_count, session.contours = 0, []
    session.live_points = [[*map(float, p), "anterior"] for p in live_points]
    session.planes_added = list(planes)
    app.core.changed()


def test_a_patch_or_one_wall_gives_a_red_pose_warning_and_is_not_continued(app):
    from navapp.tracking.results import status_line

    sd = app.core.sd
    ant = sd.stylus_path[sd.stylus_labels == "anterior"]
    patch = ant[np.argsort(np.linalg.norm(ant - ant[0], axis=1))[:40]]  # a few seconds of digitising
    only(app, live_points=patch)
    entry = run_to_end(app, RunKind.RIGID)
    res = app.core.result
    assert res.pose_warning and "cover" in res.pose_warning, res.pose_warning
    assert "cover" in entry.warning and "cover" in status_line(app.core.last_reg)
    assert "pose not" in status_line(app.core.last_reg) or "cover" in status_line(app.core.last_reg)

    # one plane's posterior wall alone: the determinacy check sees no stylus data, coverage does
    wall = next(i for i, p in sorted(app.core.planes.items()) if len(p.features.get("posterior", ())) > 20)
    only(app, planes=[wall])
    run_to_end(app, RunKind.RIGID)
    assert app.core.result.pose_warning and "cover" in app.core.result.pose_warning
    # the tumours' distances from the image say it too (Chromium at 1366 × 768: "tumour1 (registered):
    # in this image", nothing beside it, under the red banner; a rigid answer has no band to say it)
    lines = app.shown.target_plane_lines(wall)
    assert lines and all(line.endswith("; ⚠ pose not to be believed") for line in lines), lines
    saved = app.core.session.result
    assert saved["pose_warning"] == app.core.result.pose_warning  # a restart shows it again

    # Re-register does not continue from it: a fresh fit on all data
    entry = run_to_end(app, RunKind.WARM)
    assert entry.run == RunKind.ALL.label

    # live re-registration starts afresh too
    from navapp.app.live import LiveFollower

    link = types.SimpleNamespace(live=app.live, core=app.core)
    follower = LiveFollower(link)
    follower._base()
    assert follower.reg is not None and follower.reg.last is None

    # with the whole sweep the pose is believed again, and a warm start continues
    only(app)
    app.stylus.collect_now()
    run_to_end(app, RunKind.ALL)
    assert app.core.result.pose_warning is None
    follower = LiveFollower(link)
    follower._base()
    assert follower.reg.last is app.core.last_reg
    assert run_to_end(app, RunKind.WARM).run == RunKind.WARM.label


def test_a_deformable_fit_on_a_pose_nobody_should_believe_gives_no_tumour_figure(app):
    """Issue 50, item 2: on a gross pose the tumour bands read "predicted error 451.6 mm
    (48.6–1696.5)" (here 202 and 31 mm beside true 39 and 133 mm): a figure off by more than
    3× either way. The calibration says nothing at a point whose pose is 100 mm off; the band
    says what to do instead. The same holds of the surface's dots and the organ's line."""
    from navapp.app.shown import NO_TARGET_FIGURE

    sd = app.core.sd
    ant = sd.stylus_path[sd.stylus_labels == "anterior"]
    only(app, live_points=ant[np.argsort(np.linalg.norm(ant - ant[0], axis=1))[:40]])
    run_to_end(app, RunKind.SURFACE)
    res = app.core.result
    assert res.pose_warning and res.target_bands
    for b in res.target_bands:
        assert not np.isfinite(b.predicted_mm) and b.warning.text == NO_TARGET_FIGURE, b
        assert "mm" not in b.text() and "register again" in b.text()
    # nor over the surface, nor over the organ (the demo's 40-point patch: 535 mm predicted over
    # the organ, 15 × its true 35 mm; notes/scripts/predicted_demo.py)
    reg = app.core.last_reg
    assert res.predicted_mm is None
    assert reg.deformed and reg.organ is not None
    assert not any("predicted error over the organ" in w.text for w in reg.warnings), reg.warnings


def test_the_surgeon_states_the_pose_and_a_patch_keeps_it(app, tmp_path):
    """Issue 46, item 1: the viewer lets the surgeon state the pose of the data. A few seconds of
    digitising searched from scratch give a gross pose; stated "as the tracker gives it" (the
    data's frame is the preoperative one here), the same patch keeps the pose; stated "the
    previous registration's", it keeps the pose of the good registration on show. The statement
    is a line of the action log, in session.json and case.toml (``navapp register SESSION`` fits
    as the viewer did), and comes back after a restart."""
    import tomllib

    from navapp.app.session import open_session
    from navapp.app.state import PoseFrame, StatedPose
    from navapp.registration.rigid import RigidResult
    from navapp.registration.rotation import rotation

    sd, core = app.core.sd, app.core
    ant = sd.stylus_path[sd.stylus_labels == "anterior"]
    patch = ant[np.argsort(np.linalg.norm(ant - ant[0], axis=1))[:40]]
    try:
        only(app, live_points=patch)
        searched = run_to_end(app, RunKind.RIGID).error_mean_mm

        said = app.runs.set_pose(StatedPose(PoseFrame.GIVEN, 2.0, 2.0))
        assert said and "tracker" in said and app.runs.set_pose(StatedPose(PoseFrame.GIVEN, 2.0, 2.0)) is None
        assert tomllib.loads((core.session.folder / "case.toml").read_text())["intraop"]["pose"] == {
            "known": True, "sd_mm": 2.0, "sd_deg": 2.0}
        assert "pose of the data stated" in (core.session.folder / "actions.jsonl").read_text()
        given = run_to_end(app, RunKind.RIGID).error_mean_mm
        assert given < 0.25 * searched, (given, searched)

        # the previous registration's pose: the whole sweep in a tracker frame off by 12° / 20 mm,
        # registered (the pose searched), on show; then the patch in that frame
        G = RigidResult(rotation(np.radians([12.0, -5.0, 4.0])), np.array([20.0, -8.0, 6.0]), 0, 0.0)
        app.runs.set_pose(StatedPose())
        n = len(sd.stylus_path)
        core.session.stylus_count, core.session.contours, core.session.planes_added = 0, [], []
        core.session.live_points = [[*map(float, G.apply(x)), str(f)] for x, f in
                                    zip(sd.stylus_path[:n], sd.stylus_labels[:n], strict=True)]
        core.changed()
        run_to_end(app, RunKind.RIGID)
        shown, x = core.result.rigid, core.model.basis.nodes
        only(app, live_points=G.apply(patch))

        def off(kind_of_pose):
            app.runs.set_pose(kind_of_pose)
            run_to_end(app, RunKind.RIGID)
            return np.linalg.norm(core.result.rigid.apply(x) - shown.apply(x), axis=1).mean()

        about_previous = off(StatedPose(PoseFrame.PREVIOUS, 1.0, 1.0))
        about_tracker = off(StatedPose(PoseFrame.GIVEN, 1.0, 1.0))
        assert about_previous < 2.0 < 10.0 < about_tracker, (about_previous, about_tracker)
        assert "intraop" in tomllib.loads((core.session.folder / "case.toml").read_text())
        off(StatedPose(PoseFrame.PREVIOUS, 1.0, 1.0))
        assert "intraop" not in tomllib.loads((core.session.folder / "case.toml").read_text())

        reopened, _ = open_session(core.session.folder, sd)
        assert reopened.pose == StatedPose(PoseFrame.PREVIOUS, 1.0, 1.0)
    finally:
        app.runs.set_pose(StatedPose())
        only(app)


def test_live_following_switched_on_again_registers_at_once(app, monkeypatch):
    """Issue 48: the live follower continues from a believed result on show, so its fit has a
    last state before it has registered anything. When that first update raised (the follower
    switches itself off and says why) and the surgeon switched it on again with the probe held
    still, it waited for a new frame that never came: on, no error, "Not re-registered on live
    frames yet" for good, as CI saw. Driven pass by pass (``_step``), so the order is fixed."""
    from navapp.app.live import LiveFollower
    from navapp.registration.live import LiveRegistration

    only(app)
    app.stylus.collect_now()
    run_to_end(app, RunKind.ALL)
    assert app.core.result.pose_warning is None and app.core.last_reg is not None
    link = types.SimpleNamespace(live=app.live, core=app.core, frame=None)  # a still probe: no frame comes
    follower = LiveFollower(link)  # its thread not started: each pass is called here
    update, calls = LiveRegistration.update, []

    def fails_once(reg, frame, options=None):
        calls.append(frame)
        if len(calls) == 1:
            raise RuntimeError("the first update failed")
        return update(reg, frame, options)

    monkeypatch.setattr(LiveRegistration, "update", fails_once)
    assert follower.set(True) is None
    follower._step()
    assert not follower.on and follower.last_error == "RuntimeError: the first update failed"
    assert follower.summary() == "Stopped: RuntimeError: the first update failed"  # not "Not re-registered…"
    assert follower.reg.last is app.core.last_reg  # continued from the result on show
    assert follower.set(True) is None and follower.summary() == "Not re-registered on live frames yet."
    follower._step()
    assert len(calls) == 2 and follower.frames == 1, follower.summary()
    assert follower.summary().startswith("1 frames re-registered")
    follower._step()  # no new frame: nothing to do until one comes
    assert len(calls) == 2
    assert follower.set(False) is None
    follower._step()  # switched off: converged on the kept data and kept as the result
    assert app.core.result.run == RunKind.LIVE.label and follower.reg.frame is None


def test_a_pose_not_to_be_believed_is_said_once_with_all_its_reasons(app, monkeypatch):
    """CI's small-window browser test: one plane's wall, then Rigid, gave the pinned red banner
    and a second red box "Registration: check the fit" over the liver, because the pose search's
    own line (ICP turned the organ further than a tracker errs) was in the run's warnings but
    not in the pinned one. Which plane's wall did so depended on the plane the tab showed."""
    from navapp.app.runs import CHECK_THE_FIT

    told = []
    monkeypatch.setattr(app.core, "notify", lambda title, body, error=False: told.append(title))
    for plane in sorted(app.core.planes):
        only(app, planes=[plane])
        run_to_end(app, RunKind.RIGID)
        app.core.settle()
        pinned = app.core.result.pose_warning
        assert pinned, plane
        assert all(w.text in pinned for w in app.core.last_reg.warnings), (plane, app.core.last_reg.warnings)
    assert CHECK_THE_FIT not in told, told

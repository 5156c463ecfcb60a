"""The guided demo: the steps a newcomer is walked through. Each step has a short
explanation, one action for its button, a precondition (why the button cannot be pressed
yet, shown instead of letting it do nothing) and a completion test (the guide moves on
only when the step's work is actually done, e.g. the whole sweep digitised). Actions and
tests are functions of the App and the browser's ``ClientState``. No viser here: actions
reach the browser's view through ``core.views``."""

from collections.abc import Callable
from dataclasses import dataclass

from .imaging import FREE_PLANE_BASE
from .state import RunKind


@dataclass(frozen=True)
class Step:
    title: str
    text: str
    button: str
    action: Callable  # (app, cs) -> error message or None
    blocked: Callable = lambda app, cs: None  # (app, cs) -> why the button cannot be pressed yet, or None
    done: Callable | None = None  # (app, cs) -> True once the step's work is complete; None: when the action succeeds


def _view(app, cs):
    return app.core.views.get(cs.client_id)


def _need_scene(app, cs):
    return None if app.core.sd is not None else "Wait: the scene is still being prepared (see the status above)."


def _need_model(app, cs):
    if app.core.worker is None:
        return "Wait: the registration model is still being prepared (see the status above)."
    if app.core.run is not None:
        return "Wait: a registration is running."
    return None


def _need_sweep(app, cs):
    why = _need_model(app, cs)
    if why:
        return why
    sd, session = app.core.need_scene()
    n, total = session.stylus_count, len(sd.stylus_path)
    if n < total:
        return f"Wait: the stylus sweep is at {n} of {total} points."
    return None


def _ran(*kinds: RunKind):
    def done(app, cs):
        log = app.core.session.log if app.core.session else []
        return app.core.run is None and any(e.kind in kinds and not e.cancelled for e in log)
    return done


def _preop(app, cs):
    v = _view(app, cs)
    if v is not None:
        for name in ("Preoperative liver", "Preoperative vessels", "Targets"):
            v.layers.cb[name].value = True
        v.layers.cb["True deformed liver (ghost)"].value = False
        v.layers.apply_visibility()
        v.layers.look("Anterior")


def _truth(app, cs):
    v = _view(app, cs)
    if v is not None:
        v.layers.cb["True deformed liver (ghost)"].value = True
        v.layers.apply_visibility()


def _stylus(app, cs):
    v = _view(app, cs)
    if v is not None:
        v.layers.cb["True deformed liver (ghost)"].value = False
        v.layers.apply_visibility()
    speed = (lambda: float(v.stylus.speed.value)) if v is not None else (lambda: 1.0)
    if not app.stylus.sweeping:
        app.stylus.start(speed, cs)


def _sweep_done(app, cs):
    sd, session = app.core.sd, app.core.session
    return sd is not None and session is not None and session.stylus_count >= len(sd.stylus_path) \
        and not app.stylus.sweeping


def demo_plane(app):
    """The first preset plane that cuts a portal vein branch across (a closed contour to draw)."""
    planes = app.core.planes
    for i in sorted(planes):
        if i < FREE_PLANE_BASE and "portal_centerline" in planes[i].features:
            return i
    return min(planes)


def _plane(app, cs):
    i = demo_plane(app)
    app.imaging.show(cs, i)
    v = _view(app, cs)
    if v is not None:
        v.layers.look_at_plane(app.core.planes[i].probe_to_tracker)
        v.ultrasound.open_2d()


def _draw(app, cs):
    if cs.plane is None:
        app.imaging.show(cs, demo_plane(app))
    app.drawing.command(cs, "Feature", "PV contour")
    v = _view(app, cs)
    if v is not None:
        v.ultrasound.open_2d()


def _drew(app, cs):
    return any(c.closed for c in app.core.need_session().contours)


def _all(app, cs):
    if cs.drawing is not None and len(cs.drawing.vertices) >= 3:
        app.drawing.command(cs, "Close")
    v = _view(app, cs)
    if v is not None:
        v.layers.look("Anterior")
    _, worker = app.core.need_model()
    return app.runs.start(RunKind.WARM if worker.last is not None else RunKind.ALL, cs)


def _compare(app, cs):
    v = _view(app, cs)
    if v is not None:
        v.guide.show_comparison()


STEPS = (
    Step("Preoperative model",
         "The liver segmented from the preoperative CT (semi-transparent), its portal vein (red), hepatic "
         "veins (blue) and the tumours to be resected (purple). Everything the surgeon navigates by lives here.",
         "Show the preoperative model from the front", _preop),
    Step("Intraoperative deformation",
         "In theatre the liver is mobilised and packed: it sags and twists away from its CT shape. "
         "The green ghost is the true deformed liver of this simulated case; the system never sees it.",
         "Show the true deformed liver", _truth, _need_scene),
    Step("Stylus digitisation",
         "A tracked stylus is swept over the exposed anterior surface; every few millimetres its tip "
         "position is recorded. Only about a fifth of the anterior surface is reachable. The guide moves on "
         "when the sweep is complete.",
         "Digitise the anterior surface", _stylus, _need_scene, _sweep_done),
    Step("Rigid registration",
         "First a rigid fit (ICP on the salient features: falciform ligament and inferior ridges). The "
         "error colours show what a rigid fit cannot fix.",
         "Register rigidly", lambda app, cs: app.runs.start(RunKind.RIGID, cs), _need_sweep, _ran(RunKind.RIGID)),
    Step("Deformable registration, surface only",
         "LIBR deforms the model with a linear-elastic basis of boundary modes until it matches the "
         "stylus data, keeping strain energy low. Watch it converge live.",
         "Register deformably (surface data)", lambda app, cs: app.runs.start(RunKind.SURFACE, cs), _need_model,
         _ran(RunKind.SURFACE)),
    Step("An ultrasound plane",
         "A tracked ultrasound probe images the liver's interior. The plane is shown at its tracked pose in "
         "3D, and its image in the 2D view on the left, with the model's portal vein (red), hepatic veins "
         "(blue) and liver boundary cut by the plane: dashed before, solid after registration.",
         "Show plane 1", _plane, _need_scene),
    Step("Draw contours",
         "In the 2D view on the left, choose PV contour, click around the dark portal-vein lumen to place "
         "vertices (click on without waiting: each shows at once, and they reach the server in order, on the "
         "plane they were clicked on), then Close. A contour left unfinished on another plane goes on when "
         "you come back to it. Every click becomes an image pixel and "
         "then a 3D point through the probe's calibration and tracking. The guide moves on once a contour "
         "is closed.",
         "Draw in the 2D view", _draw, _need_scene, _drew),
    Step("Register with ultrasound",
         "Deformable registration with everything: stylus surface, the drawn vessel contours, their "
         "centerline points and the posterior wall. It warm-starts from the last result.",
         # done by either kind: with the earlier steps skipped there is no result to warm-start from
         # and the step runs a fresh fit (waiting for a warm one kept the guide at this step for good)
         "Register deformably (all data)", _all, _need_model, _ran(RunKind.WARM, RunKind.ALL)),
    Step("Compare errors",
         "Each registration's mean and maximum error against the true deformation, and its time.",
         "Show the comparison", _compare, _need_model),
)


def first_open_step(app, cs) -> int:
    """Where a new tab's guide starts: after the last step whose work is already done (a
    session restored with its sweep and runs starts past them), else at the first step."""
    if app.core.session is None:
        return 0
    last = -1
    for i, st in enumerate(STEPS):
        if st.done is not None and st.done(app, cs):
            last = i
    return min(last + 1, len(STEPS) - 1)

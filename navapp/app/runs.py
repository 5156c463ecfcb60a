"""Registration runs in the viewer: starting, streaming, cancelling and finishing one (and
the cost sweep, which uses the same worker). No viser here.

What a run is (``state.RunKind``), the run in progress (``state.Run``) and the row it leaves
in the session's log (``state.RunEntry``) are typed state. The worker thread streams states
into ``Run`` under the shared lock; every view reads the run through ``Core.run``.
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..anatomy.caseio import SUPPORTS_FILE, read_support_points
from ..errors import InputError, NavappError
from ..evaluation.cost import lm_sweep
from ..features import BY_NAME
from ..fitwarning import FitWarning, one_line
from ..mechanics.supports import HeldSupports, Supports
from ..registration.objective import Weights
from ..registration.pipeline import Registration
from ..registration.prior import PosePrior
from ..registration.quality import EXPECTED_NOISE_MM, MARGIN_MM
from ..registration.residuals import point_residual_at, point_residuals
from ..registration.rigid import RigidResult, after, beta_pose
from .actions import Act
from .contours import OriginKind
from .core import Core
from .imaging import FREE_PLANE_BASE, LIVE_PLANE_BASE
from .palette import feature_words
from .shown import Shown
from .slicer import Slicer
from .state import (
    CARRIED,
    Change,
    ClientState,
    PoseFrame,
    RegisteredState,
    Run,
    RunEntry,
    RunKind,
    StatedPose,
    StatedSupports,
    WorstPoint,
    checked_by,
)
from .worker import Update, cancelled, viewer_options

MIN_POINTS = 3  # fewer data points than this fix nothing
WORST_SHOWN = 5  # data points furthest from the registered model, listed for removal
BUSY = "A registration is already running; wait for it or cancel it."
SETTLE_S = 0.8  # a stated supports' model is built once the statement has stood this long (s)


class Runs:
    """Starting, streaming, cancelling and finishing registrations; the cost sweep."""

    def __init__(self, core: Core, shown: Shown, slicer: Slicer, following: Callable[[], bool]):
        self.core, self.shown, self.slicer = core, shown, slicer
        self.following = following  # live re-registration is on (``live.Live.following``)
        self._starting = threading.Lock()  # a start and a cancel click are handled one after the other
        self._orders = ThreadPoolExecutor(max_workers=1, thread_name_prefix="navapp-orders")
        self._loaded_points: tuple | None = None  # the support points loaded last (a file uploaded)

    def order(self, action: Callable[[], object]) -> None:
        """Run a button's request (start, Cancel, sweep) after every request clicked before it.
        viser runs plain callbacks in a pool of threads, so a Cancel clicked right after a start
        was handled first, found nothing running, and the run went on (CI's browser test: 3 of 3
        runs); the panels call this from coroutine callbacks, which viser runs as the clicks
        arrive, and one thread runs the requests in that order."""
        def run():
            try:
                action()
            except Exception as exc:  # a request's bug is said, not lost in the pool
                self.core.notify("Registration", f"{exc.__class__.__name__}: {exc}", error=True)

        self._orders.submit(run)

    def start(self, kind: RunKind, cs: ClientState | None = None) -> str | None:
        """Start a registration, an action of ``cs``; returns why it could not start, or None."""
        core = self.core
        worker = core.worker
        if worker is None:
            return "Still preparing the registration model."
        left_out: list = []
        data, origins = core.data_with_origins(surface_only=kind is RunKind.SURFACE, left_out=left_out)
        npts = sum(len(v) for v in data.values())
        if npts < MIN_POINTS:
            return "Collect data first (stylus sweep or an ultrasound plane)."
        if worker.busy:
            return BUSY
        if self.following():
            return "Live re-registration is on (Live tracking panel): switch it off first."
        if kind is RunKind.WARM and worker.last is None:
            kind = RunKind.ALL
        doubt = core.result.pose_warning if core.result is not None else None
        if kind is RunKind.WARM and doubt:
            # never continue from a pose nobody should believe: a fresh fit chooses its own
            kind = RunKind.ALL
            core.notify("Registration", "Not continued from the result on show (its pose is not to be believed): "
                        "a fresh registration on all data instead.", error=True)
        model, waiting = self._model(kind)
        if model is None:
            return waiting
        prior, given = self._pose(kind)
        with self._starting:
            with core.lock:
                core.run = Run(kind, npts, time.monotonic(), data=data, origins=origins, left_out=left_out,
                               model=model)
            if not worker.start(data, deform=kind.deformable, warm=kind is RunKind.WARM, pose_prior=prior, model=model,
                                given=given):
                with core.lock:
                    core.run = None
                return BUSY
        core.changed(Change.RUN)
        core.record(cs, Act.RUN, f"{kind.label}, {npts} points")
        return None

    def _model(self, kind: RunKind):
        """The model a run of ``kind`` fits: a warm start's is the one its result is in, a fresh
        run's is held at the stated supports. (None, why) while that one is still being built."""
        core = self.core
        worker = core.worker
        if kind is RunKind.WARM and worker is not None and worker.last is not None:
            return worker.last.model, None
        with core.lock:
            sd, session = core.need_scene()
            held = session.stated_supports(sd).held
        model = core.model_for(held)
        if model is None:
            return None, (f"The registration model {StatedSupports(held).words()} is still being prepared "
                          "(a basis takes about as long as the first start's); try again in a moment.")
        return model, None

    def set_supports(self, stated: StatedSupports, cs: ClientState | None = None) -> str | None:
        """State where the organ is held for the runs to come, an action of ``cs``: the model
        held there is built in the background (its basis from the cache where it was made
        before). Returns what changed in words, or None where nothing did."""
        if not self._state(stated, Act.SUPPORTS, cs):
            return None
        if not self.prepare_held():
            return f"Organ {stated.words()}. It applies from the next fresh registration."
        return (f"Organ {stated.words()}: its model is being prepared (about as long as the first start's "
                "basis); the next fresh registration uses it.")

    def support_points(self) -> tuple | None:
        """The points a statement "held at points" takes: the stated ones, else the file loaded
        last, else the case's own preop/supports.csv; None where there are none."""
        core = self.core
        with core.lock:
            sd, session = core.need_scene()
            held = session.stated_supports(sd).held
            own = sd.case.preop.support_points
        if held is not None and held.held is Supports.POINTS:
            return held.points
        if self._loaded_points is not None:
            return self._loaded_points
        return None if own is None or not len(own) else tuple(tuple(float(c) for c in p) for p in own)

    def load_support_points(self, name: str, content: bytes, stiffness: float | None,
                            cs: ClientState | None = None) -> tuple[str, bool]:
        """A support-points file (``name``, its bytes: x,y,z rows, mm, preoperative frame, as a
        case's preop/supports.csv) read and checked as the command line reads that file, then
        stated: the organ held at them, firmly or on springs of ``stiffness`` Pa/mm. Returns
        (what happened in words, whether it is an error)."""
        core = self.core
        shown = Path(name).name or SUPPORTS_FILE
        with tempfile.TemporaryDirectory(prefix="navapp-supports-") as tmp:
            path = Path(tmp) / shown
            path.write_bytes(content)
            try:
                points = read_support_points(path, core.preop.liver)
            except InputError as exc:
                return str(exc).replace(str(path), shown), True
        held = HeldSupports.parse(Supports.POINTS.value, stiffness=stiffness, points=points)
        self._loaded_points = held.points
        said = self.set_supports(StatedSupports(held), cs) or f"Organ {StatedSupports(held).words()}."
        return f"{len(held.points)} support points read from {shown}. {said}", False

    def prepare_held(self) -> bool:
        """Build the model held at the stated supports in the background, if it is not built;
        returns whether it began. Said in a notice when it is ready or has failed. A statement
        made over again within ``SETTLE_S`` (a stiffness typed digit by digit) builds only the
        last one's."""
        core = self.core
        with core.lock:
            sd, session = core.need_scene()
            stated = session.stated_supports(sd)
        held = stated.held
        if held is None or core.model is None or core.model_for(held) is not None:
            return False

        def build():
            time.sleep(SETTLE_S)
            with core.lock:
                if session.stated_supports(sd).held != held:
                    return  # stated otherwise since: that statement builds its own
            t0 = time.monotonic()
            try:
                core.build_held(held)
            except Exception as exc:  # said, never a dead thread
                core.notify("Supports", f"The model {stated.words()} could not be built: {exc}", error=True)
                return
            core.notify("Supports", f"The model {stated.words()} is ready ({time.monotonic() - t0:.0f} s); "
                        "the next fresh registration uses it.")
            core.changed(Change.POSE)

        threading.Thread(target=build, daemon=True, name="navapp-held-model").start()
        return True

    def _pose(self, kind: RunKind) -> tuple[PosePrior | None, RigidResult | None]:
        """The pose prior a run of ``kind`` starts with, and the pose it is about (None: the data's
        own frame), from what the surgeon stated (``Session.stated_pose``). The previous
        registration's pose is the one on show, unless nobody should believe it: then the pose is
        searched, and the surgeon told."""
        core = self.core
        with core.lock:
            sd, session = core.need_scene()
            model, _ = core.need_model()
            stated, shown = session.stated_pose(sd), core.result
        if stated.frame is not PoseFrame.PREVIOUS or kind is RunKind.WARM:
            return stated.prior(), None
        if shown is None or shown.pose_warning:
            core.notify("Registration", "The pose of the data is searched for this run: "
                        + ("no registration is on show yet to take it from." if shown is None else
                           "the registration on show has a pose not to be believed."))
            return None, None
        # its whole pose: the rigid stage and LM's own τ, θ (the displacement left out)
        whole = shown.rigid if shown.beta is None else after(shown.rigid, beta_pose(shown.beta, model.centroid))
        return stated.prior(), whole

    def _state(self, stated: StatedPose | StatedSupports, act: Act, cs: ClientState | None) -> bool:
        """The session's statement of the pose or of the supports made ``stated``, an action of
        ``cs``; False where it already was (a tab's own refresh)."""
        core = self.core
        with core.lock:
            sd, session = core.need_scene()
            if isinstance(stated, StatedPose):
                if stated == session.stated_pose(sd):
                    return False
                session.pose = stated
            else:
                if stated == session.stated_supports(sd):
                    return False
                session.supports = stated
        core.changed(Change.POSE)
        core.record(cs, act, stated.words())
        return True

    def set_pose(self, stated: StatedPose, cs: ClientState | None = None) -> str | None:
        """State the pose of the data for the runs to come, an action of ``cs``; returns what
        changed in words, or None where nothing did (a tab's own refresh)."""
        if not self._state(stated, Act.POSE, cs):
            return None
        return f"Pose of the data: {stated.words()}. It applies from the next fresh registration."

    def cancel(self, cs: ClientState | None = None) -> str:
        """Stop the registration or the sweep in progress at its next iteration (or setting);
        returns what happened, in words for the surgeon.

        Cancel is never disabled while the model is ready: its enabled state would reach the
        browser a server round trip after the run started, which under load was after a
        seconds-long run had ended (it could not be clicked at all). A click that finds
        nothing running says so instead."""
        core = self.core
        worker = core.worker
        if worker is None:
            return "Nothing to cancel: the registration model is still being prepared."
        with self._starting:  # a click handled before the start it followed has run (callbacks run in a pool)
            if not worker.busy:
                return "Nothing to cancel: no registration is running."
            run, sweeping = core.run, core.sweeping
            if not worker.cancel():
                if run is not None and run.kind is RunKind.RIGID:
                    return "A rigid registration is not cancelled: it takes about a second, and its result is shown."
                return "Too late to cancel: the run had finished; its result is on show."
        core.record(cs, Act.CANCEL, "the accuracy sweep" if sweeping else run.kind.label if run is not None else "")
        if sweeping:  # no result is at stake: the sweep's rows so far stay in its table
            return "Cancelling the accuracy sweep: it stops after the setting it is running."
        return "Cancelling: the run stops at its next iteration; the previous result is kept."

    # ------------------------------------------------------------------ from the worker thread
    def on_update(self, u: Update):
        core, shown = self.core, self.shown
        rigid = u.rigid
        assert rigid is not None  # every streamed state has its rigid pose
        err = shown.node_error(rigid, u.beta, u.model)
        with core.lock:
            run = core.run
            if run is None:
                return
            run.streamed += 1
            run.iteration, run.omega = u.iteration, u.omega
            if err is not None:
                run.trace.append((u.elapsed, float(err.mean())))
                run.error = err
            run.state = (rigid, u.beta)
            run.model = u.model or run.model
        geom = shown.geometry(rigid, u.beta, surfaces={"liver": u.liver, **(u.vessels or {})}, model=u.model)
        core.each_view(lambda v: v.show_update(u, geom))

    def on_done(self, reg: Registration):
        core, shown = self.core, self.shown
        with core.lock:
            run = core.run
        assert run is not None  # set before the worker started
        stopped = cancelled(reg)
        # the answer: the rigid pose alone where the data do not support the deformation
        beta = reg.libr.beta if reg.libr is not None and reg.deformed else None
        err = None if stopped else shown.node_error(reg.rigid, beta, reg.model)
        checked = checked_by(core.result, reg, warm=run.kind is RunKind.WARM)
        reg.carry(checked, CARRIED)  # before anything shows its warnings: the row, the red box, Slicer
        entry = RunEntry.of(run.kind, reg, run.points, time.monotonic() - run.t0, err, run.streamed, run.trace)
        worst: list[WorstPoint] = []
        n_out = (0, 0)
        if not stopped:
            entry.targets_mm = shown.target_errors(reg.rigid, beta, reg.model)
            result = RegisteredState(run.kind.label, reg.rigid, beta, err, *shown.predict(reg, checked),
                                     data_model_frame=reg.data_model_frame, pose_warning=one_line(reg.pose_doubts),
                                     checked=checked, model=self.core.kept_model(reg.model))
            residuals = point_residuals(reg, viewer_options().weights)
            worst = worst_points(reg, run.data, run.origins, viewer_options().weights, left_out=run.left_out,
                                 residuals=residuals)
            n_out = (sum(p.rejected for p in residuals) + len(run.left_out), len(residuals) + len(run.left_out))
            with core.lock:
                core.result, core.last_reg, core.worst = result, reg, worst
                core.need_session().result = result.to_json()
        with core.lock:
            log = core.need_session().log
            log.append(entry)
            if not stopped:
                core.shown_runs[len(log) - 1] = (result, reg, worst)
            core.run = None
        core.changed(Change.RESULT)
        core.record(None, Act.FINISHED, f"row {len(log)}: {run.kind.label}" + (
            ", cancelled" if stopped else f", mean error {entry.error_mean_mm:.2f} mm"
            if entry.error_mean_mm is not None else ""))
        if not stopped:
            self._send(reg, f"row {len(log)}")
        tell(core, entry, [] if stopped else reg.pose_doubts, reg.warnings, worst, n_out)

    def _send(self, reg: Registration, what: str):
        if self.slicer.sender is not None:
            self.slicer.send(reg)
            self.core.record(None, Act.SLICER, what + (f" (failed: {self.slicer.error})" if self.slicer.error else ""))

    def show(self, row: int, cs: ClientState | None = None) -> str | None:
        """Put the result of run ``row`` (its index in the session's log) back on show — after a
        Rigid press replaced a good deformable result, say; Export, Slicer, a warm start and the
        error colours then use it. Returns why it cannot, or None."""
        core, worker = self.core, self.core.worker
        if core.run is not None or worker is None or worker.busy:
            return BUSY
        with core.lock:
            kept = core.shown_runs.get(row)
            if kept is None:
                return "That run's result is not kept (cancelled, or from before a restart)."
            result, reg, worst = kept
            core.result, core.last_reg, core.worst = result, reg, worst
            worker.last = reg
            core.need_session().result = result.to_json()
        core.changed(Change.RESULT)
        core.record(cs, Act.CHOSEN, f"row {row + 1}: {result.run}")
        self._send(reg, f"row {row + 1}")
        return None

    def restore_worst(self) -> None:
        """The worst data points of the result restored after a restart (``Shown.restore``),
        from the data it was fitted to. Only where the session's data are still those, point
        for point (the fit's own, stored in the model frame): a list from other data would
        name the wrong points. Otherwise the list is unknown (None), and the panel says so
        rather than "none beyond its noise" (said after a restart walking the demo, with
        3.9 mm points listed before it)."""
        core = self.core
        reg = core.last_reg
        with core.lock:
            if reg is None or core.result is None or core.worst:
                return
            core.worst = None
        fitted = {k: v for k, v in reg.data_model_frame.items() if len(v)}
        if not fitted:
            return
        for surface_only in (False, True):  # the session keeps the fit's data to 0.1 µm: compared to 1 µm
            left_out: list = []
            data, origins = core.data_with_origins(surface_only=surface_only, left_out=left_out)
            now = {k: reg.rigid.inverse(v) for k, v in data.items() if len(v)}
            if set(now) == set(fitted) and all(now[k].shape == fitted[k].shape
                                               and np.allclose(now[k], fitted[k], atol=1e-3) for k in now):
                worst = worst_points(reg, data, origins, viewer_options().weights, left_out=left_out)
                with core.lock:
                    if core.last_reg is reg:
                        core.worst = worst
                core.changed(Change.RESULT)
                return

    def on_error(self, exc: BaseException):
        msg = str(exc) if isinstance(exc, NavappError) else f"{exc.__class__.__name__}: {exc}"
        if not isinstance(exc, NavappError):  # a bug: the surgeon reads one line, the server's log the traceback
            traceback.print_exception(exc, file=sys.stderr)
        core = self.core
        with core.lock:
            core.run = None
        core.notify("Registration failed", msg, error=True)
        core.changed(Change.RUN)
        core.record(None, Act.FINISHED, f"failed: {msg}")

    # ------------------------------------------------------------------ cost sweep
    def sweep(self, on_row=None, on_done=None, cs: ClientState | None = None) -> str | None:
        """Rerun the current data with the LM iteration cap and tolerance varied (``evaluation.cost``)."""
        core = self.core
        model, worker, truth = core.model, core.worker, core.truth_nodes
        if model is None or worker is None or truth is None:
            return "This panel needs the true deformation (simulated scenes)."
        data = core.data()
        if sum(len(v) for v in data.values()) < MIN_POINTS:
            return "Collect data first."
        import scipy.sparse as sp

        x0 = model.basis.nodes
        B = sp.identity(len(x0), format="csr")  # the truth is known at the mesh nodes themselves
        if core.run is not None or worker.busy:
            return BUSY

        def over():
            with core.lock:
                core.sweeping = False
            core.changed(Change.RUN)

        def finished(rows):
            over()
            if on_done is not None:
                on_done(rows)

        with self._starting:
            with core.lock:
                core.sweeping = True
            # the viewer's own fit (robust weights): its 100-iteration row read 3.98 mm beside the
            # run table's 3.92 for the same data, fitted without them
            ok = worker.submit(lambda cancel: lm_sweep(model, data, x0, truth, cancel=cancel, on_row=on_row, B=B,
                                                       base=viewer_options()),
                               finished, on_error=lambda exc: over())
            if not ok:
                with core.lock:
                    core.sweeping = False
                return BUSY
        core.changed(Change.RUN)
        core.record(cs, Act.ACCURACY, f"{sum(len(v) for v in data.values())} points")
        return None


CHECK_THE_FIT = "Registration: check the fit"  # the red box's title after a run that warned


def tell(core: Core, entry: RunEntry, pinned: list[FitWarning], warnings: list[FitWarning],
         worst: list[WorstPoint], left_out: tuple[int, int] = (0, 0)):
    """What the surgeon is told when a run ends (``entry``: its row; ``pinned``: the result's
    pose doubts, pinned over the 3D view, empty when cancelled; ``warnings``: the run's;
    ``left_out``: (data points the fit gave no weight, all data points)). The red box of an
    earlier run that warned goes when a run's result without a warning replaces it: it stayed
    over the 3D view beside a clean row."""
    if entry.cancelled:
        core.notify("Registration", "Cancelled: the previous result is kept.")
        return
    # a line said already, pinned over the 3D view while the pose is on show (``ClientView._pose_alert``),
    # is not said again in a second red box: it covered more of the liver at 1366 × 768
    unsaid = [w for w in warnings if w not in pinned]
    if entry.warning and pinned and not unsaid:
        core.withdraw(CHECK_THE_FIT)
    elif entry.warning:
        core.notify(CHECK_THE_FIT, fit_notice(unsaid, entry.pose_only, left_out), error=True)
        return
    else:
        core.withdraw(CHECK_THE_FIT)
    if left_out[0]:
        core.notify("Registration", _left_out(left_out).strip())


NOTICE_HEAD = 90
"""Characters of a warning's head (its words before the first colon) in the red box."""


def fit_notice(warnings: list[FitWarning], pose_only: bool, left_out: tuple[int, int] = (0, 0)) -> str:
    """The red box's words after a run that warned: each warning's head, what is shown, and
    where the whole text is. The box is a few lines high over the 3D view (viser clips it at
    200 px, centred): the whole warnings, each a sentence or two, showed only their middles."""
    heads = [clip_words(w.head, NOTICE_HEAD) for w in warnings]
    text = "⚠ " + "; ".join(heads) + "."
    if pose_only:
        text += " Shown: the pose alone, without deformation."
    if left_out[0]:
        text += f" {_points(left_out)} left out of the fit."
    return text + " The whole text is in the Registration panel."


def clip_words(text: str, n: int) -> str:
    """``text`` cut to at most ``n`` characters at a word, with "…" where it was cut."""
    return text if len(text) <= n else text[:n].rsplit(" ", 1)[0].rstrip(" ,;:(") + "…"


def _points(left_out: tuple[int, int]) -> str:
    """"12 of 1,562 data points were" (the fit's whole count: a wrong click's line is hundreds)."""
    n, total = left_out
    return f"{n:,} of {total:,} data point{'s were' if total > 1 else ' was'}" if n > 1 else \
        f"1 of {total:,} data points was"


def _left_out(left_out: tuple[int, int]) -> str:
    """A sentence on data points the fit gave no weight (outliers), or ""."""
    if not left_out[0]:
        return ""
    return (f" — {_points(left_out)} too far from the model to be trusted and left out of the fit: the worst are "
            "listed under Worst data points (Registration panel); remove a wrong click there and register again")


def plane_name(i: int | None) -> str:
    """A plane as the Plane list numbers it."""
    if i is None:
        return "?"
    if i >= LIVE_PLANE_BASE:
        return f"live {i - LIVE_PLANE_BASE + 1}"
    return f"free {i - FREE_PLANE_BASE + 1}" if i >= FREE_PLANE_BASE else str(i + 1)


def worst_points(reg: Registration, data: dict, origins: dict, weights: Weights, n: int = WORST_SHOWN,
                 left_out: list | None = None, residuals: list | None = None) -> list[WorstPoint]:
    """The ``n`` data points furthest from ``reg``'s answer beyond what their noise allows
    (``quality``: the feature's expected noise + the fit-quality margin), worst first; of a drawn
    contour only its vertices, the clicks (a wrong click rasterises into a spike of points
    whose every pixel is off, but the click is the one thing to remove). ``left_out``: drawn
    vertices left out before the fit (``contours.StrayVertex``), listed first, as not used;
    ``residuals``: ``point_residuals(reg, weights)`` when known."""
    out: list[WorstPoint] = []
    seen: set[tuple] = set()
    for s in left_out or ():
        v = s.origin.vertex()
        if v is None or s.origin.contour is None:
            continue
        c, r = s.origin.contour.vertices[v]
        # its distance from the registered model's feature, said like every other point's
        res = point_residual_at(reg, s.feature, reg.rigid.inverse(s.point[None, :]))
        seen.add((id(s.origin.contour), v))
        x, y, z = (float(t) for t in s.point)
        out.append(WorstPoint(s.feature, float(res[0]), True, s.origin, (x, y, z),
                              f"{feature_words(s.feature)}, plane {plane_name(s.origin.plane)}, drawn vertex {v + 1} "
                              f"at pixel ({c}, {r}), off the vessel it was drawn around", v))
    out = out[:n]
    if len(out) == n:
        return out
    for p in residuals if residuals is not None else point_residuals(reg, weights):
        if p.residual_mm <= EXPECTED_NOISE_MM.get(p.feature, 1.0) + MARGIN_MM or p.feature not in origins:
            continue
        o = origins[p.feature][p.index]
        v = o.vertex() if o.kind is OriginKind.CONTOUR else None
        if o.kind is OriginKind.CONTOUR and o.pixel is not None and v is None:
            continue  # a pixel of the line between two clicks: the clicks are what can be wrong
        key = (id(o.contour), v) if v is not None else (p.feature, p.index)
        if key in seen:
            continue
        seen.add(key)
        if v is not None and o.contour is not None:
            c, r = o.contour.vertices[v]
            where = f"plane {plane_name(o.plane)}, drawn vertex {v + 1} at pixel ({c}, {r})"
        elif o.kind is OriginKind.PLANE:
            where = f"segmentation of plane {plane_name(o.plane)}"
        else:
            live = "tracked stylus" if BY_NAME[p.feature].source == "stylus" else f"live {BY_NAME[p.feature].source}"
            where = {OriginKind.STYLUS: "stylus sweep", OriginKind.LIVE: live,
                     OriginKind.SOURCE: f"simulated {BY_NAME[p.feature].source}",
                     OriginKind.CONTOUR: f"centre of a contour on plane {plane_name(o.plane)}"}[o.kind]
        x, y, z = (float(t) for t in data[p.feature][p.index])
        out.append(WorstPoint(p.feature, p.residual_mm, p.rejected, o, (x, y, z),
                              f"{feature_words(p.feature)}, {where}", v))
        if len(out) == n:
            break
    return out

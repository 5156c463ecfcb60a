"""The Registration panel: rigid and deformable runs, cancel, live progress, the error
against time (from the starting rigid pose), the run table and the result on show with the
predicted error at each target."""

from dataclasses import replace
from html import escape

import numpy as np

from ...mechanics.supports import HeldSupports, Supports
from ..core import INTERRUPTED
from ..runs import WORST_SHOWN
from ..state import (
    STATED_SD_DEG,
    STATED_SD_MM,
    Change,
    PoseFrame,
    RunKind,
    StatedPose,
    StatedSupports,
    held_of,
    supports_words,
)
from ..worker import Update

NOTE = ("The solver minimises the misfit to the data, which it can see, not the error, which it "
        "cannot: the error may rise a little while the fit converges.")
BUTTONS = {RunKind.RIGID: "Rigid", RunKind.SURFACE: "Deformable (surface only)", RunKind.ALL: "Deformable (all data)",
           RunKind.WARM: "Re-register (warm start)"}
TABLE_ROWS = 8  # the newest runs shown
NOTHING = "—"
POSE_ONLY = " → the pose alone, without deformation"  # the data did not support the deformation
# "Pose of the data": what the surgeon knows of it before the fit (``state.PoseFrame``)
FRAMES = {PoseFrame.UNKNOWN: "Unknown: search for it", PoseFrame.GIVEN: "As the tracker gives it",
          PoseFrame.PREVIOUS: "The previous registration's"}
POSE_HELP = ("How well the pose of the data is known before the fit: from a landmark or fiducial registration "
             "(as the tracker gives it), or from the registration on show. The fit then keeps the pose within "
             "that spread where the data cannot determine it; unknown, it searches for the pose.")

# "Organ held at": where the surgeon knows the liver is held (``state.StatedSupports``)
HELD = {"Free-floating (not stated)": StatedSupports(),
        "Its ligaments": StatedSupports(HeldSupports(Supports.LIGAMENTS, "N")),
        "Its ligaments, left one released": StatedSupports(HeldSupports(Supports.LIGAMENTS, "L")),
        "Its ligaments, right one released": StatedSupports(HeldSupports(Supports.LIGAMENTS, "R")),
        "A posterior bed": StatedSupports(HeldSupports(Supports.POSTERIOR)),
        "The bare area alone": StatedSupports(HeldSupports(Supports.BARE_AREA))}
HELD_HELP = ("Where the liver is held (the ligaments left intact, the bed it lies on, or points on its surface from "
             "a support-points file): the model then does not move there in any mode, so sparse data on the front "
             "need not carry the whole organ. The data can contradict the statement: then the free-floating answer "
             "is shown, with a line saying so.")
# held at the points of a support-points file (preop/supports.csv: x,y,z mm, preoperative frame)
POINTS = "Points on its surface (file)"
STIFFNESS_HELP = ("How firmly the supports hold: 0 holds them firmly (no displacement there); a spring stiffness "
                  "in Pa per mm of displacement lets every mode move there elastically (softer tissue, a retractor "
                  "that gives).")
POINTS_HELP = ("A CSV file of points on the liver surface where it is held (x,y,z in mm, preoperative frame; an "
               "optional header x,y,z), as a case's preop/supports.csv: the surface within 5 mm of each is held.")


class RegistrationPanel:
    def __init__(self, view):
        self.view, self.app, self.core = view, view.app, view.app.core
        g = view.client.gui
        with g.add_folder("Registration"):
            self.frame = g.add_dropdown("Pose of the data", options=tuple(FRAMES.values()),
                                        initial_value=FRAMES[PoseFrame.UNKNOWN], hint=POSE_HELP)
            self.sd_mm = g.add_number("Known within (mm)", STATED_SD_MM, min=0.1, max=50.0, step=0.1, disabled=True)
            self.sd_deg = g.add_number("Known within (°)", STATED_SD_DEG, min=0.1, max=45.0, step=0.1, disabled=True)
            self.held = g.add_dropdown("Organ held at", options=(*HELD, POINTS), initial_value=next(iter(HELD)),
                                       hint=HELD_HELP)
            self.stiffness = g.add_number("Springs (Pa/mm; 0: firm)", 0.0, min=0.0, max=1e6, step=1.0,
                                          disabled=True, hint=STIFFNESS_HELP)
            self.points_file = g.add_upload_button("Support points file (CSV)", mime_type=".csv,text/csv",
                                                   hint=POINTS_HELP)
            self.held_md = g.add_markdown("")
            self.btn = {kind: g.add_button(words, disabled=True) for kind, words in BUTTONS.items()}
            # never disabled once the model is ready: see ``runs.Runs.cancel``
            self.btn_cancel = g.add_button("Cancel", color="red", disabled=True)
            self.md = g.add_markdown("")
            # which finished run's result is on show: a Rigid press never loses a good deformable result
            self.on_show = g.add_dropdown("On show", options=(NOTHING,), initial_value=NOTHING, disabled=True)
            self.plot = g.add_uplot((np.zeros(1), np.zeros(1)),
                                    ({"label": "time (s)"}, {"label": "mean error (mm)", "stroke": "#d33", "width": 2,
                                                             "points": {"show": True, "size": 4}}),
                                    title="Error against time", aspect=1.6, scales={"x": {"time": False}},
                                    axes=({"label": "time since start (s)"}, {"label": "mean error (mm)"}))
            self.note = g.add_markdown(f"<small>{NOTE}</small>")
            self.table = g.add_html("")
            # the data points the last fit left furthest from the model: a wrong click is found here
            self.worst_md = g.add_markdown("")
            self.btn_worst = [g.add_button("Remove", visible=False) for _ in range(WORST_SHOWN)]
        for i, b in enumerate(self.btn_worst):
            b.on_click(view.edits(lambda e, i=i: self.remove(i)))
        # starts and Cancel are handled in the order they were clicked (``runs.Runs.order``)
        for kind, b in self.btn.items():
            b.on_click(view.edits(self._in_order(lambda kind=kind: self.start(kind))))
        self.btn_cancel.on_click(view.edits(self._in_order(self.cancel)))
        self.on_show.on_update(view.edits(lambda e: self.show()))
        stated = view.edits(lambda e: self.state_pose())
        for control in (self.frame, self.sd_mm, self.sd_deg):
            # a value set here (``_pose``, every tab following one) calls back at once, with no
            # client, half-set: only a person's change is a statement
            control.on_update(lambda e: None if e.client is None else stated(e))
        said = view.edits(lambda e: self.state_supports())
        for control in (self.held, self.stiffness):
            control.on_update(lambda e: None if e.client is None else said(e))
        self.points_file.on_upload(view.edits(lambda e: self.load_points()))
        self._choices: dict[str, int] = {}  # dropdown words → row of the log

    def _in_order(self, action):
        async def on_click(_event):  # viser awaits a coroutine callback as the click arrives, in order
            self.app.runs.order(action)
        return on_click

    def start(self, kind: RunKind):
        err = self.app.runs.start(kind, self.view.cs)
        if err:
            self.view.notify("Registration", err, error="Collect" in err)

    def cancel(self):
        self.view.notify("Cancel", self.app.runs.cancel(self.view.cs))

    def state_pose(self):
        frame = next(f for f, words in FRAMES.items() if words == self.frame.value)
        try:
            stated = StatedPose(frame, float(self.sd_mm.value), float(self.sd_deg.value))
        except (TypeError, ValueError):  # an emptied number field: the stated pose stays as it was
            self._pose()
            return
        before = self._stated()
        said = self.app.runs.set_pose(stated, self.view.cs)
        if said and (before is None or before.frame is not stated.frame):
            # a number box sends each keystroke (1, then 1.5): the panel shows the numbers, and
            # only a change of frame is worth a notice
            self.view.notify("Pose of the data", said)

    def state_supports(self):
        """The supports the controls say, stated for the runs to come: a named region or the
        points (the ones loaded last, else the case's own), held firmly or on springs."""
        try:
            k = float(self.stiffness.value)
        except (TypeError, ValueError):  # an emptied number field: the stated supports stay as they were
            self._supports()
            return
        stiffness = k if k > 0 else None
        if self.held.value == POINTS:
            points = self.app.runs.support_points()
            if points is None:
                self.view.notify("Organ held at", "No support points yet: load a support-points file (x,y,z mm, "
                                 "preoperative frame) with the button below.", error=True)
                self._supports()
                return
            stated = StatedSupports(HeldSupports(Supports.POINTS, stiffness=stiffness, points=points))
        else:
            region = HELD.get(self.held.value)
            if region is None:
                return
            stated = region if region.held is None else StatedSupports(replace(region.held, stiffness=stiffness))
        before = self._stated_supports()
        said = self.app.runs.set_supports(stated, self.view.cs)
        if said and (before is None or before.held is None or stated.held is None or
                     (before.held.held, before.held.release) != (stated.held.held, stated.held.release)):
            # the number box sends each keystroke (3, 30, 300): the panel shows the springs, and only a
            # change of where the organ is held is worth a notice
            self.view.notify("Organ held at", said)

    def load_points(self):
        """A support-points file uploaded: read, checked against the liver surface, and stated
        (held at them, firmly or on the springs shown)."""
        up = self.points_file.value
        said, error = self.app.runs.load_support_points(up.name, up.content, self._stiffness(), self.view.cs)
        self.view.notify("Support points", said, error=error)

    def _stiffness(self) -> float | None:
        try:
            k = float(self.stiffness.value)
        except (TypeError, ValueError):
            return None
        return k if k > 0 else None

    def _stated_supports(self) -> StatedSupports | None:
        core = self.core
        with core.lock:
            if core.sd is None or core.session is None:
                return None
            return core.session.stated_supports(core.sd)

    def _supports(self):
        """The controls show the session's stated supports (every tab the same)."""
        stated = self._stated_supports()
        if stated is None:
            return
        held = stated.held
        if held is None:
            words: str | None = next(iter(HELD))
        elif held.held is Supports.POINTS:
            words = POINTS
        else:
            words = next((w for w, s in HELD.items() if s.held == replace(held, stiffness=None)), None)
        if words is not None and self.held.value != words:
            self.held.value = words
        k = 0.0 if held is None or held.stiffness is None else held.stiffness
        if self.stiffness.value != k:
            self.stiffness.value = k
        self.stiffness.disabled = held is None
        self.held_md.content = f"<small>The next fresh registration: organ {stated.words()}.</small>"

    def _stated(self) -> StatedPose | None:
        core = self.core
        with core.lock:
            if core.sd is None or core.session is None:
                return None
            return core.session.stated_pose(core.sd)

    def _pose(self):
        """The controls show the session's stated pose (every tab the same)."""
        stated = self._stated()
        if stated is None:
            return
        if self.frame.value != FRAMES[stated.frame]:
            self.frame.value = FRAMES[stated.frame]
        for control, v in ((self.sd_mm, stated.sd_mm), (self.sd_deg, stated.sd_deg)):
            if control.value != v:
                control.value = v
            control.disabled = stated.frame is PoseFrame.UNKNOWN

    def show(self):
        row = self._choices.get(self.on_show.value)
        core = self.core
        if row is None or core.result is (core.shown_runs.get(row) or (None,))[0]:
            return  # our own refresh, or already on show
        if core.run is not None or core.sweeping:
            # the dropdown is disabled while a run or the sweep goes: this is the browser settling
            # its value (a tab reloaded mid-run got "A registration is already running" unasked)
            self._on_show()
            return
        err = self.app.runs.show(row, self.view.cs)
        if err:
            self.view.notify("On show", err, error=True)

    def _on_show(self):
        core = self.core
        log = core.session.log if core.session else []
        kept = sorted(core.shown_runs)
        choices = {}
        for row in kept:
            e = log[row] if row < len(log) else None
            err = f", mean error {e.error_mean_mm:.2f} mm" if e is not None and e.error_mean_mm is not None else ""
            choices[f"{row + 1}. {e.run if e else 'run'}{err}"] = row
        self._choices = choices
        shown = next((w for w, r in choices.items() if core.shown_runs[r][0] is core.result), None)
        # a result restored after a restart is on show without a row of its own (the runs before
        # the restart are not kept): named, not "—" beside "On show: deformable, all data"
        here = (f"{core.result.run} (restored after a restart)" if core.result is not None and core.result.restored
                else core.result.run if core.result is not None else NOTHING)
        options = tuple(choices) if shown is not None else (here, *choices)
        if tuple(self.on_show.options) != options:
            self.on_show.options = options
        value = shown or here
        if self.on_show.value != value:
            self.on_show.value = value
        self.on_show.disabled = (len(choices) < 2 and shown is not None or not choices
                                 or core.run is not None or core.sweeping)

    def remove(self, i: int):
        worst = self.core.worst or []
        if i >= len(worst):
            return
        self.view.notify("Removed", self.app.drawing.remove(self.view.cs, worst[i]))

    def _worst(self):
        worst = list(self.core.worst or [])
        # a point removed keeps its place, marked, its button disabled (``Drawing.remove``): the list
        # closed up under the mouse, and a double click on "Remove 1" removed the point after it too
        gone = [self.app.drawing.gone(w) for w in worst]
        if self.core.result is None:
            self.worst_md.content = ""
        elif self.core.worst is None:
            self.worst_md.content = ("**Worst data points**: not known for this result, restored after a restart: "
                                     "the data have changed since it was fitted. Register again to list them.")
        elif not worst and self.core.result.pose_warning:
            # the points fit a pose nobody should believe (one plane's wall, 33 mm off): "every point
            # lies on the model" read as reassurance beside the red banner
            self.worst_md.content = ("**Worst data points**: none beyond its noise — the points fit the model, but "
                                     "in a pose not to be believed (the red banner): add data elsewhere, not fewer.")
        elif not worst:
            self.worst_md.content = "**Worst data points**: none beyond its noise — every point lies on the model."
        else:
            lines = [f"{i + 1}. " + (f"~~{w.text()}~~ — removed" if out else w.text())
                     for i, (w, out) in enumerate(zip(worst, gone, strict=True))]
            # a rigid answer does not follow the organ's deformation: its worst points are mostly that
            # deformation (7 mm stylus points on the demo), and "remove a wrong one" invited removing good data
            head = ("**Worst data points** (distance to the rigid answer, which does not follow the organ's "
                    "deformation: most of these distances are that deformation — register deformably before "
                    "removing any, and remove only a point you know is wrong):  \n"
                    if self.core.result.beta is None else
                    "**Worst data points** (distance to the registered model; remove a wrong one, "
                    "then register again):  \n")
            self.worst_md.content = head + "  \n".join(lines)
        for i, b in enumerate(self.btn_worst):
            b.visible = i < len(worst)
            if i < len(worst):
                b.disabled = gone[i]
                b.label = f"{i + 1} removed" if gone[i] else f"Remove {i + 1} ({worst[i].residual_mm:.1f} mm)"

    def refresh(self, what: Change):
        core, live = self.core, self.app.live
        worker = core.worker
        run = core.run
        for kind, b in self.btn.items():
            b.disabled = (worker is None or run is not None or core.sweeping
                          or (kind is RunKind.WARM and worker.last is None))
        self.btn_cancel.disabled = worker is None
        if what is Change.LIVE and live.link is not None and live.following:
            self.md.content = (f"**Live re-registration on**: {live.link.follower.summary()}. The result is kept "
                               f"when it is switched off.")
        if what in (Change.POSE, Change.SCENE):
            self._pose()
            self._supports()
        if what in (Change.RESULT, Change.DATA, Change.SCENE):
            self._worst()
        if what in (Change.RESULT, Change.SCENE, Change.MODEL, Change.RUN):
            self._on_show()
        if what in (Change.MODEL, Change.RESULT, Change.RUN, Change.LOG, Change.SCENE):
            self._table()
            if run is not None:
                self.md.content = f"Running **{run.kind.label}** on {run.points} points…"
                return
            if core.sweeping:  # the run buttons are greyed: say why (a tab saw no reason for 20 s)
                self.md.content = ("**The accuracy sweep is running** (What accuracy costs): registrations wait for "
                                   "it; Cancel stops it.")
                return
            self._summary()
            self._plot_shown()

    def _plot_shown(self):
        """The error-against-time curve of the run whose result is on show; emptied for one
        without a curve (a rigid run). It showed the last deformable run's curve with a rigid
        result picked under On show. A result with no row (a live frame, one restored after a
        restart) leaves the plot as it is."""
        core = self.core
        log = core.session.log if core.session else []
        row = next((r for r, kept in core.shown_runs.items() if kept[0] is core.result), None)
        if row is None or row >= len(log):
            return
        trace = log[row].trace
        t, e = np.array(trace, float).T if trace else (np.zeros(1), np.zeros(1))
        self.plot.data = (t, e)

    def show_update(self, u: Update):
        run = self.core.run
        if run is None:
            return
        trace = list(run.trace)
        if trace:
            t, e = np.array(trace).T
            self.plot.data = (t, e)
        err = f", mean error {trace[-1][1]:.2f} mm" if trace else ""
        omega = "" if np.isnan(u.omega) else f", Ω = {u.omega:.4g}"
        what = "starting pose" if u.iteration == 0 else f"iteration {u.iteration}"
        self.md.content = f"**{run.kind.label}** — {what}{omega}, {u.elapsed:.2f} s{err}"

    def _summary(self):
        core = self.core
        log = core.session.log if core.session else []
        if not log:
            self.md.content = "No registration yet."
            return
        last = log[-1]
        if last.cancelled:
            head = f"**{last.run} cancelled** after {last.seconds:.2f} s; the previous result is kept."
        else:
            head = f"**Last: {last.run}{POSE_ONLY if last.pose_only else ''}, {last.seconds:.2f} s"
            if last.error_mean_mm is not None:
                head += f", mean error {last.error_mean_mm:.2f} mm, max {last.error_max_mm:.2f} mm"
            head += "**"
            if last.warning:
                head += f"  \n⚠ {last.warning}"
        res = core.result
        if res is not None:
            err = res.node_error_mm
            pose_only = res.beta is None and RunKind.from_label(res.run) not in (RunKind.RIGID, RunKind.RESTORED)
            # the run table's figure is kept to 0.001 mm (``RunEntry.of``): formatted from the same
            # rounding, the same result read 3.92 in "Last" and 3.91 here
            head += (f"  \nOn show: {res.run}{POSE_ONLY if pose_only else ''}"
                     + (f" (mean error {round(float(err.mean()), 3):.2f} mm)" if err is not None else ""))
            if res.model is not None:  # a basis held at stated supports: said, as the data may contradict them
                head += f"; model {supports_words(held_of(res.model))}"
            elif (stated := self._stated_supports()) is not None and stated.held is not None:
                # supports are stated, and this answer is not held at them (the data did not bear them
                # out, or it was fitted before they were stated): said beside the statement
                head += "; model free-floating"
            # an earlier run put back on show (On show) brings its own warning: only the last run's was
            # said, and a warned result chosen after a clean run read as clean (a bare ⚠ in its row)
            row = next((r for r, kept in core.shown_runs.items() if kept[0] is res), None)
            if row is not None and row != len(log) - 1 and row < len(log) and log[row].warning:
                head += f"  \n⚠ {log[row].warning}"
            if res.predicted_mm is not None:
                head += (f"  \nPredicted error (no truth used): mean {res.predicted_mm.mean():.1f} mm over the "
                         f"liver surface")
            for b in res.target_bands:  # the tumours: predicted error, band, and the result's warning for each
                head += f"  \n{b.name}: {b.text()}"
        self.md.content = head

    def _table(self):
        core = self.core
        log = core.session.log if core.session else []
        if not log:
            self.table.content = ""
            return
        names = [t.name for t in core.preop.targets]
        tum = " / ".join(n.replace("tumour", "") for n in names)
        # units in the header, not in every cell: nine columns in the panel's 384 px. An HTML
        # table with its own padding: the markdown table's cells had 2 px between them, and
        # "17.57" beside "2.1 / 5.3" read "17.572.1 / 5.3" at 1366 and 1600 px alike
        head = ["#", "run", "points", "s", "iterations", "mean mm", "max mm",
                f"tumour{'s' if len(names) > 1 else ''} {tum} mm", ""]
        rows = []
        first = max(len(log) - TABLE_ROWS, 0)
        for i, e in enumerate(log[first:], start=first + 1):
            its = "ICP" if e.stop == "rigid" else f"{e.iterations}"
            mean = f"{e.error_mean_mm:.2f}" if e.error_mean_mm is not None else "–"
            mx = f"{e.error_max_mm:.2f}" if e.error_max_mm is not None else "–"
            tumours = " / ".join(f"{e.targets_mm[n]:.1f}" for n in names if n in e.targets_mm) if e.targets_mm else "–"
            # "cancelled" in the run's own cell: the last column is narrow and cut it to "cance"
            run = f"{escape(e.run)}, <b>{'interrupted' if e.stop == INTERRUPTED else 'cancelled'}</b>" \
                if e.cancelled else escape(e.run)
            note = "" if e.cancelled else ("⚠ pose only" if e.pose_only else "⚠" if e.warning else e.note)
            rows.append([str(i), run, str(e.points), f"{e.seconds:.1f}", its, mean, mx, tumours, escape(note or "")])
        self.table.content = run_table_html(head, rows)


TABLE_STYLE = ("border-collapse:collapse;font-size:0.78em;font-variant-numeric:tabular-nums;line-height:1.35;"
               "width:100%")
CELL = "padding:1px 4px;border-bottom:1px solid #8883;vertical-align:top"
TEXT_COLUMNS = (1, 8)  # the run's name and its note read left to right; the numbers align right


def run_table_html(head: list[str], rows: list[list[str]]) -> str:
    """The run table as HTML: ``head`` the column titles (plain text), ``rows`` each row's cells
    (HTML, escaped by the caller). Every cell keeps 8 px between its text and the next's."""
    def cell(tag, i, text):
        align = "left" if i in TEXT_COLUMNS else "right"
        wrap = "" if tag == "th" or i in TEXT_COLUMNS else ";white-space:nowrap"
        return f"<{tag} style='{CELL};text-align:{align}{wrap}'>{text}</{tag}>"

    top = "<tr>" + "".join(cell("th", i, escape(h)) for i, h in enumerate(head)) + "</tr>"
    body = "".join("<tr>" + "".join(cell("td", i, c) for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table style='{TABLE_STYLE}'>{top}{body}</table>"

"""The Registration panel: rigid and deformable runs, cancel, live progress, the error
against time (from the starting rigid pose), and the table of runs."""

import numpy as np

NOTE = ("The solver minimises the misfit to the data, which it can see, not the error, which it "
        "cannot: the error may rise a little while the fit converges.")


class RegistrationPanel:
    def __init__(self, view):
        self.view, self.app = view, view.app
        g = view.client.gui
        with g.add_folder("Registration"):
            self.btn = {
                "rigid": g.add_button("Rigid", disabled=True),
                "surface": g.add_button("Deformable (surface only)", disabled=True),
                "all": g.add_button("Deformable (all data)", disabled=True),
                "warm": g.add_button("Re-register (warm start)", disabled=True),
            }
            self.btn_cancel = g.add_button("Cancel", color="red", disabled=True)
            self.md = g.add_markdown("")
            self.plot = g.add_uplot((np.zeros(1), np.zeros(1)),
                                    ({"label": "time (s)"}, {"label": "mean error (mm)", "stroke": "#d33", "width": 2,
                                                             "points": {"show": True, "size": 4}}),
                                    title="Error against time", aspect=1.6, scales={"x": {"time": False}},
                                    axes=({"label": "time since start (s)"}, {"label": "mean error (mm)"}))
            self.note = g.add_markdown(f"<small>{NOTE}</small>")
            self.table = g.add_markdown("")
        for kind, b in self.btn.items():
            b.on_click(lambda e, kind=kind: self.start(kind))
        self.btn_cancel.on_click(lambda e: self.app.cancel())

    def start(self, kind):
        err = self.app.register(kind)
        if err:
            self.view.notify("Registration", err, error="Collect" in err)

    def refresh(self, what):
        app = self.app
        ready = app.worker is not None
        running = app.run is not None
        for kind, b in self.btn.items():
            b.disabled = not ready or running or (kind == "warm" and (app.worker is None or app.worker.last is None))
        self.btn_cancel.disabled = not running
        live = app.live
        if what == "live" and live is not None and live.follower.on:
            self.md.content = (f"**Live re-registration on**: {live.follower.summary()}. The result is kept "
                               f"when it is switched off.")
        if what in ("model", "result", "run", "log", "scene"):
            self._table()
            if running:
                self.md.content = f"Running **{app.run['label']}** on {app.run['points']} points…"
            else:
                self._summary()
            if not running:
                log = app.session.log if app.session else []
                done = [e for e in log if not e.get("cancelled") and e.get("trace")]
                if done:
                    t, e = np.array(done[-1]["trace"], float).T
                    self.plot.data = (t, e)

    def show_update(self, u):
        run = self.app.run
        if run is None:
            return
        if run["trace"]:
            t, e = np.array(run["trace"]).T
            self.plot.data = (t, e)
        err = f", mean error {run['trace'][-1][1]:.2f} mm" if run["trace"] else ""
        omega = "" if np.isnan(u.omega) else f", Ω = {u.omega:.4g}"
        what = "starting pose" if u.iteration == 0 else f"iteration {u.iteration}"
        self.md.content = f"**{run['label']}** — {what}{omega}, {u.elapsed:.2f} s{err}"

    def _summary(self):
        app = self.app
        log = app.session.log if app.session else []
        if not log:
            self.md.content = "No registration yet."
            return
        last = log[-1]
        if last.get("cancelled"):
            head = f"**{last['run']} cancelled** after {last['seconds']:.2f} s; the previous result is kept."
        else:
            head = f"**Last: {last['run']}, {last['seconds']:.2f} s"
            if "error_mean_mm" in last:
                head += f", mean error {last['error_mean_mm']:.2f} mm, max {last['error_max_mm']:.2f} mm"
            head += "**"
            if last.get("warning"):
                head += f"  \n⚠ {last['warning']}"
        res = app.result
        if res is not None:
            err = res.node_error_mm
            head += f"  \nOn show: {res.run}" + (f" (mean error {err.mean():.2f} mm)" if err is not None else "")
            if res.predicted_mm is not None:
                head += (f"  \nPredicted error (no truth used): mean {res.predicted_mm.mean():.1f} mm over the "
                         f"liver surface")
            for b in res.target_bands:
                head += f"  \n{b.name}: {b.text()}"
        self.md.content = head

    def _table(self):
        app = self.app
        log = app.session.log if app.session else []
        if not log:
            self.table.content = ""
            return
        rows = ["| run | points | time | iterations | mean err | max err | |", "|---|---|---|---|---|---|---|"]
        for e in log[-8:]:
            its = "ICP" if e["stop"] == "rigid" else f"{e['iterations']} it"
            mean = f"{e['error_mean_mm']:.2f} mm" if "error_mean_mm" in e else "–"
            mx = f"{e['error_max_mm']:.2f} mm" if "error_max_mm" in e else "–"
            note = "cancelled" if e.get("cancelled") else ("⚠ poor fit" if e.get("warning") else e.get("note", ""))
            rows.append(f"| {e['run']} | {e['points']} | {e['seconds']:.2f} s | {its} | {mean} | {mx} | {note} |")
        self.table.content = "\n".join(rows)

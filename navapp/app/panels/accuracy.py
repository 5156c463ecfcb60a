"""What accuracy costs: rerun the current data with the LM iteration cap and stopping
tolerance varied; every point is one registration (★ = Pareto front)."""

import numpy as np

from ...evaluation.cost import LM_CAPS, LM_RTOLS, pareto_front


class AccuracyPanel:
    def __init__(self, view):
        self.view, self.app = view, view.app
        g = view.client.gui
        with g.add_folder("What accuracy costs", expand_by_default=False):
            g.add_markdown("Reruns the current data with the LM iteration cap and the stopping tolerance "
                           "varied; each point is one registration (★ = Pareto front).")
            # it starts at once: "Sweep settings" read as a panel of settings to open (walking the demo)
            self.btn = g.add_button(f"Run the sweep ({len(LM_CAPS) + len(LM_RTOLS)} registrations)", disabled=True)
            self.plot = g.add_uplot((np.zeros(1), np.zeros(1)),
                                    ({"label": "seconds"}, {"label": "TRE (mm)", "stroke": "#36c", "width": 0,
                                                            "points": {"show": True, "size": 8}}),
                                    title="TRE against registration time", aspect=1.6,
                                    scales={"x": {"time": False}},
                                    axes=({"label": "registration time (s)"}, {"label": "mean TRE (mm)"}))
            self.md = g.add_markdown("")
        self.btn.on_click(view.edits(self._sweep_in_order))

    async def _sweep_in_order(self, _event):  # after any start or Cancel clicked before it (``Runs.order``)
        self.app.runs.order(self.sweep)

    def refresh(self, what):
        core = self.app.core
        self.btn.disabled = core.worker is None or core.run is not None or core.sweeping

    def sweep(self):
        rows = []

        def on_row(r):
            rows.append(r)
            t = np.array([x.seconds for x in rows])
            e = np.array([x.tre_mean_mm for x in rows])
            o = np.argsort(t)
            self.plot.data = (t[o], e[o])
            front = pareto_front(t, e)
            lines = ["| setting | time | TRE | iterations |", "|---|---|---|---|"]
            for j in o:
                lines.append(f"| {rows[j].label}{' ★' if front[j] else ''} | {rows[j].seconds:.2f} s | "
                             f"{rows[j].tre_mean_mm:.2f} mm | {rows[j].iterations} |")
            self.md.content = "\n".join(lines)

        def done(out):
            worker = self.app.core.worker
            cancelled = worker is not None and worker.cancel_requested
            self.view.notify("Cost", f"Cancelled after {len(out)} settings." if cancelled
                             else f"{len(out)} settings run.")

        err = self.app.runs.sweep(on_row, done, self.view.cs)
        if err:
            self.view.notify("Cost", err)

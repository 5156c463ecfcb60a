"""The Stylus panel: the tracked stylus sweeps the exposed anterior surface; its tip's live
distance to each target is shown while it moves."""

from ..state import Change


class StylusPanel:
    def __init__(self, view):
        self.view, self.app = view, view.app
        g = view.client.gui
        with g.add_folder("Stylus"):
            self.md = g.add_markdown("Waiting for the scene…")
            self.speed = g.add_slider("Speed (× realistic)", 1.0, 20.0, 1.0, 5.0)
            self.btn = g.add_button("Digitise the anterior surface", disabled=True)
            self.btn_all = g.add_button("Collect the whole sweep now", disabled=True)
            self.dist = g.add_markdown("")
        self.btn.on_click(view.edits(lambda e: self.app.stylus.start(lambda: float(self.speed.value), view.cs)))
        self.btn_all.on_click(view.edits(lambda e: self.app.stylus.collect_now(view.cs)))

    def refresh(self, what):
        sd, session = self.app.core.sd, self.app.core.session
        if sd is None or session is None:
            return
        if what in (Change.SCENE, Change.DATA):
            n = min(session.stylus_count, len(sd.stylus_path))
            self.md.content = f"{n} of {len(sd.stylus_path)} sweep points digitised"
            self.btn.disabled = self.btn_all.disabled = False
            self.btn.label = "Stop digitising" if self.app.stylus.sweeping else "Digitise the anterior surface"

    def show_tip(self, pos):
        if pos is None:
            self.btn.label = "Digitise the anterior surface"
            # the tool is no longer drawn: its last distances stayed beside it ("87.2 mm from the
            # stylus tip" after the sweep, while a tab opened since showed none)
            self.dist.content = ""
            return
        self.btn.label = "Stop digitising"
        lines = self.app.shown.target_distance_lines(pos)
        self.dist.content = "  \n".join(lines)

"""The Stylus panel: the tracked stylus sweeps the exposed anterior surface; its tip's live
distance to each target is shown while it moves."""



class StylusPanel:
    def __init__(self, view):
        self.view, self.app = view, view.app
        g = view.client.gui
        with g.add_folder("Stylus"):
            self.md = g.add_markdown("Waiting for the scene…")
            self.speed = g.add_slider("Speed (× realistic)", 1.0, 20.0, 1.0, 5.0)
            self.btn = g.add_button("Digitise anterior surface", disabled=True)
            self.btn_all = g.add_button("Collect the whole sweep now", disabled=True)
            self.dist = g.add_markdown("")
        self.btn.on_click(lambda e: self.app.start_stylus(lambda: float(self.speed.value)))
        self.btn_all.on_click(lambda e: self.app.collect_stylus_now())

    def refresh(self, what):
        app = self.app
        if app.sd is None or app.session is None:
            return
        if what in ("scene", "data"):
            n = min(app.session.stylus_count, len(app.sd.stylus_path))
            self.md.content = f"{n} of {len(app.sd.stylus_path)} sweep points digitised"
            self.btn.disabled = self.btn_all.disabled = False
            self.btn.label = "Stop digitising" if app.sweeping else "Digitise anterior surface"

    def show_tip(self, pos):
        if pos is None:
            self.btn.label = "Digitise anterior surface"
            return
        self.btn.label = "Stop digitising"
        lines = self.app.target_distance_lines(pos)
        self.dist.content = "  \n".join(lines)

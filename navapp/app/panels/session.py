"""The Session panel: where the session is kept and Export."""

from ..state import Change


class SessionPanel:
    def __init__(self, view):
        self.view, self.app = view, view.app
        g = view.client.gui
        with g.add_folder("Session"):
            self.md = g.add_markdown("")
            self.btn = g.add_button("Export (PLY, VTK, CSV)", disabled=True)
        self.btn.on_click(view.edits(lambda e: self.export()))

    def refresh(self, what):
        core = self.app.core
        if core.session is not None and what in (Change.SCENE, Change.MODEL):
            self.md.content = f"Everything you enter is saved at once in `{core.session.folder}`."
        self.btn.disabled = core.last_reg is None

    def export(self):
        out, msg = self.app.export()
        self.view.notify("Export", msg, error=out is None)
        if out is not None:
            self.md.content = f"Exported to `{out}`"

"""The Session panel: where the session is kept, Export, and the action log's newest lines."""

from html import escape

from ..state import Change

LOG_LINES = 12  # the newest lines of the action log shown; the whole log is in the session folder


class SessionPanel:
    def __init__(self, view):
        self.view, self.app = view, view.app
        g = view.client.gui
        with g.add_folder("Session"):
            self.md = g.add_markdown("")
            self.btn = g.add_button("Export (PLY, VTK, CSV)", disabled=True)
            with g.add_folder("Action log"):
                self.log = g.add_html("")
        self.btn.on_click(view.edits(lambda e: self.export()))

    def refresh(self, what):
        core = self.app.core
        if core.session is not None and what in (Change.SCENE, Change.MODEL):
            self.md.content = f"Everything you enter is saved at once in `{core.session.folder}`."
        self.btn.disabled = core.last_reg is None
        if what in (Change.SCENE, Change.ACTIONS) and core.actions is not None:
            entries = core.actions.entries()
            lines = [escape(e.line()) for e in entries[-LOG_LINES:][::-1]]  # newest first
            more = len(entries) - len(lines)
            foot = f"<br><i>{more} earlier in {escape(core.actions.path.name)}</i>" if more > 0 else ""
            html = ("<small>" + ("<br>".join(lines) or "Nothing changed yet.") + foot + "</small>")
            if self.log.content != html:
                self.log.content = html

    def export(self):
        out, msg = self.app.export(self.view.cs)
        self.view.notify("Export", msg, error=out is None)
        if out is not None:
            self.md.content = f"Exported to `{out}`"

"""The Guided demo panel (per browser): the step's text, its one button (disabled with the
reason while its precondition does not hold), Back / Skip, and moving on only when a
step's work is done."""

from ..guide import STEPS, first_open_step


class GuidePanel:
    def __init__(self, view):
        self.view, self.app, self.cs = view, view.app, view.cs
        g = view.client.gui
        with g.add_folder("Guided demo"):
            self.md = g.add_markdown("")
            self.btn = g.add_button("", color="green")
            self.why = g.add_markdown("")
            self.nav = g.add_button_group("Step", ("◀ Back", "Skip ▶"))
            self.extra = g.add_markdown("")
        self.btn.on_click(view.edits(lambda e: self.press()))
        self.nav.on_click(lambda e: self.move(-1 if e.target.value.startswith("◀") else 1))
        # a new tab starts past the work the session already holds (a reload takes its own). A tab
        # that connects while a restarted server is still loading sees no session yet: it is
        # placed again when the model is ready, unless the surgeon has moved it (walking the demo,
        # two tabs reconnected early went from step 9 to step 1, and a reload kept it)
        self._placing = self.cs.guide_step == 0
        self._place()
        self.show()

    def _place(self):
        if not self._placing:
            return
        self.cs.guide_step = first_open_step(self.app, self.cs)
        if self.app.core.worker is not None:  # the model is ready and the stored result restored
            self._placing = False

    @property
    def step(self):
        return STEPS[self.cs.guide_step]

    def move(self, d):
        self._placing = False
        self.cs.guide_step = max(0, min(len(STEPS) - 1, self.cs.guide_step + d))
        self.extra.content = ""
        self.show()

    def press(self):
        st = self.step
        why = st.blocked(self.app, self.cs)
        if why:
            self.view.notify("Guided demo", why)
            return
        err = st.action(self.app, self.cs)
        if err:
            self.view.notify("Guided demo", err, error=True)
            return
        if st.done is None and self.cs.guide_step < len(STEPS) - 1:
            self.move(1)
        else:
            self.show()

    def show(self):
        st = self.step
        self.md.content = f"**Step {self.cs.guide_step + 1} of {len(STEPS)}: {st.title}**  \n{st.text}"
        self.btn.label = st.button
        why = st.blocked(self.app, self.cs)
        self.btn.disabled = bool(why)
        self.why.content = f"<small>{why}</small>" if why else ""

    def refresh(self, what):
        self._place()
        st = self.step
        if st.done is not None and st.done(self.app, self.cs) and self.cs.guide_step < len(STEPS) - 1:
            self.move(1)
        else:
            self.show()

    def show_comparison(self):
        self.extra.content = self.view.registration.table.content or "No registrations yet."

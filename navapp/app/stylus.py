"""The simulated stylus sweep: the tip moves along the scene's sweep path at a steady speed
(times the panel's factor) in a thread of its own, the points it passes become data as it
goes, and each sweep is one undoable action. No viser here.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .actions import Act
from .core import Core
from .state import Action, Change, ClientState, Undone

STYLUS_MM_PER_S = 40.0  # a steady sweep of the tip, at "1×"
FRAME_S = 0.05
SAVE_EVERY_S = 0.5  # the session is saved this often while the tip moves


@dataclass
class StylusBatch(Action):
    stylus: Stylus
    before: int  # points digitised before the sweep

    def undo(self, cs):
        if self.stylus.sweeping:
            return "Stop the stylus sweep first."
        session = self.stylus.core.need_session()
        session.stylus_count = min(session.stylus_count, self.before)
        return Undone.DONE


class Stylus:
    def __init__(self, core: Core):
        self.core = core
        self.tip: np.ndarray | None = None  # where the simulated tip is while it sweeps
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._sweeping = False
        self._owner: ClientState | None = None  # the tab that started the sweep: its undo

    @property
    def sweeping(self) -> bool:
        return self._sweeping

    def start(self, speed: Callable[[], float] = lambda: 1.0, cs: ClientState | None = None) -> bool:
        """Start (or stop, if running) the stylus sweep; ``speed()`` is read every frame.
        The sweep is an action of ``cs``, the tab that started it (None: of nobody's)."""
        if self.core.sd is None:
            return False
        if self._sweeping:
            self._stop.set()
            return True
        self._stop.clear()
        self._owner = cs
        self._sweeping = True
        self.core.record(cs, Act.SWEEP, "started")
        self._thread = threading.Thread(target=self._sweep, args=(speed,), daemon=True, name="navapp-stylus")
        self._thread.start()
        return True

    def _sweep(self, speed):
        core = self.core
        sd, session = core.need_scene()
        path = sd.stylus_path
        with core.lock:
            i = min(session.stylus_count, len(path))
            start = i
        pos = path[i] if i < len(path) else path[-1]
        last_saved = time.monotonic()
        while i < len(path) and not self._stop.is_set():
            step = STYLUS_MM_PER_S * speed() * FRAME_S
            while step > 0 and i < len(path):
                d = np.linalg.norm(path[i] - pos)
                if d <= step:
                    pos, step, i = path[i], step - d, i + 1
                else:
                    pos, step = pos + (path[i] - pos) * step / d, 0.0
            self.tip = pos
            with core.lock:
                session.stylus_count = i
            core.each_view(_show_stylus(pos))
            if time.monotonic() - last_saved > SAVE_EVERY_S or i == len(path):
                core.changed(Change.DATA)
                last_saved = time.monotonic()
            time.sleep(FRAME_S)
        self.tip = None
        # Logged before the sweep is reported over: a run started on seeing it over (the guide's
        # next step, another tab) must come after its points in the action log.
        self._record_batch(start, self._owner)
        core.record(self._owner, Act.POINTS, f"sweep points {start + 1}-{i} of {len(path)}" if i > start else
                    "none")
        self._sweeping = False  # before the last refresh, so the views see the sweep as over
        core.each_view(lambda v: v.show_stylus(None))
        core.changed(Change.DATA)

    def _record_batch(self, start: int, owner: ClientState | None):
        """One undoable action per sweep, in the undo of the tab that made it only: another
        tab's Undo must never take away data it did not collect."""
        core = self.core
        with core.lock:
            if owner is not None and core.need_session().stylus_count > start:
                owner.current().undo.append(StylusBatch(self, start))

    def collect_now(self, cs: ClientState | None = None):
        """The whole sweep at once, an action of ``cs``."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        core = self.core
        sd, session = core.need_scene()
        with core.lock:
            start = session.stylus_count
            session.stylus_count = len(sd.stylus_path)
        self._record_batch(start, cs)
        core.record(cs, Act.POINTS, f"whole sweep at once: points {start + 1}-{len(sd.stylus_path)}")
        core.changed(Change.DATA)


def _show_stylus(pos):
    return lambda v: v.show_stylus(pos)

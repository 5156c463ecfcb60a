"""The registered model's motion on screen: a run streams only a few states (the rigid pose,
an iteration or two, the answer), and shown as they come the liver jumped 2–3 times per run.
A ``Tween`` moves what one tab shows from the state on screen to each new one over a fraction
of a second. Display only: the states themselves, their errors and the run's timing are the
registration's; the frames in between are straight lines between two shown states (for the
deformation, linear in β, they are states of the linear model too)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

TWEEN_S = 0.4  # one state change is drawn over this long: long enough to follow, short beside a run
FRAME_S = 0.04  # a frame every 40 ms (25 per second) while a change is drawn


def ease(f: float) -> float:
    """Smoothstep: starts and ends at rest, so a retarget mid-way shows no kink."""
    f = min(max(f, 0.0), 1.0)
    return f * f * (3.0 - 2.0 * f)


class Tween:
    """Moves the arrays one tab shows (name → (n, 3) float32 vertex or point positions) to new
    ones in frames, from a thread of its own; ``draw(frame)`` puts a frame on screen (the
    caller's handles), under ``lock`` (the tab's, ``ClientView.lock``, which every caller of
    ``to``, ``note`` and ``stop`` holds too).

    What is on screen is known to it: the last frame it drew, or what the caller ``note``-d it
    showed itself. ``to(target)`` moves from there; names it has not seen, or whose array changed
    shape, are not moved (the caller shows them at once). The last frame of a move is ``target``
    exactly."""

    def __init__(self, draw: Callable[[dict[str, np.ndarray]], None], lock,
                 duration_s: float = TWEEN_S, frame_s: float = FRAME_S, clock: Callable[[], float] = time.monotonic):
        self.draw, self.lock = draw, lock
        self.duration_s, self.frame_s, self.clock = duration_s, frame_s, clock
        self._mutex = threading.Lock()  # guards the move; the tab's lock is taken first
        self._start: dict[str, np.ndarray] = {}
        self._target: dict[str, np.ndarray] = {}
        self._drawn: dict[str, np.ndarray] = {}  # what is on screen, per name
        self._t0 = 0.0
        self._thread: threading.Thread | None = None
        self.closed = False

    def note(self, name: str, a: np.ndarray):
        """The caller put ``a`` on screen itself."""
        with self._mutex:
            self._drawn[name] = a

    def shows(self, name: str, a: np.ndarray) -> bool:
        """``a`` is on screen for ``name`` and no move is under way for it."""
        with self._mutex:
            d = self._drawn.get(name)
            return name not in self._target and d is not None and d.shape == a.shape and np.array_equal(d, a)

    def stop(self) -> set[str]:
        """No move (the caller shows the next state at once); returns the empty set of names moved."""
        with self._mutex:
            self._start, self._target = {}, {}
        return set()

    def to(self, target: dict[str, np.ndarray], run: bool = True) -> set[str]:
        """Move to ``target``; returns the names it moves (the others are the caller's to show
        now). ``run=False`` sets the move up without its thread (``frame`` draws it)."""
        with self._mutex:
            start = {}
            for name, t in target.items():
                s = self._drawn.get(name)
                if s is not None and s.shape == t.shape and not np.array_equal(s, t):
                    start[name] = s
            self._start = start
            self._target = {n: np.asarray(target[n], np.float32) for n in start}
            self._t0 = self.clock()
            if start and run and not self.closed and (self._thread is None or not self._thread.is_alive()):
                self._thread = threading.Thread(target=self._loop, name="navapp-tween", daemon=True)
                self._thread.start()
            return set(start)

    def frame(self) -> tuple[dict[str, np.ndarray], bool]:
        """The frame for now (name → array), and whether it is the move's last."""
        with self._mutex:
            if not self._target:
                return {}, True
            f = (self.clock() - self._t0) / self.duration_s if self.duration_s > 0 else 1.0
            done = f >= 1.0
            if done:
                out = dict(self._target)
                self._start, self._target = {}, {}
            else:
                w = np.float32(ease(f))
                out = {n: s + (self._target[n] - s) * w for n, s in self._start.items()}
            self._drawn.update(out)
            return out, done

    def close(self):
        """The tab went: no further frames."""
        self.closed = True

    def _loop(self):
        while not self.closed:
            with self.lock:  # the tab's lock, then the move's: the order of every caller of ``to``
                out, done = self.frame()
                try:
                    if out:
                        self.draw(out)
                except Exception:  # the tab closed mid-move; its handles are gone
                    self.closed = True
                    return
            if done:
                with self._mutex:
                    if not self._target:  # no new move began meanwhile
                        self._thread = None
                        return
            time.sleep(self.frame_s)

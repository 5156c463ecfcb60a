"""The registered model moves between a run's states on screen rather than jumping
(``navapp.app.motion``): a run streams 2–3 states, and the liver jumped from each to the next.
Frames are drawn against a clock the test holds, so nothing here depends on the machine's load."""

import threading
import time

import numpy as np

from navapp.app.motion import Tween


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def tween(**kw):
    clock = Clock()
    drawn = []
    t = Tween(lambda frame: drawn.append(frame), threading.RLock(), duration_s=0.4, clock=clock, **kw)
    return t, clock, drawn


def test_a_change_is_drawn_in_steps_and_ends_exactly_on_the_new_state():
    t, clock, _ = tween()
    a = np.zeros((50, 3), np.float32)
    b = a + np.float32(10.0)  # the run's next state: every vertex 17.3 mm away
    t.note("liver", a)
    assert t.to({"liver": b}, run=False) == {"liver"}
    frames = []
    for step in range(1, 12):
        clock.t = 0.04 * step
        out, done = t.frame()
        frames.append(out["liver"])
        if done:
            break
    assert done and np.array_equal(frames[-1], b)  # the answer on screen is the answer, not close to it
    path = [a] + frames
    steps = [float(np.abs(q - p).max()) for p, q in zip(path, path[1:], strict=False)]
    assert len(frames) >= 8 and max(steps) < 0.25 * 10.0, steps  # shown as it came: one 10 mm jump
    assert all(s >= 0 for s in steps) and np.all(np.diff([f[0, 0] for f in frames]) >= 0)  # never back


def test_a_new_state_mid_move_starts_from_what_is_on_screen():
    t, clock, _ = tween()
    a = np.zeros((4, 3), np.float32)
    t.note("liver", a)
    t.to({"liver": a + np.float32(10.0)}, run=False)
    clock.t = 0.2
    mid, _ = t.frame()
    shown = mid["liver"].copy()
    assert 0.0 < shown[0, 0] < 10.0
    t.to({"liver": a - np.float32(5.0)}, run=False)  # the next state arrives before the move ends
    clock.t = 0.24
    nxt, _ = t.frame()
    assert np.abs(nxt["liver"] - shown).max() < 1.0  # from where it was, not from the old start
    clock.t = 1.0
    end, done = t.frame()
    assert done and np.array_equal(end["liver"], a - np.float32(5.0))


def test_new_or_reshaped_nodes_and_a_stop_are_the_callers_to_show_at_once():
    t, clock, _ = tween()
    a = np.zeros((4, 3), np.float32)
    t.note("liver", a)
    moved = t.to({"liver": a + 1, "tumour1": a, "hepatic": a}, run=False)
    assert moved == {"liver"}  # nothing known on screen for the others
    t.note("hepatic", np.zeros((7, 3), np.float32))
    assert t.to({"hepatic": a}, run=False) == set()  # another shape: no straight line between them
    assert t.to({"liver": a + 1}, run=False) == {"liver"}
    assert t.stop() == set()
    out, done = t.frame()
    assert done and out == {}  # live re-registration shows each state at once


def test_the_thread_draws_the_move_and_ends():
    drawn = []
    lock = threading.RLock()
    t = Tween(lambda frame: drawn.append(frame["liver"].copy()), lock, duration_s=0.2, frame_s=0.01)
    a = np.zeros((4, 3), np.float32)
    t.note("liver", a)
    with lock:
        t.to({"liver": a + np.float32(3.0)})
    end = time.monotonic() + 60  # generous: a loaded machine may be slow to run the thread
    while (t._thread is not None and t._thread.is_alive()) and time.monotonic() < end:
        time.sleep(0.05)
    assert drawn and np.array_equal(drawn[-1], a + np.float32(3.0))
    assert t.shows("liver", a + np.float32(3.0))

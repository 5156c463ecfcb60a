"""Progress shown on anything slow: tqdm bars on stderr, and a ticking stage timer for
calls that report no progress of their own (e.g. Gmsh).

Silence: ``QUIET`` is the application's switch (the CLI's ``--quiet``, the test suite);
library code that must not draw bars (a worker process, a study step) uses the scoped
``quiet()`` context, which restores the previous state when the block ends and never
touches ``QUIET``."""

import contextvars
import sys
import threading
import time
from contextlib import contextmanager

from tqdm import tqdm

QUIET = False  # set by the CLI's --quiet and by tests (application-wide); library code uses quiet()
_scoped_quiet = contextvars.ContextVar("navapp_progress_quiet", default=False)
_listeners: list = []  # callables (desc, fraction or None) — e.g. the viewer's status panel


def is_quiet() -> bool:
    """True when bars are hidden: ``QUIET`` set, or inside a ``quiet()`` block."""
    return QUIET or _scoped_quiet.get()


@contextmanager
def quiet(on: bool = True):
    """Hide bars and stage timers inside the block (this thread / context only), then
    restore what was there before, also when the block raises."""
    token = _scoped_quiet.set(on)
    try:
        yield
    finally:
        _scoped_quiet.reset(token)


def add_listener(fn):
    """Also report progress to ``fn(desc, fraction)``: fraction in [0, 1] for bars, None
    when a stage starts (no measurable progress). Returns ``fn`` (for remove_listener)."""
    _listeners.append(fn)
    return fn


def remove_listener(fn):
    if fn in _listeners:
        _listeners.remove(fn)


def _notify(desc, fraction):
    for fn in list(_listeners):
        try:
            fn(desc, fraction)
        except Exception:  # a failing display must never stop a computation
            pass


class _Bar(tqdm):
    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.label, self.done = kw["desc"], 0  # tqdm keeps neither when disabled

    def update(self, n=1):
        out = super().update(n)
        self.done += n
        if _listeners and self.total:
            _notify(self.label, min(1.0, self.done / self.total))
        return out

    def to(self, n):
        """Move the bar to ``n`` done (the meshing bar follows a child's CPU seconds)."""
        if n > self.done:
            self.update(n - self.done)


def bar(total, desc, unit="it"):
    """A tqdm bar on stderr (hidden when ``is_quiet()``), also reported to the listeners."""
    _notify(desc, 0.0)
    return _Bar(total=total, desc=desc, unit=unit, file=sys.stderr, disable=is_quiet(), leave=False,
                dynamic_ncols=True, mininterval=0.2)


def work(desc, total):
    """A bar for work measured in seconds of CPU (e.g. a mesher in a child process against
    its expected CPU time): percentage, elapsed and ETA, no rate."""
    _notify(desc, 0.0)
    return _Bar(total=total, desc=desc, file=sys.stderr, disable=is_quiet(), leave=False, dynamic_ncols=True,
                mininterval=0.5, bar_format="{desc}: {percentage:3.0f}% [{elapsed}<{remaining}]")


_write_lock = threading.Lock()


def echo(line: str):
    """Print ``line`` on stderr on a line of its own: an active bar is cleared first and
    redrawn after it (a bare print would be glued onto the bar's line)."""
    with _write_lock:
        tqdm.write(line, file=sys.stderr)


@contextmanager
def stage(desc):
    """Show ``desc`` with elapsed seconds ticking while the block runs; yields a dict that
    receives ``seconds`` when the block ends."""
    out: dict = {}
    stop = threading.Event()
    t0 = time.perf_counter()
    _notify(desc, None)
    hidden = is_quiet()  # read here: the ticking thread does not see this context's quiet()

    def tick():
        with tqdm(desc=desc, bar_format="{desc}: {elapsed}", file=sys.stderr, disable=hidden, leave=False) as t:
            while not stop.wait(0.5):
                t.refresh()

    th = threading.Thread(target=tick, daemon=True)
    th.start()
    try:
        yield out
    finally:
        stop.set()
        th.join()
        out["seconds"] = time.perf_counter() - t0

"""Progress shown on anything slow: tqdm bars on stderr, and a ticking stage timer for
calls that report no progress of their own (e.g. Gmsh).

Silence: ``QUIET`` is the application's switch (the CLI's ``--quiet``, the test suite);
library code that must not draw bars (a worker process, a study step) uses the scoped
``quiet()`` context, which restores the previous state when the block ends and never
touches ``QUIET``.

A terminal redraws a bar in place at each ``\r``; a file or a pipe (a log, CI, ``2> log``)
keeps every state on one endless line, and whatever is printed next — a warning — was glued
onto it. Where stderr is not a terminal, each state a bar draws therefore ends its own line
(``_Lines``), at most one every ``FILE_INTERVAL`` seconds, so every warning starts a line."""

import contextvars
import sys
import threading
import time
from contextlib import contextmanager

from tqdm import tqdm

QUIET = False  # set by the CLI's --quiet and by tests (application-wide); library code uses quiet()
_scoped_quiet = contextvars.ContextVar("navapp_progress_quiet", default=False)
_scoped_aside: contextvars.ContextVar[threading.Event | None] = contextvars.ContextVar("navapp_progress_aside",
                                                                                      default=None)
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


@contextmanager
def aside(heard: threading.Event):
    """Work done beside the task being reported (e.g. a basis made ahead while a scene is
    simulated), in this thread / context: no bars, and nothing told to the listeners, whose
    one status line belongs to the main task, until ``heard`` is set — when the main task
    waits for this work, which is then the task (its steps and estimates reach the
    listeners; the terminal shows the steps' names through them)."""
    token, quiet_token = _scoped_aside.set(heard), _scoped_quiet.set(True)
    try:
        yield
    finally:
        _scoped_quiet.reset(quiet_token)
        _scoped_aside.reset(token)


def add_listener(fn):
    """Also report progress to ``fn(desc, fraction)``: fraction in [0, 1] for bars, None
    when a stage starts (no measurable progress). Returns ``fn`` (for remove_listener)."""
    _listeners.append(fn)
    return fn


def remove_listener(fn):
    if fn in _listeners:
        _listeners.remove(fn)


FILE_INTERVAL = 10.0
"""Seconds between two states of one bar written to a file (a terminal redraws 5 a second):
a log keeps a line per bar state, so fewer, and still a sign of life on a long stage."""


class _Lines:
    """stderr for a bar when it is not a terminal: a redraw (``\r`` + the bar) becomes the
    bar's text ending its line, and the blanking of a cleared bar (``\r`` + spaces, cursor
    moves), which only a terminal needs, is dropped; any other text passes as it is."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, s):
        s = str(s)
        if s.startswith(("\r", "\x1b[")):
            text = s.replace("\x1b[A", "").strip("\r").rstrip()
            if text:
                self._stream.write(text + "\n")
            return len(s)
        return self._stream.write(s)

    def flush(self):
        getattr(self._stream, "flush", lambda: None)()

    def __getattr__(self, name):  # encoding, isatty, fileno, … of the real stream
        return getattr(self._stream, name)


def _terminal() -> bool:
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):  # no stderr, or a closed one
        return False


def _stderr():
    """(the stream bars write to, the seconds between two of a bar's states)."""
    return (sys.stderr, 0.2) if _terminal() else (_Lines(sys.stderr), FILE_INTERVAL)


def _notify(desc, fraction):
    heard = _scoped_aside.get()
    if heard is not None and not heard.is_set():
        return
    for fn in list(_listeners):
        try:
            fn(desc, fraction)
        except Exception:  # a failing display must never stop a computation
            pass


class _Bar(tqdm):
    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.label, self.done = kw["desc"], 0  # tqdm keeps neither when disabled
        self.log = isinstance(kw.get("file"), _Lines)  # tqdm wraps the stream it is given

    def update(self, n=1):
        out = super().update(n)
        self.done += n
        if _listeners and self.total:
            _notify(self.label, min(1.0, self.done / self.total))
        return out

    def set_postfix_str(self, s="", refresh=True):
        # tqdm redraws on every postfix change, past ``mininterval``: LIBR's Ω each iteration
        # wrote a line per iteration to a log; the next timed redraw shows it there
        return super().set_postfix_str(s, refresh=refresh and not self.log)

    def to(self, n):
        """Move the bar to ``n`` done (the meshing bar follows a child's CPU seconds)."""
        if n > self.done:
            self.update(n - self.done)


def bar(total, desc, unit="it"):
    """A tqdm bar on stderr (hidden when ``is_quiet()``), also reported to the listeners."""
    _notify(desc, 0.0)
    stream, interval = _stderr()
    return _Bar(total=total, desc=desc, unit=unit, file=stream, disable=is_quiet(), leave=False,
                dynamic_ncols=True, mininterval=interval)


def work(desc, total):
    """A bar for work measured in seconds of CPU (e.g. a mesher in a child process against
    its expected CPU time): percentage, elapsed and ETA, no rate."""
    _notify(desc, 0.0)
    stream, interval = _stderr()
    return _Bar(total=total, desc=desc, file=stream, disable=is_quiet(), leave=False, dynamic_ncols=True,
                mininterval=max(0.5, interval), bar_format="{desc}: {percentage:3.0f}% [{elapsed}<{remaining}]")


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
    stream, interval = _stderr()

    def tick():
        with tqdm(desc=desc, bar_format="{desc}: {elapsed}", file=stream, disable=hidden, leave=False) as t:
            while not stop.wait(max(0.5, interval)):
                t.refresh()

    th = threading.Thread(target=tick, daemon=True)
    th.start()
    try:
        yield out
    finally:
        stop.set()
        th.join()
        out["seconds"] = time.perf_counter() - t0

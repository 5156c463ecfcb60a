"""Re-registration as the probe moves: the data kept so far (stylus points, frozen iUS
planes) plus the newest frame's contours, re-registered warm-started from the previous
state (rigid pose and β kept, ICP skipped, LM from β) on every new frame.

``navapp bench live`` (``evaluation.live_bench``) measures it; the viewer's "Re-register on
every frame" runs it. Calls ``pipeline.register`` unchanged.
"""

import os
import statistics
import time
from collections import deque
from contextlib import ExitStack
from dataclasses import replace

import numpy as np

from ..threads import limit_threads, split_kernels
from .libr import LMOptions
from .pipeline import Registration, register


def merge(*datasets) -> dict:
    """Feature-wise concatenation of data dictionaries (feature → (N, 3) mm)."""
    out: dict[str, np.ndarray] = {}
    for d in datasets:
        for k, v in (d or {}).items():
            v = np.asarray(v, float).reshape(-1, 3)
            if len(v):
                out[k] = np.vstack([out[k], v]) if k in out else v
    return out


def machine_busy() -> bool:
    """Whether the machine's runnable threads (the 1-minute load average) fill its cores: a
    second thread would wait its turn, so an update is not split (``SecondCore``)."""
    try:
        return os.getloadavg()[0] >= (os.cpu_count() or 1)
    except OSError:  # no load average on this system: let the timings decide
        return False


class SecondCore:
    """Whether the next update splits its compiled kernels among threads (``split_kernels``)
    or runs on one: whichever has been faster per LM iteration lately, on this machine now.
    Both give the same bits, so the choice is speed alone. The second core pays only where the
    machine runs the helper thread at once: on this project's 2-core machine under other work
    (load 10–16) splitting every update made it 1.5× slower, trying it now and then cost ~10 %
    CPU (docs/decisions/speed.md, "The live update on two cores").

    The two ways alternate until each has ``keep`` timings; then the faster by the median of
    its last ``keep`` runs, with the other tried every ``probe_every``-th update, so a change in
    the machine's load turns the choice within a few probes. While ``busy()`` (default: the
    load average fills the cores) nothing is split or tried."""

    def __init__(self, keep: int = 5, probe_every: int = 10, busy=machine_busy):
        self.times: dict[bool, deque] = {True: deque(maxlen=keep), False: deque(maxlen=keep)}
        self.keep, self.probe_every, self.busy = keep, probe_every, busy
        self.updates = 0

    def faster(self) -> bool:
        """True: splitting has the lower median of its last timings."""
        return statistics.median(self.times[True]) <= statistics.median(self.times[False])

    def pick(self) -> bool:
        """True: split the next update."""
        if self.busy():
            return False
        self.updates += 1
        short = [way for way in (True, False) if len(self.times[way]) < self.keep]
        if short:
            return short[0] if len(short) == 1 else self.updates % 2 == 1
        best = self.faster()
        return (not best) if self.updates % self.probe_every == 0 else best

    def record(self, split: bool, seconds_per_iteration: float) -> None:
        self.times[split].append(seconds_per_iteration)


class LiveRegistration:
    """``base``: data that stays (tracker space, mm); ``update(frame)`` registers base ∪
    frame, warm-started from the last result (cold the first time). ``threads``: how many
    threads an update may use: its compiled kernels split among them (``threads.split_kernels``;
    the same bits) where ``SecondCore`` finds that faster (``adapt``; False: always), the BLAS /
    OpenMP pools held at one (threadpoolctl: two BLAS threads sum otherwise, and JᵀWJ at the
    demo's 2,184 × 141 took 1.17 against 1.01 ms on them). None: the kernels on all cores, the
    pools as installed. ``iterations_per_frame``: LM iterations per update
    (None: to convergence). One is the
    default: the next frame continues from there, so the fit converges across frames —
    measured by ``navapp bench live`` on the demo liver with stylus + 3 planes: 22.6 ms
    per update against 35.6 ms for the two iterations a converged warm start takes, the same
    TRE (2.56 mm) after the last frame. Call ``settle()`` for a converged fit (e.g. when
    the probe rests or the image is frozen)."""

    def __init__(self, model, base: dict | None = None, options=None, threads: int | None = 2,
                 iterations_per_frame: int | None = 1, adapt: bool = True):
        self.model, self.threads = model, threads
        self.second_core = SecondCore() if adapt else None
        self.options = options or LMOptions()
        self.frame_options = (replace(self.options, max_iterations=iterations_per_frame)
                              if iterations_per_frame else self.options)
        self.frame: dict | None = None
        self.base = merge(base)
        self.last: Registration | None = None
        self.history: list = []  # (seconds, iterations) per update
        self.split: list[bool] = []  # per update: its kernels split among threads

    def _limits(self, split: bool):
        stack = ExitStack()
        if self.threads:
            stack.enter_context(limit_threads(1))
        stack.enter_context(split_kernels(self.threads if split else 1))
        return stack

    def _split(self) -> bool:
        """Whether the next update splits its kernels (``SecondCore``'s pick where it adapts)."""
        if self.threads == 1:
            return False
        return self.second_core.pick() if self.second_core is not None else True

    def register(self, frame: dict | None = None):
        """Cold registration (multi-start rigid + LIBR) of base ∪ frame."""
        self.frame = frame
        # one cold registration: split only where the choice has found that faster
        choice = self.second_core
        split = self.threads != 1 and (choice is None or (min(map(len, choice.times.values())) == choice.keep
                                                         and choice.faster() and not choice.busy()))
        with self._limits(split):
            t = time.perf_counter()
            self.last = register(self.model, merge(self.base, frame), options=self.options)
            self.history.append((time.perf_counter() - t, self.last.libr.iterations if self.last.libr else 0))
        return self.last

    def update(self, frame: dict, options=None):
        """Warm-started re-registration with the newest frame's data."""
        last = self.last
        if last is None or last.libr is None:
            return self.register(frame)
        self.frame = frame
        split = self._split()
        with self._limits(split):
            t = time.perf_counter()
            reg = register(self.model, merge(self.base, frame), options=options or self.frame_options,
                           beta0=last.libr.beta, rigid=last.rigid)
            seconds, iterations = time.perf_counter() - t, reg.libr.iterations if reg.libr else 0
        self.history.append((seconds, iterations))
        self.split.append(split)
        if self.second_core is not None and self.threads != 1:
            self.second_core.record(split, seconds / max(iterations, 1))
        self.last = reg
        return reg

    def settle(self):
        """Converge on the current data (warm-started, no iteration cap)."""
        return self.update(self.frame or {}, self.options)

    def keep(self, frame: dict):
        """Freeze a frame's data into the base (the user keeps this plane)."""
        self.base = merge(self.base, frame)

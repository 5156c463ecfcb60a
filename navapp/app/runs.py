"""Registration runs in the viewer: what kind of run, the run in progress, the row it
leaves in the session's log, and starting, streaming, cancelling and finishing one (and
the cost sweep, which uses the same worker). No viser here.

A run's kind is a ``RunKind``; its ``label`` is only what the run table shows and the
session file stores. The worker thread streams states into ``Run`` under the shared lock;
every view reads the run through ``Core.run``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

from ..errors import NavappError
from ..evaluation.cost import lm_sweep
from ..registration.pipeline import Registration
from ..registration.rigid import RigidResult
from .state import Change, RegisteredState
from .worker import Update, cancelled

if TYPE_CHECKING:
    from .server import App

MIN_POINTS = 3  # fewer data points than this fix nothing


class RunKind(Enum):
    """What a run fits with what; the value is the button's key, ``label`` the words shown."""

    RIGID = "rigid"
    SURFACE = "surface"
    ALL = "all"
    WARM = "warm"
    LIVE = "live"
    RESTORED = "restored"

    @property
    def label(self) -> str:
        return _LABELS[self]

    @property
    def deformable(self) -> bool:
        return self is not RunKind.RIGID

    @staticmethod
    def from_label(label: str) -> RunKind:
        """The kind a stored label names (session files store labels); unknown: RESTORED."""
        return next((k for k, v in _LABELS.items() if v == label), RunKind.RESTORED)


_LABELS = {RunKind.RIGID: "rigid", RunKind.SURFACE: "deformable, surface", RunKind.ALL: "deformable, all data",
           RunKind.WARM: "deformable, all data (warm)", RunKind.LIVE: "live (every frame)",
           RunKind.RESTORED: "restored"}


@dataclass
class Run:
    """The registration in progress (written by the worker thread under ``Core.lock``)."""

    kind: RunKind
    points: int
    t0: float
    trace: list[tuple[float, float]] = field(default_factory=list)  # (seconds, mean true error mm) per state
    streamed: int = 0  # states received from the worker
    iteration: int = 0
    omega: float = float("nan")
    error: np.ndarray | None = None  # (M,) true error at the mesh nodes of the latest state
    state: tuple[RigidResult, np.ndarray | None] | None = None  # the latest state (rigid pose, β)


@dataclass
class RunEntry:
    """One row of the run table (the session's log)."""

    run: str  # RunKind.label
    points: int
    seconds: float
    iterations: int
    stop: str  # the LM stop reason, "rigid" for a rigid-only run
    updates_streamed: int = 0
    cancelled: bool = False
    trace: list[list[float]] = field(default_factory=list)  # [[seconds, mean error mm]]
    warning: str | None = None  # the fit-quality check's warning
    error_mean_mm: float | None = None  # against the truth, simulated scenes only
    error_max_mm: float | None = None
    live: str | None = None  # a live re-registration's summary
    note: str = ""

    @property
    def kind(self) -> RunKind:
        return RunKind.from_label(self.run)

    @staticmethod
    def of(kind: RunKind, reg: Registration, points: int, seconds: float, error: np.ndarray | None = None,
           streamed: int = 0, trace=(), live: str | None = None) -> RunEntry:
        """The row of a finished (or cancelled) registration; ``error`` (M,) its true error."""
        lm = reg.libr
        stopped = cancelled(reg)
        e = RunEntry(kind.label, int(points), round(float(seconds), 3), lm.iterations if lm else 0,
                     lm.stop_reason if lm else "rigid", streamed, stopped,
                     [[round(t, 3), round(v, 3)] for t, v in trace],
                     reg.quality.warning if reg.quality is not None and reg.quality.warning else None)
        if error is not None and not stopped:
            e.error_mean_mm, e.error_max_mm = round(float(error.mean()), 3), round(float(error.max()), 3)
        if live is not None:
            e.live, e.note = live, live.split(",")[0]
        return e

    def to_json(self) -> dict:
        d = {"run": self.run, "points": self.points, "seconds": self.seconds, "iterations": self.iterations,
             "stop": self.stop, "updates_streamed": self.updates_streamed, "cancelled": self.cancelled,
             "trace": self.trace}
        for k in ("warning", "error_mean_mm", "error_max_mm", "live"):
            if getattr(self, k) is not None:
                d[k] = getattr(self, k)
        if self.note:
            d["note"] = self.note
        return d

    @staticmethod
    def from_json(d: dict) -> RunEntry:
        return RunEntry(str(d["run"]), int(d["points"]), float(d["seconds"]), int(d["iterations"]), str(d["stop"]),
                        int(d.get("updates_streamed", 0)), bool(d.get("cancelled", False)),
                        [list(map(float, x)) for x in d.get("trace", [])], d.get("warning"),
                        d.get("error_mean_mm"), d.get("error_max_mm"), d.get("live"), str(d.get("note", "")))


class Runs:
    """Starting, streaming, cancelling and finishing registrations; the cost sweep."""

    def __init__(self, app: App):
        self.app, self.core = app, app.core

    def start(self, kind: RunKind) -> str | None:
        """Start a registration; returns why it could not start, or None."""
        core = self.core
        worker = core.worker
        if worker is None:
            return "Still preparing the registration model."
        data = core.data(surface_only=kind is RunKind.SURFACE)
        npts = sum(len(v) for v in data.values())
        if npts < MIN_POINTS:
            return "Collect data first (stylus sweep or an ultrasound plane)."
        if worker.busy:
            return "A registration is already running; wait for it or cancel it."
        if self.app.live.following:
            return "Live re-registration is on (Live tracking panel): switch it off first."
        if kind is RunKind.WARM and worker.last is None:
            kind = RunKind.ALL
        with core.lock:
            core.run = Run(kind, npts, time.monotonic())
        if not worker.start(data, deform=kind.deformable, warm=kind is RunKind.WARM):
            return "A registration is already running; wait for it or cancel it."
        core.changed(Change.RUN)
        return None

    def cancel(self):
        if self.core.worker is not None:
            self.core.worker.cancel()

    # ------------------------------------------------------------------ from the worker thread
    def on_update(self, u: Update):
        core, shown = self.core, self.app.shown
        rigid = u.rigid
        assert rigid is not None  # every streamed state has its rigid pose
        err = shown.node_error(rigid, u.beta)
        with core.lock:
            run = core.run
            if run is None:
                return
            run.streamed += 1
            run.iteration, run.omega = u.iteration, u.omega
            if err is not None:
                run.trace.append((u.elapsed, float(err.mean())))
                run.error = err
            run.state = (rigid, u.beta)
        geom = shown.geometry(rigid, u.beta, surfaces={"liver": u.liver, **(u.vessels or {})})
        core.each_view(lambda v: v.show_update(u, geom))

    def on_done(self, reg: Registration):
        core, shown = self.core, self.app.shown
        with core.lock:
            run = core.run
        assert run is not None  # set before the worker started
        stopped = cancelled(reg)
        beta = reg.libr.beta if reg.libr is not None else None
        err = None if stopped else shown.node_error(reg.rigid, beta)
        entry = RunEntry.of(run.kind, reg, run.points, time.monotonic() - run.t0, err, run.streamed, run.trace)
        if not stopped:
            result = RegisteredState(run.kind.label, reg.rigid, beta, err, *shown.predict(reg))
            with core.lock:
                core.result, core.last_reg = result, reg
                core.need_session().result = result.to_json()
        with core.lock:
            core.need_session().log.append(entry)
            core.run = None
        core.changed(Change.RESULT)
        if not stopped:
            self.app.slicer.send(reg)
        if stopped:
            core.notify("Registration", "Cancelled: the previous result is kept.")
        elif entry.warning:
            core.notify("Registration: check the fit", entry.warning, error=True)

    def on_error(self, exc: BaseException):
        msg = str(exc) if isinstance(exc, NavappError) else f"{exc.__class__.__name__}: {exc}"
        core = self.core
        with core.lock:
            core.run = None
        core.notify("Registration failed", msg, error=True)
        core.changed(Change.RUN)

    # ------------------------------------------------------------------ cost sweep
    def sweep(self, on_row=None, on_done=None) -> str | None:
        """Rerun the current data with the LM iteration cap and tolerance varied (``evaluation.cost``)."""
        core = self.core
        model, worker, truth = core.model, core.worker, core.truth_nodes
        if model is None or worker is None or truth is None:
            return "This panel needs the true deformation (simulated scenes)."
        data = core.data()
        if sum(len(v) for v in data.values()) < MIN_POINTS:
            return "Collect data first."
        import scipy.sparse as sp

        x0 = model.basis.nodes
        B = sp.identity(len(x0), format="csr")  # the truth is known at the mesh nodes themselves
        ok = worker.submit(lambda cancel: lm_sweep(model, data, x0, truth, cancel=cancel, on_row=on_row, B=B),
                           on_done)
        return None if ok else "A registration is running; try again when it has finished."

"""Registration in a worker thread, for the viewer: one run at a time, per-iteration
updates throttled to at most ``max_rate_hz`` (latest wins, the final state always
delivered), cancellation within one LM iteration (a cancelled run is reported to ``on_done`` but does
not replace the last result), errors reported instead of lost. Every run streams its
starting state (the rigid pose or the warm start) first.

No viser here: the server wires ``on_update`` / ``on_done`` / ``on_error`` to the scene.
"""

import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from ..anatomy.model import VESSELS
from ..registration.libr import LMOptions
from ..registration.model import RegistrationModel
from ..registration.objective import robust_weights
from ..registration.pipeline import Registration, RobustOptions, register
from ..registration.prior import PosePrior
from ..registration.rigid import RigidResult


@dataclass
class Update:
    iteration: int
    omega: float
    elapsed: float  # seconds since the run started
    liver: np.ndarray  # (V, 3) deformed liver-surface nodes (the tet boundary), tracker space, mm
    final: bool = False
    vessels: dict | None = None  # "portal" / "hepatic" → (V, 3) deformed vessel-surface vertices, mm
    beta: np.ndarray | None = None  # the state β (None for a rigid-only result)
    rigid: RigidResult | None = None  # the rigid pose of this state
    model: RegistrationModel | None = None  # the model β is in (the run's: its basis held at the stated supports)


def viewer_options() -> LMOptions:
    """The viewer's fits: robust on every feature (``objective.robust_weights``: Huber and
    outlier rejection), as one wrong click on an image is one slip of the hand away; the
    salient features keep the pipeline's Huber δ (``RobustOptions.huber_salient_mm``)."""
    return LMOptions(weights=robust_weights(RobustOptions().huber_salient_mm or 1.0))


def cancelled(reg: Registration) -> bool:
    """Whether a registration was stopped by the user before it converged."""
    return reg.libr is not None and reg.libr.stop_reason == "cancelled"


class RegistrationWorker:
    """Runs ``pipeline.register`` on a registration model in a background thread."""

    def __init__(self, model, on_update=None, on_done=None, on_error=None, max_rate_hz=20.0):
        self.model = model
        self.on_update = on_update or (lambda u: None)
        self.on_done = on_done or (lambda r: None)
        self.on_error = on_error or (lambda e: None)
        self.interval = 1.0 / max_rate_hz
        self._thread = None
        self._cancel = threading.Event()
        self._lock = threading.Lock()
        # set when the running registration's result is decided (kept or cancelled): a Cancel
        # after it is refused, so "the previous result is kept" is never followed by the new one
        self._decided = True
        self.last: Registration | None = None

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, data: dict, deform=True, warm=False, options: LMOptions | None = None,
              pose_prior: PosePrior | None = None, given: RigidResult | None = None,
              model: RegistrationModel | None = None) -> bool:
        """Start a run; returns False, starting nothing, while another run is going.
        ``warm`` continues from the last result's rigid pose and β (e.g. after adding a plane),
        in the last result's model. ``model``: a fresh run's model (default the worker's, the
        free-floating one; the viewer passes the one held at the stated supports).
        ``pose_prior``: what is known of the pose (``register(pose_prior=)``), about ``given``
        (the previous registration's pose) or, without it, the data's own frame; a warm run
        carries the last run's prior, centred on its pose, while one is stated."""
        with self._lock:
            if self.busy:
                return False
            self._cancel.clear()
            self._decided = not deform  # a rigid registration has no iteration to stop at
            prev = self.last if warm else None
            run_model = prev.model if prev is not None else (model or self.model)
            self._thread = threading.Thread(target=self._run, daemon=True, args=(
                data, deform, prev, options or viewer_options(), pose_prior, given, run_model))
            self._thread.start()
            return True

    def cancel(self) -> bool:
        """Ask the running fit or job to stop at its next iteration boundary. Returns False,
        asking nothing, when nothing is running or the running registration's result is
        already decided (it finished, or it is rigid); a run asked in time is reported
        cancelled even if it was past its last check, and never becomes the state."""
        with self._lock:
            if not self.busy or self._decided:
                return False
            self._cancel.set()
            return True

    @property
    def cancel_requested(self) -> bool:
        """Whether the latest run or job was asked to stop (until the next one starts)."""
        return self._cancel.is_set()

    def join(self, timeout=None):
        if self._thread is not None:
            self._thread.join(timeout)

    def surfaces(self, rigid, beta, model: RegistrationModel | None = None) -> dict:
        """"liver" (the tet boundary) / "portal" / "hepatic" → (V, 3) vertices of the
        registration model's surfaces at state β (None: rigid only), tracker space, mm.
        ``model``: the one β is in (default the worker's)."""
        model = model or self.model
        out = {}
        for name in ("liver", *VESSELS):
            f = model.features.get(name)
            if f is not None:
                out[name] = rigid.apply(f.rest if beta is None else model.positions(f, beta)[1])
        return out

    def _state(self, iteration, omega, t0, rigid, beta, model, final=False) -> Update:
        s = self.surfaces(rigid, beta, model)
        return Update(iteration, omega, time.monotonic() - t0, s.pop("liver"), final, s,
                      None if beta is None else np.array(beta), rigid, model)

    def submit(self, job, on_done=None, on_error=None) -> bool:
        """Run ``job(cancel_event)`` (e.g. a settings sweep) in the worker thread, under the
        same one-at-a-time rule as registrations; its return value goes to ``on_done``, an
        exception to the worker's ``on_error`` and then to this job's own ``on_error``."""
        with self._lock:
            if self.busy:
                return False
            self._cancel.clear()
            self._decided = False  # a job (the sweep) stops at its next setting whenever asked

            def run():
                try:
                    out = job(self._cancel)
                    (on_done or (lambda r: None))(out)
                except Exception as exc:
                    self.on_error(exc)
                    if on_error is not None:
                        on_error(exc)

            self._thread = threading.Thread(target=run, daemon=True)
            self._thread.start()
            return True

    def _run(self, data, deform, prev, options, pose_prior, given, model):
        t0 = time.monotonic()
        last_sent = -np.inf
        try:
            if prev is not None:
                rigid_run, rigid = None, prev.rigid
                prior = (prev.pose_prior or pose_prior) if pose_prior is not None else None
            else:
                rigid_run = register(model, data, deform=False, options=options, pose_prior=pose_prior,
                                     given=given)
                rigid, prior = rigid_run.rigid, rigid_run.pose_prior
            if not deform:
                reg = rigid_run or register(model, data, deform=False, options=options, rigid=rigid,
                                            pose_prior=prior)
                final = self._state(0, float("nan"), t0, rigid, None, reg.model, True)
            else:
                def on_iteration(p):
                    nonlocal last_sent
                    now = time.monotonic()
                    if now - last_sent >= self.interval:  # otherwise dropped: the next state supersedes it
                        last_sent = now
                        # the model β is in: the free-floating one once the data contradicted the supports
                        self.on_update(self._state(p.iteration, p.omega, t0, rigid, p.beta, p.model or model))

                beta0 = prev.libr.beta if prev is not None and prev.libr is not None else None
                # the starting state (the rigid pose, or the warm start) is always shown first
                self.on_update(self._state(0, float("nan"), t0, rigid, beta0, model))
                last_sent = time.monotonic()
                if prev is None and pose_prior is not None:
                    # the declared path whole, as ``navapp register`` runs it (the deformable fit's
                    # own noise scale, ``pipeline._settle_scale``); its rigid stage is the one above
                    reg = register(model, data, deform=True, options=options, callback=on_iteration,
                                   cancel=self._cancel, pose_prior=pose_prior, given=given, undeclared=self.model)
                    rigid = reg.rigid
                else:
                    reg = register(model, data, deform=True, options=options, callback=on_iteration,
                                   cancel=self._cancel, beta0=beta0, rigid=rigid, pose_prior=prior,
                                   undeclared=self.model)
                lm = reg.libr
                assert lm is not None  # a deformable run has an LM result
                # the answer's own model: the free-floating one where the data contradicted the supports
                final = self._state(lm.iterations, lm.omega, t0, rigid, lm.beta, reg.model, True)
            with self._lock:  # the decision: a Cancel before it stops the run, one after it is refused
                if self._cancel.is_set() and reg.libr is not None and not cancelled(reg):
                    # asked after LM's and the checks' last look at the event (the last fold fit,
                    # the organ's predicted error): the surgeon was told the previous result is kept
                    reg.libr = replace(reg.libr, stop_reason="cancelled")
                self._decided = True
            if not cancelled(reg):  # a cancelled run is reported but never becomes the state to continue from
                self.last = reg
                self.on_update(final)
            self.on_done(reg)
        except Exception as exc:  # surfaced to the UI as a notification, never a dead thread
            self.on_error(exc)

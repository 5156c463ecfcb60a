"""Levenberg–Marquardt over β = (α, τ, θ) (paper eq. 14) with trust-region control of λ.

Step: (JᵀWJ + λ·diag(JᵀWJ)) Δ = −JᵀW f. The step is accepted when the objective, with
correspondences recomputed at β + Δ, falls; λ shrinks when the actual reduction matches
the linear model's prediction well (ratio ρ > 0.75) and grows when it does not (ρ < 0.25)
or the step is rejected. Stop reasons: "converged" (|ΔΩ| < tol on an accepted step),
"max_iterations", "stalled" (λ grew past 1e16 without an accepted step), "no_data",
"cancelled".
"""

import threading
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from threadpoolctl import threadpool_limits

from .model import RegistrationModel
from .objective import Weights, evaluate


@dataclass
class LMOptions:
    tol: float = 1e-12  # on |ΔΩ| (Ω dimensionless, SI)
    max_iterations: int = 100
    lam0: float = 1e-3
    weights: Weights = field(default_factory=Weights)
    deform: bool = True  # False: only τ, θ move (a rigid fit through the same machinery)


@dataclass
class Progress:
    iteration: int
    beta: np.ndarray
    omega: float
    features: dict
    elapsed: float
    accepted: bool
    lam: float


@dataclass
class LibrResult:
    beta: np.ndarray
    omega: float
    iterations: int
    stop_reason: str
    history: list  # Ω after every accepted step, starting with Ω(β0)
    features: dict
    seconds: float
    timings: dict  # seconds spent in deform / closest / jacobian / solve


def _solve(A, g):
    """Solve the damped normal equations; fall back to least squares when singular."""
    try:
        return sla.solve(A, g, assume_a="pos", check_finite=False)
    except (sla.LinAlgError, ValueError):
        return sla.lstsq(A, g, check_finite=False)[0]


def register_libr(model: RegistrationModel, data: dict, beta0=None, options: LMOptions = LMOptions(),
                  callback=None, cancel: threading.Event | None = None) -> LibrResult:
    """Fit β to ``data`` (feature → (N, 3) mm, in the model's frame).

    ``callback(Progress)`` is called after every iteration (accepted or not); setting
    ``cancel`` stops the fit at the next iteration boundary with the best β so far.
    BLAS is pinned to one thread inside: the matrices here are small (≈141 columns) and
    threaded BLAS spent ~20× longer synchronising than computing on a 2-core machine.
    """
    with threadpool_limits(1):
        return _register(model, data, beta0, options, callback, cancel)


def _register(model, data, beta0, options, callback, cancel):
    n = model.basis.Ju.shape[1]
    start = time.perf_counter()
    beta = np.zeros(n + 6) if beta0 is None else np.array(beta0, float)
    if beta.shape != (n + 6,) or not np.isfinite(beta).all():
        raise ValueError(f"beta0 must be finite with length {n + 6}")
    free = np.ones(n + 6, bool)
    if not options.deform:
        free[:n] = False
    tim = {"deform": 0.0, "closest": 0.0, "jacobian": 0.0, "solve": 0.0}

    def run(b, jac=True):
        ev = evaluate(model, data, b, options.weights, jacobian=jac)
        for k, v in ev.timings.items():
            tim[k] += v
        return ev

    ev = run(beta)
    history = [ev.omega]
    if not data:
        return LibrResult(beta, ev.omega, 0, "no_data", history, ev.features, time.perf_counter() - start, tim)
    lam = options.lam0
    reason = "max_iterations"
    it = 0
    for it in range(1, options.max_iterations + 1):
        if cancel is not None and cancel.is_set():
            reason = "cancelled"
            it -= 1
            break
        t0 = time.perf_counter()
        J = ev.J[:, free]
        JW = J.T * ev.w
        A = JW @ J
        g = -JW @ ev.f
        d = np.diag(A).copy()
        d = np.maximum(d, 1e-12 * max(d.max(), 1e-300))
        step = np.zeros(n + 6)
        step[free] = _solve(A + lam * np.diag(d), g)
        tim["solve"] += time.perf_counter() - t0
        trial = beta + step
        if not np.isfinite(step).all():
            lam *= 10
            accepted = False
        else:
            ev_new = run(trial)
            lin = ev.f + ev.J @ step
            predicted = ev.omega - float(ev.w @ (lin * lin))
            actual = ev.omega - ev_new.omega
            accepted = actual > 0 and np.isfinite(ev_new.omega)
            rho = actual / predicted if predicted > 0 else 0.0
            if accepted:
                beta, ev = trial, ev_new
                history.append(ev.omega)
                lam = lam / 3 if rho > 0.75 else (lam * 2 if rho < 0.25 else lam)
                lam = max(lam, 1e-12)
            else:
                lam *= 4
        if callback is not None:
            callback(Progress(it, beta.copy(), ev.omega, ev.features, time.perf_counter() - start, accepted, lam))
        if accepted and abs(actual) < options.tol:
            reason = "converged"
            break
        if not accepted and (lam > 1e16 or ev.omega == 0.0):
            reason = "converged" if ev.omega == 0.0 else "stalled"
            break
    return LibrResult(beta, ev.omega, it, reason, history, ev.features, time.perf_counter() - start, tim)

"""Levenberg–Marquardt over β = (α, τ, θ) (paper eq. 14) with trust-region control of λ.

Each iteration recomputes the closest-point correspondences at the current β (the paper's
S_i "updated every iteration"), then takes the step
    (JᵀWJ + λ·diag(JᵀWJ) + C) Δ = −JᵀW f.
Choices where the paper is open:
- the trust-region ratio ρ compares the decrease of Ω with the *same* correspondences
  (held fixed within the iteration, as the normals and tangents are) to the decrease the
  linear model predicts; with correspondences recomputed inside the ratio, Ω jumps where
  a closest point changes triangle and ρ is noise. ρ > 0.75 shrinks λ (÷3), ρ < 0.25 grows
  it (×2), a rejected step grows it ×4;
- C = w_E f_E ∇²f_E = w_E f_E J_σᵀJ_ε / M is the part of the exact Hessian of the
  strain-energy term that Gauss–Newton drops. f_E is quadratic in α, so w_E f_E² is
  quartic, and without C the model underestimates it and λ must stay large (more
  iterations; docs/decisions/registration.md). It changes the path, not the objective;
  ``LMOptions(energy_curvature=False)`` gives the plain step of eq. 14.

Stop reasons (``STOP_REASONS``): "converged" (|ΔΩ| < tol on an accepted step, or Ω = 0),
"stationary" (|ΔΩ| < rtol · Ω on two accepted steps in a row), "max_iterations",
"stalled" (λ grew past 1e16 without an accepted step), "no_data", "cancelled".
"""

import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from scipy.linalg import lapack

from ..defaults import LM_MAX_ITERATIONS
from ..threads import both, limit_threads
from .model import RegistrationModel
from .objective import Evaluation, Weights, add_jacobian, evaluate, keep_end


@dataclass
class LMOptions:
    """Settings of the Levenberg–Marquardt fit of β (paper eq. 14).

    ``tol`` on |ΔΩ| (the paper's rule) and ``rtol`` on |ΔΩ| / Ω twice in a row end the fit;
    ``weights`` holds w_F (m⁻²) and w_E (Pa⁻²) of eq. 7; ``deform=False`` fits only τ, θ.
    """

    tol: float = 1e-12  # on |ΔΩ| (Ω dimensionless, SI), the paper's rule
    # on |ΔΩ| / Ω, twice in a row: correspondence switching keeps Ω jittering far above tol.
    # 0.1, not 0.01: a few hundredths of a mm of TRE for fewer iterations (docs/decisions/registration.md)
    rtol: float = 1e-1
    max_iterations: int = LM_MAX_ITERATIONS
    lam0: float = 1e-2
    weights: Weights = field(default_factory=Weights)
    deform: bool = True  # False: only τ, θ move (a rigid fit through the same machinery)
    pose: bool = True  # False: τ, θ stay at β0's (the rigid stage's pose is kept; only α moves)
    recompute_in_ratio: bool = False  # True: ρ from Ω with recomputed correspondences (for comparison)
    energy_curvature: bool = True  # add w_E f_E ∇²f_E to JᵀWJ (see module doc)
    condition: bool = False  # report LibrResult.condition (one small eigen-decomposition per iteration)


STOP_REASONS = ("converged", "stationary", "max_iterations", "stalled", "no_data", "cancelled")


@dataclass
class Progress:
    iteration: int
    beta: np.ndarray
    omega: float
    features: dict
    elapsed: float
    accepted: bool
    lam: float
    model: RegistrationModel | None = None  # the model β is in (a caller may fit more than one in turn)


@dataclass
class LibrResult:
    """A LIBR fit: ``beta`` (3k + 6,) = (α, τ mm, θ rad) of eq. 8 in the model frame, its Ω
    (eq. 7, dimensionless), the ``stop_reason`` (``STOP_REASONS``) and per-feature residuals."""

    beta: np.ndarray
    omega: float
    iterations: int
    stop_reason: str
    history: list  # Ω after every accepted step (correspondences recomputed), from Ω(β0)
    steps: list  # per accepted step: (Ω before, Ω after with that iteration's correspondences)
    features: dict
    seconds: float
    # seconds in deform / kdtree (the surfaces' hierarchy refit; a centerline's k-d tree built
    # and queried) / closest (the exact points, normals, tangents) / jacobian / solve
    timings: dict
    # 2-norm condition number of the last undamped LM matrix JᵀWJ + C, Jacobi-scaled (unit
    # diagonal, so units of α, τ, θ do not count); inf when singular. Only with LMOptions(condition=True)
    condition: float | None = None


_posv, _pocon, _lange = lapack.get_lapack_funcs(("posv", "pocon", "lange"), (np.empty((1, 1)),))
_EPS = float(np.finfo(float).eps)


def _solve(A, g):
    """Solve the damped normal equations; minimum-norm least squares when (near) singular,
    e.g. collinear data leave a rotation undetermined.

    LAPACK's Cholesky solve (posv, upper triangle) and its reciprocal condition estimate
    (pocon) called directly: what ``scipy.linalg.solve(assume_a="pos")`` does, with its rule
    (not positive definite, or rcond below machine ε: least squares instead) and the same
    bits, at half its cost for LM's 141 × 141 (0.09 against 0.19 ms; docs/decisions/speed.md,
    "Issue 49, session 38")."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a non-finite A: to least squares, as before
        c, x, info = _posv(A, g, lower=False)
        if info == 0:
            rcond, info = _pocon(c, _lange("1", A))  # the upper factor
            if info == 0 and not rcond < _EPS:  # as SciPy: NaN (a non-finite A) is not "ill-conditioned"
                return x
    return sla.lstsq(A, g, check_finite=False)[0]


# Rows from which LM's JᵀWJ is summed as two halves of rows, one beside the other where a live
# update splits its kernels (``threads.both``); below it the hand-over costs more than the half
# saves (docs/decisions/speed.md, "JᵀWJ in two halves of rows").
GRAM_HALVES_MIN = 1024


def gram(Js: np.ndarray) -> np.ndarray:
    """(√W J)ᵀ(√W J) of eq. 14's normal equations.

    Parameters
    ----------
    Js : (m, p) float
        √W J, rows the residuals, columns the free parameters of β.

    Returns
    -------
    (p, p) float
        Symmetric. From ``GRAM_HALVES_MIN`` rows, the sum of the two halves' products (each by
        BLAS's rank-k update), whether or not they run side by side, so the bits do not depend on
        the thread an update was given."""
    m = len(Js)
    if m < GRAM_HALVES_MIN:
        return Js.T @ Js
    cut = m // 2
    top, bottom = np.empty((2, Js.shape[1], Js.shape[1]))
    both(lambda: np.matmul(Js[:cut].T, Js[:cut], out=top), lambda: np.matmul(Js[cut:].T, Js[cut:], out=bottom))
    top += bottom
    return top


def register_libr(model: RegistrationModel, data: dict, beta0=None, options: LMOptions | None = None,
                  callback=None, cancel: threading.Event | None = None, first: Evaluation | None = None) -> LibrResult:
    """Fit β to ``data`` (feature → (N, 3) mm, in the model's frame).

    ``callback(Progress)`` is called after every iteration (accepted or not); setting
    ``cancel`` stops the fit at the next iteration boundary with the best β so far.
    ``first``: the evaluation at β0 of these data with its Jacobian, when the caller has it
    (``objective.points_of``: a cross-validation fold's rows of one evaluation of all data);
    the fit is then the one it would be without it, that evaluation not made again.
    BLAS is pinned to one thread inside: the matrices here are small (≈141 columns) and
    threaded BLAS spent ~20× longer synchronising than computing on a 2-core machine.
    """
    with limit_threads(1):
        return _register(model, data, beta0, options or LMOptions(), callback, cancel, first)


def _register(model, data, beta0, options, callback, cancel, first=None):
    n = model.basis.Ju.shape[1]
    start = time.perf_counter()
    beta = np.zeros(n + 6) if beta0 is None else np.array(beta0, float)
    if beta.shape != (n + 6,) or not np.isfinite(beta).all():
        raise ValueError(f"beta0 must be finite with length {n + 6}")
    free = np.ones(n + 6, bool)
    if not options.deform:
        free[:n] = False
    if not options.pose:
        free[n:] = False
    tim = {"deform": 0.0, "kdtree": 0.0, "closest": 0.0, "jacobian": 0.0, "solve": 0.0}
    # a fit that holds α at zero (a rigid fit from β = 0) needs only J's pose columns
    alpha_columns = options.deform or bool(beta[:n].any())

    def run(b, jac=True, frozen=None, scales=None, warm=None):
        ev = evaluate(model, data, b, options.weights, jacobian=jac, frozen=frozen, scales=scales,
                      alpha_columns=alpha_columns, warm=warm)
        for k, v in ev.timings.items():
            tim[k] += v
        return ev

    if first is not None and not (first.J is not None and np.array_equal(first.beta, beta)
                                  and list(first.correspondence) == list(data)):
        raise ValueError("register_libr: first must be an evaluation of these data at beta0, with its Jacobian")
    ev = run(beta) if first is None else first
    history = [ev.omega]
    prev_omega = ev.omega
    best = (ev.omega, beta.copy(), ev.features)
    quiet = 0
    steps = []
    if not data:
        return LibrResult(beta, ev.omega, 0, "no_data", history, [], ev.features, time.perf_counter() - start, tim)
    lam = options.lam0
    reason = "max_iterations"
    condition = None
    it = 0
    for it in range(1, options.max_iterations + 1):
        if cancel is not None and cancel.is_set():
            reason = "cancelled"
            it -= 1
            break
        t0 = time.perf_counter()
        if ev.J is None:
            add_jacobian(model, ev, alpha_columns)
            tim["jacobian"] += time.perf_counter() - t0
            t0 = time.perf_counter()
        J = ev.J if free.all() else ev.J[:, free]
        # JᵀWJ as (√W J)ᵀ(√W J): NumPy hands a product of an array's transpose with itself to
        # BLAS's symmetric rank-k update, half of the general product's work (1.5 against
        # 2.4 ms for the live demo's 2,184 × 141 on one thread; docs/decisions/speed.md)
        if ev.Js is None:
            Js = J * np.sqrt(ev.w)[:, None]
        else:  # made with J (``add_jacobian``): the same bits, without another pass over J
            Js = ev.Js if free.all() else ev.Js[:, free]
        A = gram(Js)
        g = -(J.T @ (ev.w * ev.f))
        if options.energy_curvature and options.deform:
            fE, wE = ev.f[-1], ev.w[-1]
            A[:n, :n] += wE * fE * model.basis.energy / model.basis.M
        d = np.diag(A).copy()
        d = np.maximum(d, 1e-12 * max(d.max(), 1e-300))
        if options.condition:
            eig = np.linalg.eigvalsh(A / np.sqrt(np.outer(d, d)))
            condition = float(eig[-1] / eig[0]) if eig[0] > 0 else float("inf")
        step = np.zeros(n + 6)
        step[free] = _solve(A + lam * np.diag(d), g)
        tim["solve"] += time.perf_counter() - t0
        trial = beta + step
        if not np.isfinite(step).all():
            lam *= 10
            accepted = False
        else:
            held = run(trial, jac=False, frozen=None if options.recompute_in_ratio else ev.correspondence,
                       scales=ev.scales)
            lin = ev.f + ev.J @ step
            predicted = ev.omega - float(ev.w @ (lin * lin))
            actual = ev.omega - held.omega
            accepted = actual > 0 and np.isfinite(held.omega)
            rho = actual / predicted if predicted > 0 else 0.0
            if accepted:
                steps.append((ev.omega, held.omega))
                beta = trial
                # new correspondences, the next iteration's starting point; its Jacobian is
                # added only if there is a next iteration
                # each surface search starts from this iteration's triangles (the same answer)
                ev = run(beta, jac=False, warm=ev.correspondence)
                history.append(ev.omega)
                change = prev_omega - ev.omega
                prev_omega = ev.omega
                lam = lam / 3 if rho > 0.75 else (lam * 2 if rho < 0.25 else lam)
                lam = max(lam, 1e-12)
            else:
                lam *= 4
        if callback is not None:
            callback(Progress(it, beta.copy(), ev.omega, ev.features, time.perf_counter() - start, accepted, lam,
                              model))
        if accepted and abs(change) < options.tol:
            reason = "converged"
            break
        if accepted:
            if ev.omega < best[0]:
                best = (ev.omega, beta.copy(), ev.features)
            quiet = quiet + 1 if abs(change) < options.rtol * ev.omega else 0
            if quiet >= 2:
                reason = "stationary"
                break
        if not accepted and (lam > 1e16 or ev.omega == 0.0):
            reason = "converged" if ev.omega == 0.0 else "stalled"
            break
    if ev.omega > best[0]:  # jitter at the end: report the best state seen
        beta = best[1]
        ev = run(beta, jac=False)
    keep_end(model, ev)  # a warm start (the next frame) begins here
    return LibrResult(beta, ev.omega, it, reason, history, steps, ev.features, time.perf_counter() - start, tim,
                      condition)

"""The cross-validation's folds on two threads (issue 49): the same held-out RMS per block, to the
bit, as the folds one after another and as each fold fitted apart; ``threads.in_threads``'s rules
(order, errors, nesting, the BLAS limit and warning filters left as found). No timing here:
``navapp bench register``."""

import threading
import warnings
from contextlib import nullcontext
from dataclasses import replace

import numpy as np
import pytest
from conftest import noisy_feature_data
from threadpoolctl import threadpool_info

from navapp import threads
from navapp.registration import support
from navapp.registration.libr import LMOptions, register_libr
from navapp.registration.objective import Weights, evaluate


def _blocks(s):
    return [(b.centre.tobytes(), b.points, b.rigid_mm, b.deformable_mm) for b in s.blocks]


def _choice(c):
    """A pose choice's fields, its trimmed fit's pose as bytes (``PoseChoice`` holds arrays)."""
    if c is None:
        return None
    local = None if c.local is None else (c.local.R.tobytes(), c.local.t.tobytes(), c.local.rms_mm, c.local.kept)
    return c.source, c.moved_mm, c.on_model, local, c.turn_deg, c.fits


def test_concurrent_folds_are_the_sequential_folds_and_each_fold_apart_to_the_bit(small_model, monkeypatch):
    """On two threads (forced: this machine may have one core) the folds' fits run on both and
    every block's rigid and deformable held-out RMS, with and without a fold's extended model,
    is the same bits as the folds one after another and as each fold fitted apart from β = 0 on
    its own training points (fails if a fold's fit or prediction read another fold's points)."""
    rng = np.random.default_rng(23)
    data = noisy_feature_data(small_model, rng)
    settings = support.SupportOptions(iterations=6)
    options = LMOptions(weights=Weights(huber_mm={"anterior": 1.5}))
    n = small_model.basis.Ju.shape[1]
    fit = support.register_libr
    ran_on: set[int] = set()
    lock = threading.Lock()

    def recorded(model, train, *a, **k):
        with lock:
            ran_on.add(threading.get_ident())
        return fit(model, train, *a, **k)

    monkeypatch.setattr(support, "register_libr", recorded)
    monkeypatch.setattr(support, "task_threads", lambda: 2)
    # a fold's extended model: today's, for the folds whose training fit turns the organ one way
    # (so that both of ``extend``'s answers, a model and None, are taken)
    extend = lambda train, beta: small_model if beta[n + 3] > 0 else None  # noqa: E731
    small_model.cache.evaluation, small_model.cache.ends = None, ()
    both = support.check_support_pair(small_model, data, options, settings, extend=extend)
    assert both is not None and len(ran_on) == 2  # both threads fitted folds
    ran_on.clear()
    with support.sequential_folds():
        alone = support.check_support_pair(small_model, data, options, settings, extend=extend)
    assert alone is not None and len(ran_on) == 1
    assert _blocks(both[0]) == _blocks(alone[0]) and _blocks(both[1]) == _blocks(alone[1])
    # each fold apart: its training points fitted from β = 0 (no shared start), its block predicted
    labels = support.blocks_of(data, settings.blocks)
    fold = replace(options, max_iterations=settings.iterations)
    apart = []
    for b in range(settings.blocks):
        train = {k: p[labels[k] != b] for k, p in data.items() if (labels[k] != b).any()}
        held = {k: p[labels[k] == b] for k, p in data.items() if (labels[k] == b).any()}
        beta = register_libr(small_model, train, None, fold).beta
        pose = register_libr(small_model, train, None, replace(fold, deform=False)).beta
        rms = [support.pooled_rms(evaluate(small_model, held, x, options.weights, jacobian=False).features, held)
               for x in (pose, beta)]
        apart.append((rms[0], rms[1]))
    assert [(r, d) for _, _, r, d in _blocks(both[0])] == apart
    assert any(b.deformable_mm != b.rigid_mm for b in both[0].blocks)


def test_in_threads_keeps_order_raises_and_leaves_limits_and_filters_as_found():
    """Results in index order; BLAS at one thread inside every task and as it was after; a
    filter left behind by two tasks' ``catch_warnings`` exiting out of order removed (fails
    without ``in_threads``'s own limit or ``catch_warnings``); a call from inside a task runs
    there; a task's error raised in the caller after both threads stop."""
    def blas_threads():
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    before_blas, before_filters = blas_threads(), list(warnings.filters)
    inside, seen = [], set()
    entered, second, first_out = threading.Event(), threading.Event(), threading.Event()

    def task(i):
        seen.add(threading.get_ident())
        inside.append(blas_threads())
        # the first two tasks (one a thread): 0 enters catch_warnings, then 1; 0 leaves, then 1,
        # which restores the filters 0 had set
        if i == 0:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                entered.set()
                assert second.wait(30)
            first_out.set()
        elif i == 1:
            assert entered.wait(30)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                second.set()
                assert first_out.wait(30)
        return i, threads.in_threads(lambda j: j * i, 3, threads=2)

    out = threads.in_threads(task, 12, threads=2)
    assert out == [(i, [0, i, 2 * i]) for i in range(12)]
    assert len(seen) == 2 and all(set(b) == {1} for b in inside)
    assert blas_threads() == before_blas and warnings.filters == before_filters

    def failing(i):
        if i == 3:
            raise ValueError("fold 3")
        return i

    with pytest.raises(ValueError, match="fold 3"):
        threads.in_threads(failing, 8, threads=2)
    assert blas_threads() == before_blas
    assert threads.in_threads(lambda i: i, 5, threads=1) == list(range(5))


def test_screened_candidates_on_two_threads_are_the_sequential_screening_to_the_bit(small_model, monkeypatch):
    """The rigid stage's candidate poses, each screened by a few LM iterations, on two threads
    (forced) and in one: the same Ω per candidate and the same registration, to the bit (fails if
    a candidate's fit ran on another candidate's data). The data, a patch of one surface, leave
    several basins."""
    from navapp.registration import pipeline

    rng = np.random.default_rng(31)
    X = small_model.features["liver"].rest
    patch = X[np.linalg.norm(X - X[0], axis=1) < 35.0]
    data = {"anterior": patch + rng.normal(scale=0.5, size=patch.shape) + [3.0, -2.0, 1.0]}
    plain = pipeline.in_threads
    calls = []

    def forced(threads):
        def run(task, count, _threads=None):
            calls.append(count)
            return plain(task, count, threads)
        return run

    answers = []
    # the screening alone on two threads, then in one; then beside the pose choice's trimmed fit
    # (the screening then runs in turn inside its task)
    for threads_used, pose_ahead in ((2, 1), (1, 1), (2, 2)):
        monkeypatch.setattr(pipeline, "in_threads", forced(threads_used))
        monkeypatch.setattr(support, "task_threads", lambda n=pose_ahead: n)
        small_model.cache.evaluation, small_model.cache.ends = None, ()
        reg = pipeline.register(small_model, data, init=pipeline.RobustOptions(support=None))
        answers.append(([s.omega for s in reg.starts], reg.libr.beta.tobytes(), reg.rigid.R.tobytes(),
                        _choice(reg.pose_choice)))
    assert calls and all(c >= 2 for c in calls)  # more than one candidate was screened
    assert answers[0] == answers[1] == answers[2]


def test_in_threads_lead_runs_on_the_calling_thread_while_the_helper_takes_the_tasks():
    """``lead`` runs on the calling thread, the tasks begin on the helper meanwhile (the first
    task is taken before the lead ends), results in index order; on one thread the lead comes
    first; a failing lead is raised and no task is taken after it."""
    caller = threading.get_ident()
    lead_on, started, order = [], threading.Event(), []

    def lead():
        lead_on.append(threading.get_ident())
        assert started.wait(30)  # the helper took a task while the lead runs
        order.append("lead")

    def task(i):
        started.set()
        order.append(i)
        return i * i

    assert threads.in_threads(task, 6, threads=2, lead=lead) == [i * i for i in range(6)]
    assert lead_on == [caller] and order[0] == 0
    order.clear()
    assert threads.in_threads(lambda i: order.append(i) or i, 3, threads=1, lead=lambda: order.append("lead")) \
        == [0, 1, 2]
    assert order == ["lead", 0, 1, 2]

    def failing():
        raise ValueError("the fit")

    taken = []
    with pytest.raises(ValueError, match="the fit"):
        threads.in_threads(lambda i: taken.append(i), 50, threads=2, lead=failing)
    assert len(taken) < 50


def test_fit_beside_the_folds_is_the_registration_in_turn(small_model, monkeypatch):
    """On two threads (forced) the deformable fit of all the data runs on this thread while the
    folds begin on the helper, the error estimate after it among the folds, and the trimmed fit
    from the given pose beside the multi-start search: the same answer, blocks, error estimate,
    pose choice and lines, to the bit, as everything in turn on one thread (fails if a fold, the
    estimate or the pose choice read another state than in turn, e.g. the folds the fit's data
    after a refit)."""
    from navapp.registration import pipeline, pose
    from navapp.registration.rotation import rotation

    rng = np.random.default_rng(41)
    n = small_model.basis.Ju.shape[1]
    x = small_model.basis.nodes + (small_model.basis.Ju @ rng.normal(size=n)).reshape(-1, 3) * 0.6
    R, c = rotation(np.radians([4.0, -3.0, 2.0])), small_model.centroid
    pts = x[small_model.basis.surface][::3]
    data = {"anterior": (pts - c) @ R.T + c + [4.0, -3.0, 2.0] + rng.normal(scale=0.3, size=pts.shape)}
    leads, trimmed_in_task = [], []
    check, trim = support.check_support, pose.trimmed_from_given

    def recorded_check(*a, **k):
        leads.append(k.get("lead") is not None)
        return check(*a, **k)

    def recorded_trim(*a, **k):
        trimmed_in_task.append(getattr(threads._inside, "task", False))
        return trim(*a, **k)

    monkeypatch.setattr(pipeline, "check_support", recorded_check)
    monkeypatch.setattr(pipeline, "trimmed_from_given", recorded_trim)
    out = []
    for cores in (2, 1):
        monkeypatch.setattr(support, "task_threads", lambda n=cores: n)
        leads.clear()
        trimmed_in_task.clear()
        small_model.cache.evaluation, small_model.cache.ends = None, ()
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            reg = pipeline.register(small_model, data)
        assert reg.deformed and reg.support is not None and reg.organ is not None
        assert leads == [cores == 2] and trimmed_in_task == ([True] if cores == 2 else [])
        out.append((reg.libr.beta.tobytes(), reg.rigid.R.tobytes(), reg.rigid.t.tobytes(), _blocks(reg.support),
                    replace(reg.organ, seconds=0.0), _choice(reg.pose_choice), [str(w.message) for w in said],
                    [w.text for w in reg.warnings]))
    assert out[0] == out[1]


def test_error_estimate_made_beside_the_folds_is_the_one_made_after_them(small_model, monkeypatch):
    """From ICP's pose the answer's error estimate runs as one more of the folds' tasks (forced
    onto two threads): the same OrganError, to the bit, as made after the folds on one thread, and
    made once (fails if it read another state than the answer's, or were made again)."""
    from navapp.registration import pipeline
    from navapp.registration.rotation import rotation

    rng = np.random.default_rng(37)
    n = small_model.basis.Ju.shape[1]
    alpha = rng.normal(size=n)
    x = small_model.basis.nodes + (small_model.basis.Ju @ alpha).reshape(-1, 3) * 0.6
    R, c = rotation(np.radians([4.0, -3.0, 2.0])), small_model.centroid
    surface = x[small_model.basis.surface]
    pts = surface[::3]
    data = {"anterior": (pts - c) @ R.T + c + [4.0, -3.0, 2.0] + rng.normal(scale=0.3, size=pts.shape)}
    made = []
    plain = pipeline.organ_error

    def recorded(reg, *a, **k):
        made.append(getattr(threads._inside, "task", False))
        return plain(reg, *a, **k)

    monkeypatch.setattr(pipeline, "organ_error", recorded)
    monkeypatch.setattr(support, "task_threads", lambda: 2)
    out = []
    for sequential in (False, True):
        made.clear()
        small_model.cache.evaluation, small_model.cache.ends = None, ()
        with support.sequential_folds() if sequential else nullcontext():
            reg = pipeline.register(small_model, data)
        assert reg.deformed and not reg.rigid.kept and reg.organ is not None
        assert made == [not sequential]  # once: beside the folds, or after them
        blocks = [(b.rigid_mm, b.deformable_mm) for b in reg.support.blocks]
        out.append((replace(reg.organ, seconds=0.0), reg.libr.beta.tobytes(), blocks))
    assert out[0] == out[1]


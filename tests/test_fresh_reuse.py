"""A fresh registration's fits computing nothing twice (issue 49): each shortcut gives the
same bits as the full computation it replaces (no timing here: ``navapp bench register``)."""

import threading
from dataclasses import replace

import numpy as np
import pytest
from conftest import noisy_feature_data

from navapp.registration import libr, objective
from navapp.registration.libr import LMOptions, register_libr
from navapp.registration.objective import Weights, add_jacobian, evaluate


def test_positions_at_rest_do_not_read_the_basis(small_model):
    """At α = 0 a feature's displacement is zero without reading B·J_u: the same points, to the
    bit, as the product with α = 0 gives (fails if B·J_u is read: NaN in it shows)."""
    rng = np.random.default_rng(3)
    n = small_model.basis.Ju.shape[1]
    beta = np.concatenate([np.zeros(n), [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    feat = small_model.features["liver"]
    poisoned = replace(feat, BJ=np.full_like(feat.BJ, np.nan))
    local, x = small_model.positions(poisoned, beta)
    ref_local, ref_x = objective.deform(feat.rest, (feat.BJ.reshape(-1, n) @ beta[:n]).reshape(-1, 3), beta,
                                        small_model.centroid)
    assert np.array_equal(local, ref_local) and np.array_equal(x, ref_x)
    beta[:n] = rng.normal(size=n) * 0.1  # away from rest the basis is read
    assert np.isnan(small_model.positions(poisoned, beta)[1]).all()


@pytest.mark.parametrize("numpy_path", [False, True])
def test_pose_only_jacobian_is_the_full_one_without_alpha(small_model, numpy_path):
    """``add_jacobian(alpha_columns=False)`` at α = 0, compiled and by NumPy (the benches'
    "before"): the pose columns, f and S·x0 of the full Jacobian to the bit, the α columns zero;
    refused away from α = 0."""
    from contextlib import nullcontext

    rng = np.random.default_rng(5)
    n = small_model.basis.Ju.shape[1]
    data = noisy_feature_data(small_model, rng)
    beta = np.concatenate([np.zeros(n), [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    with objective.numpy_jacobian() if numpy_path else nullcontext():
        full = add_jacobian(small_model, evaluate(small_model, data, beta, Weights(), jacobian=False))
        pose = add_jacobian(small_model, evaluate(small_model, data, beta, Weights(), jacobian=False),
                            alpha_columns=False)
    assert np.array_equal(full.f, pose.f)
    assert np.array_equal(full.J[:, n:], pose.J[:, n:])
    assert not pose.J[:, :n].any()
    for name, c in pose.correspondence.items():
        assert c.SBJ is None and np.array_equal(c.S_rest, full.correspondence[name].S_rest)
    beta[0] = 0.1
    with pytest.raises(ValueError):
        add_jacobian(small_model, evaluate(small_model, data, beta, Weights(), jacobian=False), alpha_columns=False)


def test_rigid_fit_from_rest_is_the_same_without_the_alpha_columns(small_model, monkeypatch):
    """A rigid fit from β = 0 (the cross-validation's rigid folds) forms no α column and no
    S·B·J_u, and ends at the same β, Ω and history, to the bit, as the fit that forms the whole
    Jacobian (fails if the α kernel runs or a step changes)."""
    rng = np.random.default_rng(11)
    data = noisy_feature_data(small_model, rng)
    rigid = LMOptions(deform=False, max_iterations=8)
    small_model.cache.evaluation, small_model.cache.ends = None, ()
    kernel = objective._alpha_kernel()
    calls = [0]
    if kernel is not None:
        def counted(*a):
            calls[0] += 1
            return kernel[0](*a)

        monkeypatch.setattr(objective, "_jacobian_kernel", [(counted, kernel[1], kernel[2])])
    fast = register_libr(small_model, data, None, rigid)
    assert calls[0] == 0
    monkeypatch.undo()
    small_model.cache.evaluation, small_model.cache.ends = None, ()
    whole = {"evaluate": libr.evaluate, "add_jacobian": libr.add_jacobian}
    monkeypatch.setattr(libr, "evaluate", lambda *a, alpha_columns=True, **k: whole["evaluate"](*a, **k))
    monkeypatch.setattr(libr, "add_jacobian", lambda m, ev, alpha_columns=True: whole["add_jacobian"](m, ev))
    reference = register_libr(small_model, data, None, rigid)
    assert fast.iterations == reference.iterations >= 2
    assert np.array_equal(fast.beta, reference.beta)
    assert fast.omega == reference.omega and fast.history == reference.history


def test_stage_clock_laps_add_up_and_repeat_into_one_stage(monkeypatch):
    """``StageClock``: each mark takes the time since the previous one, a stage marked twice
    sums its laps, and the laps add up to the whole (clocks replaced: nothing timed here)."""
    from navapp.registration import stages

    ticks = iter([0.0, 1.0, 3.0, 6.0, 10.0])
    cpu = iter([0.0, 0.5, 0.5, 2.0, 2.5])
    monkeypatch.setattr(stages.time, "perf_counter", lambda: next(ticks))
    monkeypatch.setattr(stages.time, "process_time", lambda: next(cpu))
    clock = stages.StageClock()
    for name in ("rigid", "support", "rigid", "organ_error"):
        clock.mark(name)
    assert clock.times == {"rigid": stages.StageTime(1.0 + 3.0, 0.5 + 1.5), "support": stages.StageTime(2.0, 0.0),
                           "organ_error": stages.StageTime(4.0, 0.5)}
    assert sum(t.wall for t in clock.times.values()) == 10.0


def test_bench_register_stage_table_lists_every_stage_and_the_sum():
    from navapp.evaluation.benchmark import stage_table

    text = stage_table({"before": {"support": {"cpu": 0.5, "wall": 1.0}, "icp": {"cpu": 0.01, "wall": 0.02}},
                        "after": {"support": {"cpu": 0.25, "wall": 0.5}}})
    lines = text.splitlines()
    assert [ln.split()[0] for ln in lines[1:]] == ["support", "icp", "sum"]
    assert lines[1].split()[1:] == ["500.0", "1000.0", "250.0", "500.0"]
    assert lines[3].split()[1:] == ["510.0", "1020.0", "250.0", "500.0"]
    # a variant's name longer than the default column (``bench register``'s cold_search) keeps the heads apart
    three = stage_table({v: {"support": {"cpu": 0.5, "wall": 1.0}} for v in ("before", "cold_search", "after")})
    heads = [w for v in ("before", "cold_search", "after") for w in (v, "cpu", v, "wall")]
    assert three.splitlines()[0].split()[3:] == heads


def _all_kinds(model, rng):
    """Noisy points of every feature kind, fiducials included (three rows a point)."""
    data = noisy_feature_data(model, rng)
    data["fiducials"] = model.features["fiducials"].rest + rng.normal(size=model.features["fiducials"].rest.shape)
    falx = model.features["falciform"].rest
    data["falciform"] = falx + rng.normal(size=falx.shape) * 3.0
    return data


def test_points_of_is_the_evaluation_of_the_kept_points_to_the_bit(small_model):
    """``points_of``: the rows of the kept points of an evaluation of all points equal, bit for
    bit, the evaluation of the kept points alone (f, w with w_F / N_F of the kept count, the
    robust factors with an outlier cut from the kept points' median, J, Ω, statistics,
    correspondences); a feature with no point kept is dropped."""
    from navapp.registration.objective import Rejection, points_of

    rng = np.random.default_rng(7)
    n = small_model.basis.Ju.shape[1]
    data = _all_kinds(small_model, rng)
    data["anterior"][:10] += 30.0  # beyond the cut of every subset below
    weights = Weights(huber_mm={"falciform": 1.0, "portal_contour": 2.0}, reject=Rejection(floor_mm=3.0, k=2.0))
    zero = np.zeros(n + 6)
    whole = evaluate(small_model, data, zero, weights, jacobian=True)
    keep = {k: rng.random(len(p)) < 0.7 for k, p in data.items()}
    keep["portal_centerline"][:] = False
    keep["fiducials"][:] = True  # paired row by row: whole or not at all
    part = points_of(whole, keep, weights)
    kept = {k: p[keep[k]] for k, p in data.items() if keep[k].any()}
    small_model.cache.evaluation, small_model.cache.ends = None, ()
    alone = evaluate(small_model, kept, zero, weights, jacobian=True)
    assert list(part.correspondence) == list(alone.correspondence) == list(kept)
    for name in ("f", "w", "J"):
        assert np.array_equal(getattr(part, name), getattr(alone, name)), name
    assert part.omega == alone.omega and part.features == alone.features
    assert part.scales.keys() == alone.scales.keys()
    assert all(np.array_equal(part.scales[k], alone.scales[k]) for k in part.scales)
    for k, c in part.correspondence.items():
        a = alone.correspondence[k]
        assert c.S.same(a.S)
        assert (c.direction is None) == (a.direction is None)
        assert c.direction is None or np.array_equal(c.direction, a.direction)
        assert np.array_equal(c.SBJ, a.SBJ) and np.array_equal(c.S_rest, a.S_rest)
    keep["fiducials"][0] = False
    with pytest.raises(ValueError):
        points_of(whole, keep, weights)


def test_cross_validation_folds_start_from_one_evaluation(small_model, monkeypatch):
    """The cross-validation evaluates all its points at β = 0 once, and every fold's fits start
    from their rows: the same held-out RMS per block, to the bit, as folds that each evaluate
    their own start (fails with a start evaluated per fit: eleven evaluations at β = 0)."""
    from navapp.registration import support

    rng = np.random.default_rng(13)
    data = noisy_feature_data(small_model, rng)
    settings = support.SupportOptions(iterations=6)
    options = LMOptions(weights=Weights(huber_mm={"falciform": 1.0}))
    at_rest = [0]
    plain = support.evaluate
    lock = threading.Lock()  # the folds' fits run on two threads

    def counted(model, data, beta, *a, **k):
        with lock:
            at_rest[0] += not np.asarray(beta).any() and k.get("frozen") is None
        return plain(model, data, beta, *a, **k)

    monkeypatch.setattr(libr, "evaluate", counted)
    monkeypatch.setattr(support, "evaluate", counted)
    small_model.cache.evaluation, small_model.cache.ends = None, ()
    shared = support.check_support(small_model, data, options, settings)
    assert at_rest[0] == 1
    fit = support.register_libr
    monkeypatch.setattr(support, "register_libr", lambda *a, first=None: fit(*a))
    small_model.cache.evaluation, small_model.cache.ends = None, ()
    apart = support.check_support(small_model, data, options, settings)
    assert at_rest[0] == 1 + 1 + 2 * settings.blocks
    assert shared is not None and apart is not None
    assert [(b.rigid_mm, b.deformable_mm, b.points) for b in shared.blocks] == \
        [(b.rigid_mm, b.deformable_mm, b.points) for b in apart.blocks]


def test_cross_validation_leaves_the_answers_kept_evaluation(small_model):
    """The folds' fits do not push the answer's last evaluation out of the model's kept fit ends:
    the error estimate and the first warm start after a fresh registration find it (fails
    with the folds' ends kept: ten fits against four places)."""
    from navapp.registration import support
    from navapp.registration.objective import _at

    rng = np.random.default_rng(19)
    data = noisy_feature_data(small_model, rng)
    small_model.cache.evaluation, small_model.cache.ends = None, ()
    answer = register_libr(small_model, data, None, LMOptions(max_iterations=6))
    before = small_model.cache.ends
    assert support.check_support(small_model, data, LMOptions(), support.SupportOptions(iterations=4)) is not None
    assert small_model.cache.ends is before
    kept = _at(small_model, answer.beta)
    assert kept is not None and all(np.array_equal(kept[2][k][0], data[k]) for k in data)


def test_pose_choice_searches_the_given_pose_once(small_model, monkeypatch):
    """``choose_pose`` hands its search at the given pose to the trimmed fit, which searched it
    again before: the same choice, to the bit (fails with two searches at the given pose)."""
    from navapp.registration import pose
    from navapp.registration.rigid import RigidResult

    rng = np.random.default_rng(29)
    data = noisy_feature_data(small_model, rng)
    given = RigidResult(np.eye(3), np.zeros(3), 0, 0.0, kept=True)
    at_given = [0]
    plain = pose._surface_points

    def counted(model, data, p, *a, **k):
        at_given[0] += bool(np.array_equal(p.R, given.R) and np.array_equal(p.t, given.t))
        return plain(model, data, p, *a, **k)

    monkeypatch.setattr(pose, "_surface_points", counted)
    choice = pose.choose_pose(small_model, data, given)
    assert at_given[0] == 1
    again = pose.trimmed_pose(small_model, data, given, pose.POSE_RULE.keep)  # searching from scratch
    assert choice.moved_mm == again[1]
    assert choice.local is None or (np.array_equal(choice.local.R, again[0].R)
                                    and np.array_equal(choice.local.t, again[0].t))

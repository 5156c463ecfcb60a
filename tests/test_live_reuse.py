"""What a warm re-registration per frame reuses from the last one (coverage, the pose's
determinacy, the last evaluation's geometry and correspondences) gives the answers computed
afresh, whatever the data do between calls."""

from contextlib import nullcontext
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from navapp.registration.coverage import COVER_MM, MIN_COVERAGE, data_coverage, note_coverage
from navapp.registration.model import RegistrationModel
from navapp.registration.objective import KEPT_ENDS, Weights, _at, evaluate, keep_end
from navapp.registration.pose import _determinacy, pose_determinacy
from navapp.registration.rigid import RigidResult


def _fresh(model, data) -> float:
    """The coverage rule as first written: one k-d tree of all points, every surface node asked."""
    pts = [np.asarray(p, float).reshape(-1, 3) for p in data.values() if len(p)]
    if not pts:
        return 0.0
    d, _ = cKDTree(np.vstack(pts)).query(model.features["liver"].rest, distance_upper_bound=COVER_MM)
    return float(np.mean(d < COVER_MM))


def _bare(model) -> RegistrationModel:
    return RegistrationModel(model.basis, model.features, model.centroid)  # an empty cache


def _surface_sample(model, rng, n, spread=1.0):
    rest = model.features["liver"].rest
    return rest[rng.choice(len(rest), n, replace=False)] + rng.normal(0.0, spread, (n, 3))


def test_coverage_reused_between_frames_equals_the_fresh_rule(small_model):
    model = _bare(small_model)
    rng = np.random.default_rng(3)
    base = {"anterior": _surface_sample(model, rng, 60), "posterior": _surface_sample(model, rng, 20, 6.0)}
    R = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
    turned = RigidResult(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.array([3.0, 0, 0]), 0, 0.0)
    seen = set()
    for i in range(12):
        frame = {"posterior": _surface_sample(model, rng, int(rng.integers(1, 30)), 8.0)}
        if i % 3 == 0:
            frame["portal_contour"] = _surface_sample(model, rng, 15, 12.0)
        data = {n: np.vstack([base[n], frame[n]]) if n in base and n in frame else base.get(n, frame.get(n))
                for n in {**base, **frame}}
        pose = turned if i == 7 else R  # one frame in another pose: every row changes
        local = {n: pose.inverse(p) for n, p in data.items()}
        if i == 9:
            local = {"anterior": local["anterior"][:25]}  # fewer rows and features than last time
        if i == 10:
            base["anterior"] = base["anterior"][::-1].copy()  # same points, another order
        got = data_coverage(model, local)
        assert got.fraction == _fresh(model, local), i
        seen.add(round(got.fraction, 3))
    assert len(seen) > 3  # the frames did change the answer
    assert data_coverage(model, {}).fraction == 0.0


def test_coverage_note_skips_a_frame_only_when_the_kept_rows_cover_enough(small_model):
    """``note_coverage`` leaves the newest frame's rows unsearched when the rows kept from the
    last call already cover enough: its warning must still be the exact rule's, frame by frame,
    whether the kept rows cover enough (skipped), fall short while the frame brings the data over
    the line, or fall short with the frame too."""
    from types import SimpleNamespace

    from navapp.fitwarning import WarningKind

    model = _bare(small_model)
    rest = model.features["liver"].rest
    rng = np.random.default_rng(11)
    near0 = np.argsort(np.linalg.norm(rest - rest[0], axis=1))
    small = rest[near0[:max(3, len(rest) // 40)]]  # a patch under MIN_COVERAGE
    wide = rest[::3]  # far over it
    cases = [(small, 8), (small, 8), (wide, 8), (wide, 5), (small, 2), (small, len(rest) // 4), (small, 3)]
    skipped = 0
    for i, (base, m) in enumerate(cases):
        frame = rest[rng.choice(len(rest), m, replace=False)] + rng.normal(0.0, 0.5, (m, 3))
        local = {"anterior": base, "posterior": frame}
        reg = SimpleNamespace(model=model, data_model_frame=local, notes=[])
        cached = model.cache.coverage
        note_coverage(reg)
        skipped += model.cache.coverage is cached and bool(cached)
        warned = any(w.kind is WarningKind.COVERAGE for w in reg.notes)
        assert warned == (_fresh(model, local) < MIN_COVERAGE), i
    assert skipped >= 1  # the wide base's second frame needed no search


def test_coverage_warning_comes_and_goes_with_the_data(small_model):
    """From a small patch (warned) to the whole sweep (not) and back, on one model."""
    model = _bare(small_model)
    rest = model.features["liver"].rest
    patch = rest[np.linalg.norm(rest - rest[0], axis=1) < 12.0]
    assert data_coverage(model, {"anterior": patch}).warning is not None
    assert data_coverage(model, {"anterior": rest[::2]}).warning is None
    assert data_coverage(model, {"anterior": patch}).warning is not None


def test_determinacy_given_again_equals_the_fresh_one(small_model):
    model = _bare(small_model)
    rng = np.random.default_rng(4)
    stylus = {"anterior": _surface_sample(model, rng, 80, 0.3)}
    pose = RigidResult(np.eye(3), np.array([1.0, 0, 0]), 0, 0.0)
    first = pose_determinacy(model, stylus, pose)
    frames = ({}, {"posterior": _surface_sample(model, rng, 30)}, {"portal_contour": _surface_sample(model, rng, 9)})
    for frame in frames:  # iUS features: the determinacy reads the stylus's alone
        again = pose_determinacy(model, {**stylus, **frame}, pose)
        assert again is not first and np.array_equal(again.eigenvalues, first.eigenvalues)
        assert again.warning == first.warning
    moved = {"anterior": stylus["anterior"][:40]}
    other = pose_determinacy(model, moved, pose)
    assert np.array_equal(other.eigenvalues, _determinacy(model, moved, pose).eigenvalues)
    assert not np.array_equal(other.eigenvalues, first.eigenvalues)
    shifted = RigidResult(np.eye(3), np.array([2.0, 0, 0]), 0, 0.0)
    assert np.array_equal(pose_determinacy(model, stylus, shifted).eigenvalues,
                          _determinacy(model, stylus, shifted).eigenvalues)


def test_evaluation_at_the_last_state_equals_a_fresh_one(small_model):
    """The next frame's first evaluation is at the β the last one ended at: the geometry and
    the correspondences of unchanged data are taken from it; everything equals a fresh model's."""
    model = _bare(small_model)
    rng = np.random.default_rng(6)
    n = model.basis.Ju.shape[1]
    beta = np.concatenate([rng.normal(0.0, 0.3, n), [0.5, -0.2, 0.1, 0.01, 0.0, -0.02]])
    anterior = _surface_sample(model, rng, 50, 0.5)
    posterior = _surface_sample(model, rng, 20, 0.5)
    first = evaluate(model, {"anterior": anterior, "posterior": posterior}, beta, Weights())
    assert model.cache.evaluation is not None
    posterior[:5] += 2.0  # the caller's array changed in place: not the points of the last call
    for data in ({"anterior": anterior, "posterior": posterior},
                 {"anterior": anterior, "posterior": posterior[:7], "ridge_right": _surface_sample(model, rng, 9)},
                 {"anterior": anterior}):
        for jacobian in (True, False):
            got = evaluate(model, data, beta, Weights(), jacobian=jacobian)
            fresh = evaluate(_bare(model), data, beta, Weights(), jacobian=jacobian)
            assert got.omega == fresh.omega and np.array_equal(got.f, fresh.f) and np.array_equal(got.w, fresh.w)
            assert (got.J is None) == (not jacobian) and (got.J is None or np.array_equal(got.J, fresh.J))
            assert got.features == fresh.features
    assert first.omega != evaluate(model, {"anterior": anterior, "posterior": posterior}, beta, Weights()).omega
    other = evaluate(model, {"anterior": anterior}, beta * 0.5, Weights())
    assert other.omega == evaluate(_bare(model), {"anterior": anterior}, beta * 0.5, Weights()).omega


def test_a_fits_end_is_found_again_after_other_fits(small_model):
    """Other fits between two frames (the viewer's next-plane suggestion, the bench's other
    variants) leave the ends of the last few fits to start from, with a fresh model's answers."""
    model = _bare(small_model)
    rng = np.random.default_rng(8)
    n = model.basis.Ju.shape[1]
    data = {"anterior": _surface_sample(model, rng, 50, 0.5)}
    ends = [np.concatenate([rng.normal(0.0, 0.3, n), rng.normal(0.0, 0.02, 6)]) for _ in range(KEPT_ENDS + 1)]
    for b in ends:
        keep_end(model, evaluate(model, data, b, Weights(), jacobian=False))
        evaluate(model, data, b * 0.9, Weights(), jacobian=False)  # the fit's other evaluations
    assert _at(model, ends[0]) is None  # the oldest is gone: a bounded number is kept
    for b in ends[1:]:
        assert _at(model, b) is not None
        got, fresh = (evaluate(m, data, b, Weights()) for m in (model, _bare(model)))
        assert np.array_equal(got.f, fresh.f) and np.array_equal(got.J, fresh.J)


def test_cache_copy_is_written_apart(small_model):
    """``ModelCache.copy`` (the benchmarks' ``replace(model, cache=model.cache.copy())``): the
    copy starts with the same entries, and an evaluation on one model warms only that one."""
    model = _bare(small_model)
    rng = np.random.default_rng(7)
    beta = np.zeros(model.basis.Ju.shape[1] + 6)
    evaluate(model, {"anterior": _surface_sample(model, rng, 30, 0.5)}, beta, Weights())
    other = replace(model, cache=model.cache.copy())
    assert other.cache is not model.cache and other.cache.evaluation is model.cache.evaluation
    evaluate(other, {"anterior": _surface_sample(model, rng, 30, 0.5)}, beta + 0.1, Weights())
    assert not np.array_equal(other.cache.evaluation[0], model.cache.evaluation[0])
    assert np.array_equal(model.cache.evaluation[0], beta)


def test_lm_searches_start_from_the_last_iterations_triangles_with_the_same_fit(small_model, monkeypatch):
    """After an accepted step LM searches each surface again at the new β; the search begins at
    the triangles of the last iteration's (``evaluate(warm=)``), and the fit is the one a
    search from the hierarchy's root gives, to the bit (``cold_search``)."""
    from navapp.geometry import bvh
    from navapp.registration.libr import LMOptions, register_libr
    from navapp.registration.objective import cold_search

    rng = np.random.default_rng(12)
    data = {"anterior": _surface_sample(small_model, rng, 60, 1.5),
            "posterior": _surface_sample(small_model, rng, 30, 1.5) + [1.0, -0.5, 0.8]}
    starts = []
    plain = bvh.SurfaceHierarchy.closest

    def closest(self, points, vertices, boxes, start=None):
        starts.append(None if start is None else np.array(start))
        return plain(self, points, vertices, boxes, start)

    monkeypatch.setattr(bvh.SurfaceHierarchy, "closest", closest)
    fits = {}
    for name, ctx in (("warm", None), ("cold", cold_search)):
        starts.clear()
        if ctx is None:
            fits[name] = register_libr(_bare(small_model), data, options=LMOptions(max_iterations=6))
            warm_starts = [s for s in starts if s is not None]
        else:
            with ctx():
                fits[name] = register_libr(_bare(small_model), data, options=LMOptions(max_iterations=6))
            assert all(s is None for s in starts)
    assert fits["warm"].iterations >= 2 and len(fits["warm"].steps) >= 2
    # every accepted step's search of both features started from triangles
    assert len(warm_starts) >= 2 * len(fits["warm"].steps) and all((s >= 0).all() for s in warm_starts)
    a, b = fits["warm"], fits["cold"]
    assert np.array_equal(a.beta, b.beta) and a.history == b.history and a.iterations == b.iterations


def _vessel_sample(model, name, rng, n, spread):
    rest = model.feature_for(name).rest
    return rest[rng.choice(len(rest), n, replace=False)] + rng.normal(0.0, spread, (n, 3))


def _same_evaluation(a, b) -> None:
    assert a.omega == b.omega and np.array_equal(a.f, b.f) and np.array_equal(a.w, b.w)
    assert np.array_equal(a.J, b.J) and np.array_equal(a.Js, b.Js) and a.features == b.features
    for name, c in a.correspondence.items():
        d = b.correspondence[name]
        for x, y in ((c.S.data, d.S.data), (c.S.indices, d.S.indices), (c.S.indptr, d.S.indptr),
                     (c.direction, d.direction), (c.face, d.face), (c.SBJ, d.SBJ), (c.S_rest, d.S_rest)):
            assert (x is None) == (y is None) and (x is None or np.array_equal(x, y)), name


def test_a_frames_points_after_the_kept_ones_are_searched_alone_with_the_same_evaluation(small_model, monkeypatch):
    """The next live frame's first evaluation is at the β the last update ended at, where that
    update's final evaluation searched the kept planes' contour points and the last frame's: the
    rows of a feature's first points that are the same, at the same β, are kept and only the
    points after them searched (``search_whole`` searches them all again, as before). The
    evaluation equals a fresh model's to the bit, and keeps no row of a point that moved."""
    import navapp.registration.objective as objective
    from navapp.registration.libr import LMOptions, register_libr
    from navapp.registration.objective import search_whole

    rng = np.random.default_rng(13)
    n = small_model.basis.Ju.shape[1]
    beta = np.concatenate([rng.normal(0.0, 0.3, n), [0.5, -0.2, 0.1, 0.01, 0.0, -0.02]])
    anterior = _surface_sample(small_model, rng, 40, 0.5)
    contour, line = _vessel_sample(small_model, "portal_contour", rng, 30, 1.0), \
        _vessel_sample(small_model, "portal_centerline", rng, 4, 1.0)

    def frame(k):
        return {"anterior": anterior,
                "portal_contour": np.vstack([contour, _vessel_sample(small_model, "portal_contour", rng, k, 1.5)]),
                "portal_centerline": np.vstack([line, _vessel_sample(small_model, "portal_centerline", rng, 2, 1.5)])}

    searched = []
    plain = objective.correspond

    def correspond(feat, X, Y, **kw):
        searched.append(len(Y))
        return plain(feat, X, Y, **kw)

    monkeypatch.setattr(objective, "correspond", correspond)
    last, now = frame(12), frame(9)
    moved = {**now, "portal_contour": now["portal_contour"].copy()}
    moved["portal_contour"][7] += 1.0  # a kept point moved: its rows and the ones after it are searched
    for data, kept in ((now, {"portal_contour": 30, "portal_centerline": 4}),
                       (moved, {"portal_contour": 7, "portal_centerline": 4})):
        model = _bare(small_model)
        evaluate(model, last, beta, Weights(), jacobian=False)  # the last update's final evaluation
        searched.clear()
        got = evaluate(model, data, beta, Weights())
        reached = sorted(searched)
        searched.clear()
        fresh = evaluate(_bare(small_model), data, beta, Weights())
        assert sorted(searched) == sorted(len(v) for v in data.values())
        _same_evaluation(got, fresh)  # before the count: a stale row fails here
        assert reached == sorted(len(data[k]) - kept[k] for k in kept)  # the anterior's reused whole
        with search_whole():
            model = _bare(small_model)
            evaluate(model, last, beta, Weights(), jacobian=False)
            searched.clear()
            whole = evaluate(model, data, beta, Weights())
        assert sorted(searched) == sorted(len(data[k]) for k in kept)
        _same_evaluation(got, whole)
    # another β: nothing of the last evaluation is kept
    model = _bare(small_model)
    evaluate(model, last, beta, Weights(), jacobian=False)
    _same_evaluation(evaluate(model, now, beta * 0.9, Weights()), evaluate(_bare(small_model), now, beta * 0.9,
                                                                           Weights()))
    # a live update: LM from where the last fit ended, one iteration, the same fit as searching whole
    fits = []
    for ctx in (None, search_whole):
        model = _bare(small_model)
        with ctx() if ctx else nullcontext():
            end = register_libr(model, last, beta, LMOptions(max_iterations=2))
            fits.append(register_libr(model, now, end.beta, LMOptions(max_iterations=1)))
    a, b = fits
    assert len(a.steps) == 1 and np.array_equal(a.beta, b.beta) and a.omega == b.omega and a.features == b.features

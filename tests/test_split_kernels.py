"""The compiled kernels split among threads (``threads.split_kernels``: the live update's
second core) give the one-thread kernels' answers to the bit, and only in the thread that
asked for them."""

import threading

import numpy as np
import pytest

from navapp.threads import SPLIT_MIN, kernel_threads, split_kernels

numba = pytest.importorskip("numba")


@pytest.fixture(scope="module")
def two_threads():
    """Inside ``split_kernels(2)``, or a skip where Numba's TBB layer cannot be loaded."""
    from navapp.threads import _tbb

    if not _tbb():
        pytest.skip("Numba's TBB threading layer is not available: the kernels stay on one thread")
    return lambda: split_kernels(2)


def _surface(rng):
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=3, radius=40.0)  # 1,280 triangles
    v = np.ascontiguousarray(ball.vertices + rng.normal(0.0, 1.5, ball.vertices.shape))
    return v, np.ascontiguousarray(ball.faces, dtype=np.int64)


def test_split_closest_points_are_the_one_thread_ones(two_threads):
    from navapp.geometry import bvh

    rng = np.random.default_rng(41)
    v, f = _surface(rng)
    h = bvh.SurfaceHierarchy(v, f)
    moved = v + rng.normal(0.0, 0.8, v.shape)  # the tree is refitted to deformed vertices
    points = moved[rng.choice(len(moved), 500)] * rng.uniform(0.8, 1.2, (500, 1))  # inside and outside
    boxes = bvh.refit(moved, h.faces, h.order, h.left, h.first, h.count)
    face, bary = bvh.closest(points, moved, h.faces, h.order, h.left, h.first, h.count, boxes,
                             np.full(len(points), -1, np.int64))
    start = rng.integers(0, len(f), len(points))
    with two_threads():
        assert kernel_threads() == 2
        got = []
        for s in (np.full(len(points), -1, np.int64), start):
            got.append((np.full(len(points), -7), np.full((len(points), 3), np.nan)))  # every entry written
            bvh.closest_split(points, moved, h.faces, h.order, h.left, h.first, h.count, boxes, s, *got[-1])
        via = h.closest(points, moved, boxes)  # the hierarchy takes the split build from SPLIT_MIN points on
    for fc, br in (*got, via):
        assert np.array_equal(fc, face) and np.array_equal(br, bary)
    assert (face >= 0).all() and len(np.unique(face)) > 100  # a real search, not a degenerate one


def _csr(rng, N, V, width=3):
    indptr = np.arange(0, width * N + 1, width, dtype=np.int32)
    indices = rng.integers(0, V, width * N).astype(np.int32)
    return indptr, indices, rng.random(width * N)


@pytest.mark.parametrize("per_point", [1, 3])  # a surface's one row a point, a centerline's three
def test_split_alpha_columns_are_the_one_thread_ones(two_threads, per_point):
    from navapp.registration import jacobian_compiled as jc

    rng = np.random.default_rng(43 + per_point)
    V, N, n = 300, 251, 27  # 251 points: the last chunk a part one
    indptr, indices, weights = _csr(rng, N, V)
    BJ = rng.normal(size=(V, 3, n)) * 7.3
    rows = np.repeat(np.arange(N), per_point)
    qR = rng.normal(size=(len(rows), 3))
    sw = rng.random(len(rows))

    def run(alpha_columns, order):
        U = np.empty((N, 3, n), np.float32)
        J, Js = np.full((len(rows), n), np.nan), np.full((len(rows), n), np.nan)
        alpha_columns(indptr, indices, weights, BJ, qR[order], rows[order], U, J, sw[order], Js)
        return U, J, Js

    for order in (np.arange(len(rows)), rng.permutation(len(rows))):  # rows out of point order too
        one = run(jc.alpha_columns, order)
        with two_threads():
            split = run(jc.alpha_columns_split, order)
        for a, b in zip(one, split, strict=True):
            assert np.array_equal(a, b)
        assert np.isfinite(one[1]).all()  # every entry of J written


def test_a_live_update_on_two_threads_is_the_one_thread_fit(small_model, two_threads, monkeypatch):
    """``LiveRegistration(threads=2, adapt=False)`` splits the kernels (each feature here has ≥ SPLIT_MIN
    points) and fits every frame to the same bits as on one thread."""
    from navapp.geometry import bvh
    from navapp.registration import jacobian_compiled as jc
    from navapp.registration.live import LiveRegistration
    from navapp.registration.model import RegistrationModel

    calls = {"closest": 0, "alpha": 0}
    plain_closest, plain_alpha = bvh.closest_split, jc.alpha_columns_split

    def closest_split(*a):
        calls["closest"] += 1
        return plain_closest(*a)

    def alpha_split(*a):
        calls["alpha"] += 1
        return plain_alpha(*a)

    monkeypatch.setattr(bvh, "closest_split", closest_split)
    import navapp.registration.objective as objective

    monkeypatch.setattr(objective, "_jacobian_kernel", [])
    monkeypatch.setattr(jc, "alpha_columns_split", alpha_split)
    rng = np.random.default_rng(47)
    liver = small_model.features["liver"].rest
    base = {"anterior": liver[rng.choice(len(liver), 150, replace=False)] + rng.normal(0.0, 1.0, (150, 3))}
    frames = [{"posterior": liver[rng.choice(len(liver), 80, replace=False)] + rng.normal(0.0, 2.0, (80, 3))
               + [1.0, -0.5, 0.3]} for _ in range(4)]
    fits = {}
    for threads in (1, 2):
        model = RegistrationModel(small_model.basis, small_model.features, small_model.centroid)
        live = LiveRegistration(model, base, threads=threads, adapt=False)  # split every update on two
        live.register()
        before = dict(calls)
        fits[threads] = [live.update(f).libr for f in frames]
        assert (calls != before) == (threads == 2)  # split only on two threads
    for a, b in zip(fits[1], fits[2], strict=True):
        assert np.array_equal(a.beta, b.beta) and a.omega == b.omega and a.features == b.features
    assert calls["closest"] >= 4 and calls["alpha"] >= 4


def test_split_kernels_hold_in_their_own_thread_and_give_back(two_threads):
    threads_before, chunk_before = numba.get_num_threads(), numba.get_parallel_chunksize()
    seen = {}

    def other():
        seen["other"] = (kernel_threads(), numba.get_num_threads(), numba.get_parallel_chunksize())

    with two_threads():
        seen["inside"] = (kernel_threads(), numba.get_num_threads(), numba.get_parallel_chunksize())
        with split_kernels(1):  # one thread inside two: nothing split
            seen["nested"] = kernel_threads()
        seen["after_nested"] = kernel_threads()
        t = threading.Thread(target=other)
        t.start()
        t.join()
    assert seen["inside"] == (2, 2, 1) and seen["nested"] == 1 and seen["after_nested"] == 2
    assert seen["other"] == (1, threads_before, chunk_before)
    assert (kernel_threads(), numba.get_num_threads(), numba.get_parallel_chunksize()) == \
        (1, threads_before, chunk_before)
    assert SPLIT_MIN > 1


def test_fewer_points_than_split_min_stay_on_one_thread(two_threads, monkeypatch):
    from navapp.geometry import bvh

    rng = np.random.default_rng(53)
    v, f = _surface(rng)
    h = bvh.SurfaceHierarchy(v, f)
    boxes = h.refit(v)
    used = []
    plain = bvh.closest_split
    monkeypatch.setattr(bvh, "closest_split", lambda *a: used.append(len(a[0])) or plain(*a))
    with two_threads():
        h.closest(v[:SPLIT_MIN - 1], v, boxes)
        h.closest(v[:SPLIT_MIN], v, boxes)
    assert used == [SPLIT_MIN]


def test_eq8s_product_cut_between_two_threads_is_the_whole_products_bits(two_threads, monkeypatch):
    """``model._product`` cuts B·J_u's rows at a multiple of 64 and multiplies each half by BLAS
    on its own thread: the whole product's bits (BLAS sums each row alone, in fixed groups of
    rows), at sizes on both sides of the cut's group; the second half is run even when the
    helper never starts it (taken back by the caller)."""
    from concurrent.futures import Future

    import navapp.threads as threads
    from navapp.registration.model import SPLIT_ROWS, _product

    rng = np.random.default_rng(59)
    with threads.limit_threads(1):  # as in LM (``libr``): one BLAS thread in each half
        for rows in (SPLIT_ROWS, SPLIT_ROWS + 1, 6006, 18642 + 3):
            single = rng.normal(size=(rows, 135)).astype(np.float32)
            alpha = rng.normal(size=135).astype(np.float32)
            whole = single @ alpha
            with two_threads():
                assert np.array_equal(_product(single, alpha), whole), rows
        with two_threads():  # the helper's failure is the caller's
            with pytest.raises(ValueError):
                threads.both(lambda: None, lambda: np.matmul(single, alpha[:7]))
        halves = []

        def never_begun(task):  # a helper busy elsewhere: the job waits, and the caller takes it back
            halves.append(task)
            return Future()

        monkeypatch.setattr(threads, "_pool", type("Idle", (), {"submit": staticmethod(never_begun)})())
        with two_threads():
            assert np.array_equal(_product(single, alpha), whole)  # the helper never ran: the caller did both
        assert len(halves) == 1


def test_normal_equations_in_two_halves_are_the_same_bits_on_one_thread_or_two(two_threads):
    """``libr.gram``: from ``GRAM_HALVES_MIN`` rows JᵀWJ is two halves' rank-k updates summed,
    whether the halves run side by side (a live update given the second core) or in turn, so
    the choice of ``live.SecondCore`` never changes a fit; it is JᵀJ to rounding and symmetric."""
    import navapp.threads as threads
    from navapp.registration.libr import GRAM_HALVES_MIN, gram

    rng = np.random.default_rng(61)
    with threads.limit_threads(1):
        for rows in (GRAM_HALVES_MIN - 1, GRAM_HALVES_MIN, 2184, 4097):
            Js = rng.normal(size=(rows, 141))
            one = gram(Js)
            with two_threads():
                split = gram(Js)
            assert np.array_equal(one, split), rows
            assert np.array_equal(one, one.T), rows
            np.testing.assert_allclose(one, Js.T @ Js, rtol=1e-12, atol=1e-10 * rows)


def test_second_core_takes_the_faster_way_and_turns_with_the_load():
    """``live.SecondCore``: each way timed, then the faster one, the other tried every tenth
    update, so that a loaded machine (two threads slower) turns it to one thread and back."""
    from navapp.registration.live import SecondCore

    load = [False]
    choice = SecondCore(keep=5, probe_every=10, busy=lambda: load[0])

    def run(n, split_s, one_s):
        picks = []
        for _ in range(n):
            split = choice.pick()
            picks.append(split)
            choice.record(split, split_s if split else one_s)
        return picks

    first = run(10, 0.008, 0.011)
    assert first.count(True) == 5 and first.count(False) == 5  # both timed first
    quiet = run(40, 0.008, 0.011)
    assert quiet.count(False) == 4 and all(quiet[i] for i in range(40) if (11 + i) % 10)  # probes only
    loaded = run(40, 0.045, 0.033)  # the second core taken by other work
    assert loaded[-30:].count(True) == 3  # turned to one thread, two tried every tenth update
    back = run(80, 0.008, 0.011)  # the load gone: back to two within a few probes
    assert back[-20:].count(False) == 2
    load[0] = True  # the load average fills the cores: nothing split, nothing tried
    assert not any(run(30, 0.008, 0.011))

"""S of eq. 9–10 as rows of barycentric weights (``registration.barycentric``): the arrays the
compiled kernels read are SciPy's compressed rows, and its products are SciPy's."""

import numpy as np
import scipy.sparse as sp

from navapp.registration.barycentric import Barycentric


def _rows(seed: int, n: int = 200, m: int = 3, v: int = 900):
    rng = np.random.default_rng(seed)
    w = rng.random((n, m))
    return w / w.sum(1, keepdims=True), rng.integers(0, v, (n, m)), v


def test_rows_are_the_compressed_rows_an_independent_build_gives():
    w, cols, v = _rows(0)
    S = Barycentric.of(w, cols, v)
    ref = sp.coo_matrix((w.ravel(), (np.repeat(np.arange(len(w)), 3), cols.ravel())), shape=(len(w), v))
    X = np.random.default_rng(1).normal(size=(v, 3))
    assert S.shape == ref.shape and S.indices.dtype == np.int32 and S.indptr.dtype == np.int32
    assert np.allclose(S @ X, ref @ X, rtol=0, atol=1e-12)  # COO sums a row's duplicates in its own order
    # each row summed in its stored order, as the compiled kernels and SciPy's CSR product sum it
    by_hand = np.zeros((len(w), 3))
    for i in range(len(w)):
        for j in range(S.indptr[i], S.indptr[i + 1]):
            by_hand[i] += S.data[j] * X[S.indices[j]]
    assert np.array_equal(S @ X, by_hand)


def test_selected_rows_and_the_identity():
    w, cols, v = _rows(2)
    S = Barycentric.of(w, cols, v)
    idx = np.array([5, 0, 17, 17, 199])
    X = np.random.default_rng(3).normal(size=(v, 3))
    assert np.array_equal(S[idx] @ X, (S @ X)[idx])
    assert S[idx].same(Barycentric.of(w[idx], cols[idx], v)) and not S[idx].same(S[idx[::-1]])
    eye = Barycentric.identity(7)
    Y = np.arange(21.0).reshape(7, 3)
    assert eye.shape == (7, 7) and np.array_equal(eye @ Y, Y)

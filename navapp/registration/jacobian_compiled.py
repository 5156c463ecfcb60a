"""The α columns of LM's Jacobian compiled by Numba (``objective.add_jacobian``).

Each data row's α columns are −(qᵀR)·(S·B·J_u) at its point: S·B·J_u (the basis carried to
the point, 3 × 3k) is a weighted sum of two or three rows of the feature's B·J_u, and the
product with qᵀR a sum of three of those rows. With SciPy and NumPy that is a sparse product
writing (N, 3, 3k), an indexed copy per row and an einsum; compiled, one pass that writes
S·B·J_u (kept for the held fast path) and the rows of J. S·B·J_u is summed in CSR order as
SciPy's product sums it, so it is the same to the bit; the three-term product may differ from
einsum's in the last bit. ``pose_columns`` does the rest of the row in the same spirit: τ's
columns −q, θ's −qᵀ(∂R/∂θ_j)(S·local), and S·x0 for the held fast path (S·local and S·x0
in CSR order, as SciPy). None where Numba is missing: ``objective`` then uses NumPy.
"""

from collections.abc import Callable

import numpy as np

from ..compiled import CHUNK, prange, split_jit

try:
    from numba import njit
except ImportError:  # pragma: no cover - only without numba
    njit = None


def _alpha_columns(indptr, indices, weights, BJ, qR, rows, U, J, sw, Js):
    """Fill U (N, 3, n) = S·B·J_u and J[:, :n] = −qR·(S·B·J_u)[rows] for the R rows (``rows``:
    the point of each row, nondecreasing as ``objective.residuals`` makes them), and
    Js[:, :n] = sw[:, None]·J[:, :n], the rows scaled by √w for LM's JᵀWJ (``libr``): the
    product NumPy's ``J * sw[:, None]`` makes, without another pass over J.

    Each point's S·B·J_u is summed in double precision into one (3, n) buffer, in CSR order
    as SciPy sums it, and its rows of J are made from that buffer: the same bits as from
    the sum stored in double. U may be single precision: it is what the held fast path
    multiplies by α (eq. 8 at the closest points, ``objective.Correspondence``), as the
    whole-feature deformation multiplies the single-precision B·J_u; storing half the bytes
    and not reading them back for J is a fifth of this kernel's time (docs/decisions/speed.md,
    "Issue 49, session 37"). Rows not in point order have their points summed again."""
    N, n = U.shape[0], U.shape[2]
    R = rows.shape[0]
    ordered = True
    for r in range(1, R):
        if rows[r] < rows[r - 1]:
            ordered = False
    acc = np.empty((3, n))
    r = 0
    for i in range(N):
        _point_sum(indptr, indices, weights, BJ, i, acc)
        for a in range(3):
            for k in range(n):
                U[i, a, k] = acc[a, k]
        if ordered:
            while r < R and rows[r] == i:
                _row(acc, qR, sw, r, J, Js)
                r += 1
    if not ordered:  # each row's point summed again, in the same order: the same bits
        for r in range(R):
            _point_sum(indptr, indices, weights, BJ, rows[r], acc)
            _row(acc, qR, sw, r, J, Js)


def _alpha_columns_split(indptr, indices, weights, BJ, qR, rows, U, J, sw, Js):
    """``_alpha_columns`` with the points split among Numba's threads (``threads.split_kernels``),
    in chunks of ``CHUNK``: each point's S·B·J_u and its rows made as there, so the same bits.
    Rows out of point order: ``_alpha_columns`` itself, on this thread."""
    N, n = U.shape[0], U.shape[2]
    R = rows.shape[0]
    start = np.empty(N + 1, np.int64)  # point i's rows are start[i]:start[i + 1]
    r = 0
    for i in range(N):
        start[i] = r
        while r < R and rows[r] == i:
            r += 1
    start[N] = r
    if r < R:  # not in point order
        _alpha_columns_one(indptr, indices, weights, BJ, qR, rows, U, J, sw, Js)
        return
    for c in prange((N + CHUNK - 1) // CHUNK):
        acc = np.empty((3, n))
        for i in range(c * CHUNK, min(N, (c + 1) * CHUNK)):
            _point_sum(indptr, indices, weights, BJ, i, acc)
            for a in range(3):
                for k in range(n):
                    U[i, a, k] = acc[a, k]
            for rr in range(start[i], start[i + 1]):
                _row(acc, qR, sw, rr, J, Js)


def _point_sum_py(indptr, indices, weights, BJ, i, acc):
    """acc (3, n) = point i's S·B·J_u, summed in CSR order."""
    n = acc.shape[1]
    for a in range(3):
        for k in range(n):
            acc[a, k] = 0.0
    for jj in range(indptr[i], indptr[i + 1]):
        v, w = indices[jj], weights[jj]
        for a in range(3):
            for k in range(n):
                acc[a, k] += w * BJ[v, a, k]


def _row_py(acc, qR, sw, r, J, Js):
    """Row r's α columns of J from its point's S·B·J_u (``acc``), and of Js = √w·J."""
    q0, q1, q2 = qR[r, 0], qR[r, 1], qR[r, 2]
    s = sw[r]
    for k in range(acc.shape[1]):
        J[r, k] = -(q0 * acc[0, k] + q1 * acc[1, k] + q2 * acc[2, k])
        Js[r, k] = J[r, k] * s


# the two steps each α row is made of, compiled for ``_alpha_columns`` to call (inlined by Numba)
_point_sum = njit(cache=True, nogil=True, inline="always")(_point_sum_py) if njit is not None else _point_sum_py
_row = njit(cache=True, nogil=True, inline="always")(_row_py) if njit is not None else _row_py


def _pose_columns(indptr, indices, weights, rest, local, q, dR, rows, S_rest, J, sw, Js):
    """Fill S_rest (N, 3) = S·x0 and J's six pose columns (the last six): −q for τ and
    −qᵀ(∂R/∂θ_j)(S·local)[rows] for θ, for the R rows (``rows``: the point of each row), and
    those columns of Js = sw[:, None]·J (``alpha_columns``)."""
    N, n = S_rest.shape[0], J.shape[1] - 6
    xl = np.zeros((N, 3))
    for i in range(N):
        for a in range(3):
            S_rest[i, a] = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            v, w = indices[jj], weights[jj]
            for a in range(3):
                S_rest[i, a] += w * rest[v, a]
                xl[i, a] += w * local[v, a]
    for r in range(rows.shape[0]):
        i = rows[r]
        for a in range(3):
            J[r, n + a] = -q[r, a]
        for j in range(3):
            acc = 0.0
            for a in range(3):
                for b in range(3):
                    acc += q[r, a] * dR[j, a, b] * xl[i, b]
            J[r, n + 3 + j] = -acc
        for c in range(n, n + 6):
            Js[r, c] = J[r, c] * sw[r]


def _apply(indptr, indices, weights, X, out):
    """out (N, c) = S·X for S in CSR form and a dense X (V, c), summed in CSR order from zero
    as SciPy's product sums it (the same bits), without its dispatch (~40 µs a call, ~11
    calls an LM evaluation)."""
    for i in range(out.shape[0]):
        for a in range(out.shape[1]):
            out[i, a] = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            v, w = indices[jj], weights[jj]
            for a in range(out.shape[1]):
                out[i, a] += w * X[v, a]


def _carried(U, alpha, out):
    """out (N, 3) = U·α for the S·B·J_u U (N, 3, n) the α kernel keeps in single precision,
    summed in double precision: the held fast path's J_u α at the closest points, a linear
    function of α to double precision's rounding, as LM's ratio and a finite difference need
    (a product in single precision would round it anew at every α by ~1e-6 mm). Compiled
    with reassociation allowed (``carried``): the sum over the modes is then vectorised (0.13
    against 0.37 ms in order, and 0.20 ms for NumPy's product of a double U, 1,600 points)."""
    for i in range(U.shape[0]):
        for a in range(3):
            acc = 0.0
            for k in range(U.shape[2]):
                acc += U[i, a, k] * alpha[k]
            out[i, a] = acc


alpha_columns = njit(cache=True, nogil=True)(_alpha_columns) if njit is not None else None
_alpha_columns_one: Callable = alpha_columns if alpha_columns is not None else _alpha_columns
alpha_columns_split = split_jit(_alpha_columns_split)
apply = njit(cache=True, nogil=True)(_apply) if njit is not None else None
pose_columns = njit(cache=True, nogil=True)(_pose_columns) if njit is not None else None
# reassociation lets the sum over the modes be vectorised; a fixed sum order per build, so the
# same bits every call
carried = njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})(_carried) if njit is not None else None

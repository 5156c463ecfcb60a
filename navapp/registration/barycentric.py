"""S of eq. 9–10: each data point's closest point as weights on a few of the model feature's
points — a triangle's three, a segment's two, a fiducial's own one.

Every row has the same number of entries, so the weights and their columns are two (N, m)
arrays, and the compressed-row arrays the compiled kernels read (``data``, ``indices``,
``indptr``) are views of them. A SciPy matrix is made only where a NumPy path multiplies by
S, not for every correspondence a search makes (docs/decisions/speed.md, "S without SciPy's
matrix").
"""

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True, eq=False)
class Barycentric:
    """S (N × V): row i = Σ_j weights[i, j] e_{columns[i, j]}.

    Attributes
    ----------
    weights : (N, m) float
        the closest point's barycentric weights (each row sums to one).
    columns : (N, m) int
        the model feature's points they weigh, indices into its V points; int32 where V
        and N·m fit, as SciPy would store them.
    n_columns : int
        V, the model feature's point count.
    """

    weights: np.ndarray
    columns: np.ndarray
    n_columns: int

    @classmethod
    def of(cls, weights: np.ndarray, columns: np.ndarray, n_columns: int) -> "Barycentric":
        """S from (N, m) weights and (N, m) point indices into V = ``n_columns`` points."""
        weights = np.ascontiguousarray(weights, dtype=float)
        idx = np.int32 if max(n_columns, weights.size) < np.iinfo(np.int32).max else np.int64
        return cls(weights, np.ascontiguousarray(columns, dtype=idx), int(n_columns))

    @classmethod
    def identity(cls, n: int) -> "Barycentric":
        """The (n × n) identity: fiducials pair with the model's own, row for row."""
        return cls.of(np.ones((n, 1)), np.arange(n)[:, None], n)

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.weights), self.n_columns

    @property
    def data(self) -> np.ndarray:
        """(N·m,) the weights row by row: compressed rows' values."""
        return self.weights.reshape(-1)

    @property
    def indices(self) -> np.ndarray:
        """(N·m,) the columns row by row: compressed rows' column indices."""
        return self.columns.reshape(-1)

    @cached_property
    def indptr(self) -> np.ndarray:
        """(N + 1,) where each row starts in ``data``: every row holds m entries."""
        n, m = self.weights.shape
        return np.arange(0, n * m + 1, m, dtype=self.columns.dtype) if m else np.zeros(n + 1, self.columns.dtype)

    @cached_property
    def csr(self) -> sp.csr_matrix:
        """The same S as a SciPy matrix, for the NumPy paths (made once, on first use)."""
        return sp.csr_matrix((self.data, self.indices, self.indptr), shape=self.shape)

    def __getitem__(self, rows) -> "Barycentric":
        """The rows ``rows`` (an index array or mask) of S."""
        return Barycentric(self.weights[rows], self.columns[rows], self.n_columns)

    def __matmul__(self, X) -> np.ndarray:
        """S @ X for a dense X (V, …): SciPy's product, so SciPy's bits."""
        return np.asarray(self.csr @ X)

    def same(self, other: "Barycentric") -> bool:
        """The same entries in the same places, to the bit."""
        return (self.n_columns == other.n_columns and np.array_equal(self.weights, other.weights)
                and np.array_equal(self.columns, other.columns))

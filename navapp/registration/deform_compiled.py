"""Eq. 8 at a whole feature's points from the single-precision product B·J_u α, compiled by
Numba (``model.RegistrationModel.positions``).

NumPy makes x(β) = R(θ)(x0 − x̄0 + J_u α) + τ + x̄0 in six passes over the points (the
product's conversion to double, two sums, a 3 × 3 product, two more sums), each allocating:
0.15 ms for the demo liver's 6,214 points against 0.03 ms in one pass here, at every LM
evaluation that searches (docs/decisions/speed.md, "Issue 49, session 37"). ``model.deform`` stays
eq. 8's definition; this is the same arithmetic per point (the rotated sum in another order
than BLAS's, so x within ~1e-13 mm of it). None where Numba is missing.
"""

import numpy as np

try:
    from numba import njit
except ImportError:  # pragma: no cover - only without numba
    njit = None


def _place(rest, u, centroid, R, tau, local, x):
    """Fill local (V, 3) = x0 − x̄0 + u and x (V, 3) = R·local + τ + x̄0, with u the flat (3V,)
    single-precision J_u α, each entry widened to double before the sum as NumPy's ``astype``."""
    for v in range(rest.shape[0]):
        l0 = rest[v, 0] + np.float64(u[3 * v]) - centroid[0]
        l1 = rest[v, 1] + np.float64(u[3 * v + 1]) - centroid[1]
        l2 = rest[v, 2] + np.float64(u[3 * v + 2]) - centroid[2]
        local[v, 0], local[v, 1], local[v, 2] = l0, l1, l2
        for a in range(3):
            x[v, a] = R[a, 0] * l0 + R[a, 1] * l1 + R[a, 2] * l2 + tau[a] + centroid[a]


place = njit(cache=True, nogil=True)(_place) if njit is not None else None

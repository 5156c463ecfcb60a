"""Barycentric interpolation from a tet mesh to arbitrary points (vessels, fiducials, the
simulated truth): geometry, below the mechanics that use it for their fields."""

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


def barycentric(nodes, tets, points, candidates=24):
    """Containing tet (P,) and barycentric weights (P, 4) of each point.

    Candidate tets are those with the nearest centroids; the chosen one maximises the
    smallest barycentric coordinate, so a point inside the mesh gets its containing tet
    (all weights in [0, 1]) and a point slightly outside the nearest tet's linear
    extrapolation (documented choice: vessel walls sampled on a slightly different
    surface may poke a fraction of a mm out of the parenchyma).
    """
    points = np.atleast_2d(np.asarray(points, float))
    cen = nodes[tets].mean(1)
    _, cand = cKDTree(cen).query(points, k=min(candidates, len(tets)))
    cand = cand.reshape(len(points), -1)
    p = nodes[tets[cand]]  # (P, C, 4, 3)
    T = (p[:, :, 1:] - p[:, :, :1]).transpose(0, 1, 3, 2)
    rhs = points[:, None, :] - p[:, :, 0]
    lam = np.linalg.solve(T, rhs[..., None])[..., 0]
    w = np.concatenate([1 - lam.sum(-1, keepdims=True), lam], -1)  # (P, C, 4)
    best = np.argmax(w.min(-1), axis=1)
    rows = np.arange(len(points))
    return cand[rows, best], w[rows, best]


def interpolation_matrix(nodes, tets, points) -> sp.csr_matrix:
    """B (P × M): nodal field values → values at ``points`` (4 non-zeros a row)."""
    tet, w = barycentric(nodes, tets, points)
    P = len(w)
    return sp.csr_matrix((w.ravel(), (np.repeat(np.arange(P), 4), tets[tet].ravel())), shape=(P, len(nodes)))

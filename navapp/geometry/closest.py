"""Closest points on triangle surfaces and polylines, vectorised.

Candidates come from a KD-tree on the vertices: the triangles (segments) incident to the
``near`` nearest vertices are tested exactly, which finds the true closest point for any
query whose nearest surface point lies on a triangle incident to one of its nearest
vertices (always the case for well-shaped meshes and queries near the surface).
"""

import numpy as np
from scipy.spatial import cKDTree


def incidence(n_vertices, cells):
    """Padded vertex → incident cell table (V, m); -1 pads."""
    cells = np.asarray(cells)
    v = cells.ravel()
    c = np.repeat(np.arange(len(cells)), cells.shape[1])
    order = np.argsort(v, kind="stable")
    v, c = v[order], c[order]
    counts = np.bincount(v, minlength=n_vertices)
    m = max(int(counts.max()), 1)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(v)) - start[v]
    table = np.full((n_vertices, m), -1)
    table[v, slot] = c
    return table


def closest_on_triangles(p, a, b, c):
    """Closest points on triangles abc to points p, all (N, 3) (Ericson, RTCD §5.1.5).

    Returns closest (N, 3) and barycentric weights (N, 3) of a, b, c.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        den = va + vb + vc
        v, u = vb / den, vc / den
    # Voronoi regions in Ericson's order (the first that holds wins): vertex a, vertex b,
    # edge ab, vertex c, edge ac, edge bc; otherwise the face interior
    regions = [(d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (vc <= 0) & (d1 >= 0) & (d3 <= 0),
               (d6 >= 0) & (d5 <= d6), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
               (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)]
    w = np.empty((len(p), 3))
    w[:, 0] = np.select(regions, [1.0, 0.0, 1 - t_ab, 0.0, 1 - t_ac, 0.0], 1 - v - u)
    w[:, 1] = np.select(regions, [0.0, 1.0, t_ab, 0.0, 0.0, 1 - t_bc], v)
    w[:, 2] = np.select(regions, [0.0, 0.0, 0.0, 1.0, t_ac, t_bc], u)
    w = np.nan_to_num(w, nan=1.0 / 3.0)
    return w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c, w


def closest_on_surface(points, vertices, faces, table, near=2, tree=None):
    """Closest surface points. Returns face (N,), barycentric (N, 3), closest (N, 3).

    ``table`` is ``incidence(len(vertices), faces)``; ``tree`` an optional prebuilt
    cKDTree of ``vertices``.
    """
    points = np.asarray(points, float)
    _, vi = (tree or cKDTree(vertices)).query(points, k=near)
    cand = np.sort(table[vi.reshape(len(points), -1)].reshape(len(points), -1), axis=1)  # (N, near*m)
    # test each distinct incident face once: the padding (-1) and the faces the near
    # vertices share are about half of the table's rows
    valid = cand >= 0
    valid[:, 1:] &= cand[:, 1:] != cand[:, :-1]
    r, c = np.nonzero(valid)
    f = cand[r, c]
    tri = vertices[faces[f]]  # (K, 3, 3)
    P = points[r]
    q, w = closest_on_triangles(P, tri[:, 0], tri[:, 1], tri[:, 2])
    d = np.full(cand.shape, np.inf)
    d[r, c] = np.einsum("ij,ij->i", q - P, q - P)
    flat = np.full(cand.shape, -1)
    flat[r, c] = np.arange(len(r))
    rows = np.arange(len(points))
    sel = flat[rows, np.argmin(d, axis=1)]
    return f[sel], w[sel], q[sel]


def closest_on_polyline(points, vertices, segments, table, near=2, tree=None):
    """Closest points on polyline segments. Returns segment (N,), t (N,), closest (N, 3)."""
    points = np.asarray(points, float)
    _, vi = (tree or cKDTree(vertices)).query(points, k=near)
    cand = table[vi.reshape(len(points), -1)].reshape(len(points), -1)
    valid = cand >= 0
    cs = np.where(valid, cand, 0)
    a = vertices[segments[cs, 0]]
    b = vertices[segments[cs, 1]]
    ab = b - a
    t = np.clip(np.einsum("ncj,ncj->nc", points[:, None] - a, ab) / np.maximum(np.einsum("ncj,ncj->nc", ab, ab), 1e-300), 0, 1)
    q = a + t[..., None] * ab
    d = np.linalg.norm(q - points[:, None], axis=2)
    d[~valid] = np.inf
    best = np.argmin(d, axis=1)
    rows = np.arange(len(points))
    return cs[rows, best], t[rows, best], q[rows, best]

"""Exact-arithmetic-free triangle predicates, vectorised over many pairs.

Möller–Trumbore segment/triangle intersection, and a self-intersection test for closed
triangle surfaces built on it.
"""

import numpy as np
from scipy.spatial import cKDTree


def segment_hits_triangle(p0, p1, a, b, c, eps=1e-9):
    """Do segments p0→p1 cross triangles abc? All (N, 3); returns (N,) bool and t (N,).

    Möller–Trumbore ray/triangle test restricted to the segment (0 < t < 1). Grazing
    (coplanar) cases count as no hit; a closed surface that self-intersects always has
    at least one transversal crossing, which is what this finds.
    """
    d = p1 - p0
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > eps * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(d, axis=1)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p0 - a
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    hit = ok & (u > 0) & (v > 0) & (u + v < 1) & (t > 0) & (t < 1)
    return hit, t


def self_intersecting_faces(vertices, faces, max_pairs=20_000_000):
    """Indices of faces that cross another face of the same surface (empty if none).

    Candidate pairs are triangles whose circumscribing spheres overlap (KD-tree on the
    centroids); pairs that share a vertex are adjacent and skipped. For each remaining
    pair the three edges of either triangle are tested against the other.
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces)
    tri = v[f]
    cen = tri.mean(1)
    rad = np.linalg.norm(tri - cen[:, None], axis=2).max(1)
    # one search radius for the bulk, and the few large triangles (decimated surfaces have
    # some) searched one by one, so that one large triangle does not make every pair a candidate
    tree = cKDTree(cen)
    r_small = float(np.percentile(rad, 99))
    pairs = [tree.query_pairs(2 * r_small, output_type="ndarray")]
    big = np.flatnonzero(rad > r_small)
    for b, near in zip(big, tree.query_ball_point(cen[big], rad[big] + r_small), strict=True):
        near = np.asarray(near, int)
        pairs.append(np.column_stack([np.full(len(near), b), near]))
    if len(big) > 1:
        bb = np.array(np.triu_indices(len(big), 1)).T
        pairs.append(big[bb])
    allp = np.concatenate([p.reshape(-1, 2) for p in pairs])
    allp = np.unique(np.sort(allp[allp[:, 0] != allp[:, 1]], axis=1), axis=0)
    if len(allp) > max_pairs:
        raise MemoryError("surface too large for the self-intersection test")
    i, j = allp[:, 0], allp[:, 1]
    close = np.linalg.norm(cen[i] - cen[j], axis=1) <= rad[i] + rad[j]
    i, j = i[close], j[close]
    shared = (f[i][:, :, None] == f[j][:, None, :]).any(axis=(1, 2))
    i, j = i[~shared], j[~shared]
    bad = np.zeros(len(i), bool)
    for s, o in ((i, j), (j, i)):
        A, B = tri[s], tri[o]
        for e0, e1 in ((0, 1), (1, 2), (2, 0)):
            hit, _ = segment_hits_triangle(A[:, e0], A[:, e1], B[:, 0], B[:, 1], B[:, 2])
            bad |= hit
    return np.unique(np.concatenate([i[bad], j[bad]]))

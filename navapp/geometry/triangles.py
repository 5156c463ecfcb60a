"""Exact-arithmetic-free triangle predicates, vectorised over many pairs.

Möller–Trumbore segment/triangle intersection, and a self-intersection test for closed
triangle surfaces built on it.
"""

import numpy as np


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


CHUNK_PAIRS = 2_000_000  # candidate pairs tested at once: bounds the test's memory (~0.5 GB)


def self_intersecting_faces(vertices, faces):
    """Indices of faces that cross another face of the same surface (empty if none).

    Candidate pairs come from a spatial hash of the triangles' bounding boxes: a uniform
    grid of cells about twice the typical triangle's size, each triangle entered into every
    cell its box touches, a pair kept in the one cell that holds the low corner of the
    overlap of their boxes (so no pair is made twice). Pairs that share a vertex are
    adjacent and skipped; for each remaining pair the three edges of either triangle are
    tested against the other, in chunks, so any size of surface is checked in bounded
    memory (a 100k-triangle surface in a few seconds).
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    if len(f) < 2:
        return np.zeros(0, np.int64)
    tri = v[f]
    lo, hi = tri.min(1), tri.max(1)
    size = (hi - lo).max(1)
    cell = max(2.0 * float(np.percentile(size, 90)), 1e-9)
    origin = lo.min(0)
    c0 = np.floor((lo - origin) / cell).astype(np.int64)
    c1 = np.floor((hi - origin) / cell).astype(np.int64)
    dims = c1.max(0) + 1
    span = c1 - c0 + 1
    count = span.prod(1)
    # every (triangle, cell) entry
    t = np.repeat(np.arange(len(f)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    sy, sz = span[t, 1], span[t, 2]
    ci = c0[t, 0] + local // (sy * sz)
    cj = c0[t, 1] + (local // sz) % sy
    ck = c0[t, 2] + local % sz
    key = (ci * dims[1] + cj) * dims[2] + ck
    order = np.argsort(key, kind="stable")
    key, t = key[order], t[order]
    start = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    end = np.append(start[1:], len(key))
    group_end = np.repeat(end, end - start)
    partners = group_end - np.arange(len(key)) - 1  # later entries of the same cell
    bad = np.zeros(len(f), bool)
    # entries in chunks whose pair counts stay under CHUNK_PAIRS
    csum = np.cumsum(partners)
    pos = 0
    while pos < len(key):
        stop = int(np.searchsorted(csum, (csum[pos - 1] if pos else 0) + CHUNK_PAIRS, side="right"))
        stop = max(stop, pos + 1)
        e = np.arange(pos, stop)
        n = partners[e]
        a = np.repeat(e, n)
        b = a + 1 + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
        i, j, cell_key = t[a], t[b], key[a]
        # boxes overlap, and this cell holds the overlap's low corner
        olo = np.maximum(lo[i], lo[j])
        keep = np.all(olo <= np.minimum(hi[i], hi[j]), axis=1)
        oc = np.floor((olo - origin) / cell).astype(np.int64)
        keep &= ((oc[:, 0] * dims[1] + oc[:, 1]) * dims[2] + oc[:, 2]) == cell_key
        i, j = i[keep], j[keep]
        shared = (f[i][:, :, None] == f[j][:, None, :]).any(axis=(1, 2))
        i, j = i[~shared], j[~shared]
        hit = np.zeros(len(i), bool)
        for s, o in ((i, j), (j, i)):
            A, B = tri[s], tri[o]
            for e0, e1 in ((0, 1), (1, 2), (2, 0)):
                h, _ = segment_hits_triangle(A[:, e0], A[:, e1], B[:, 0], B[:, 1], B[:, 2])
                hit |= h
        bad[i[hit]] = True
        bad[j[hit]] = True
        pos = stop
    return np.flatnonzero(bad)

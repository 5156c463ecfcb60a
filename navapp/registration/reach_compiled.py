"""The compiled kernels of ``reach`` (Numba): the nodes' bounding boxes, eq. 8 at one
vertex and the search that deforms the vertices it tests. Imported on first use, like
``geometry.bvh`` (Numba takes ~1 s to load)."""

import numpy as np

from ..geometry.closest_compiled import _jit, pair

_PAD = 1e-9  # mm: added to every bound against rounding in its own arithmetic


@_jit
def _slack(norm, z, rest, reach):
    """(C, 3) mm: per chunk and axis, the bound of the remainder's part at a change of α whose
    norm is ``norm`` and whose products with the leading directions are ``z``, plus ``_PAD``."""
    C, r = z.shape
    out = np.empty((C, 3))
    for c in range(C):
        for a in range(3):
            e = rest[c, a] * norm
            for j in range(r):
                e += reach[c, a, j] * abs(z[c, j])
            out[c, a] = e + _PAD
    return out


@_jit
def _bound(lo, hi, base_lo, base_hi, node, c, shift, A, slack, centre, half, origin):
    """lo, hi (3,): ``base`` (the node's box before the change of α) moved by the change's
    bound (``shift``, ``A`` of the change; ``slack`` from ``_slack``)."""
    d0 = centre[node, 0] - origin[c, 0]
    d1 = centre[node, 1] - origin[c, 1]
    d2 = centre[node, 2] - origin[c, 2]
    h0, h1, h2 = half[node, 0], half[node, 1], half[node, 2]
    for a in range(3):
        mid = shift[c, a] + (A[c, a, 0] * d0 + A[c, a, 1] * d1 + A[c, a, 2] * d2)
        ext = slack[c, a] + (abs(A[c, a, 0]) * h0 + abs(A[c, a, 1]) * h1 + abs(A[c, a, 2]) * h2)
        ext += 1e-12 * (abs(mid) + ext + abs(base_lo[a]) + abs(base_hi[a]))
        lo[a] = base_lo[a] + mid - ext
        hi[a] = base_hi[a] + mid + ext


@_jit
def boxes(box, norm, shift, A, z, dnorm, dshift, dA, dz, chunk, centre, half, origin, rest, reach, left, first,
          count, order, faces, local, done, previous, prev_box, prev_local, prev_done):
    """Fill ``box`` (nodes, 2, 3), the local frame's boxes of the nodes' triangles at α.

    A leaf whose vertices are all deformed (``done``) gets its exact box. Any other node at or
    below the chunks gets its undeformed box moved by the bound of α (‖α‖ and
    ``ChunkBounds.products``: shift, A, z), intersected, when ``previous``, with the earlier
    state's box moved by the bound of the change (dnorm, dshift, dA, dz) — that box exact
    where the earlier state deformed a leaf whole — and with its children's union. A node above
    the chunks gets its children's union."""
    lo = np.empty(3)
    hi = np.empty(3)
    t_lo = np.empty(3)
    t_hi = np.empty(3)
    slack = _slack(norm, z, rest, reach)
    dslack = _slack(dnorm, dz, rest, reach)
    for node in range(left.shape[0] - 1, -1, -1):
        c = chunk[node]
        kid = left[node]
        if c < 0:
            for a in range(3):
                box[node, 0, a] = min(box[kid, 0, a], box[kid + 1, 0, a])
                box[node, 1, a] = max(box[kid, 1, a], box[kid + 1, 1, a])
            continue
        if kid < 0 and _leaf_box(node, box[node, 0], box[node, 1], first, count, order, faces, local, done):
            continue
        _bound(lo, hi, centre[node], centre[node], node, c, shift, A, slack, centre, half, origin)
        for a in range(3):  # the undeformed box is centre ± half: (I + A) half is half plus |A| half
            lo[a] -= half[node, a]
            hi[a] += half[node, a]
        if previous:
            if kid >= 0 or not _leaf_box(node, t_lo, t_hi, first, count, order, faces, prev_local, prev_done):
                for a in range(3):
                    t_lo[a], t_hi[a] = prev_box[node, 0, a], prev_box[node, 1, a]
            _bound(t_lo, t_hi, t_lo, t_hi, node, c, dshift, dA, dslack, centre, half, origin)
            for a in range(3):
                lo[a] = max(lo[a], t_lo[a])
                hi[a] = min(hi[a], t_hi[a])
        for a in range(3):
            if kid >= 0:
                lo[a] = max(lo[a], min(box[kid, 0, a], box[kid + 1, 0, a]))
                hi[a] = min(hi[a], max(box[kid, 1, a], box[kid + 1, 1, a]))
            box[node, 0, a], box[node, 1, a] = lo[a], hi[a]


@_jit
def _leaf_box(node, lo, hi, first, count, order, faces, local, done):
    """The exact box (lo, hi) of a leaf's triangles at ``local`` when all their vertices are
    ``done``; False (lo, hi undefined) otherwise."""
    for a in range(3):
        lo[a] = np.inf
        hi[a] = -np.inf
    for j in range(first[node], first[node] + count[node]):
        for m in range(3):
            v = faces[order[j], m]
            if not done[v]:
                return False
            for a in range(3):
                lo[a] = min(lo[a], local[v, a])
                hi[a] = max(hi[a], local[v, a])
    return True


@_jit
def deform_leaves(leaves, first, count, order, faces, rest, BJ, alpha, R, tau, centroid, local, X, done):
    """Deform the vertices of the listed leaves' triangles not deformed yet (``_deform_vertex``)."""
    for node in leaves:
        for j in range(first[node], first[node] + count[node]):
            for m in range(3):
                v = faces[order[j], m]
                if not done[v]:
                    _deform_vertex(v, rest, BJ, alpha, R, tau, centroid, local, X)
                    done[v] = True


@_jit
def _deform_vertex(v, rest, BJ, alpha, R, tau, centroid, local, X):
    """Eq. 8 at one vertex: local = (x0 + B J_u α) − x̄0, X = R local + τ + x̄0. Each of the
    three sums over the modes in two interleaved halves (independent chains: the sum's
    latency, not its reads, bounds a vertex); every vertex the same way, so a vertex's bits do
    not depend on which others are deformed."""
    n = alpha.shape[0]
    u0 = u1 = u2 = 0.0
    w0 = w1 = w2 = 0.0
    k = 0
    while k + 1 < n:
        a, b = alpha[k], alpha[k + 1]
        u0 += BJ[v, 0, k] * a
        u1 += BJ[v, 1, k] * a
        u2 += BJ[v, 2, k] * a
        w0 += BJ[v, 0, k + 1] * b
        w1 += BJ[v, 1, k + 1] * b
        w2 += BJ[v, 2, k + 1] * b
        k += 2
    if k < n:
        a = alpha[k]
        u0 += BJ[v, 0, k] * a
        u1 += BJ[v, 1, k] * a
        u2 += BJ[v, 2, k] * a
    l0 = (rest[v, 0] + (u0 + w0)) - centroid[0]
    l1 = (rest[v, 1] + (u1 + w1)) - centroid[1]
    l2 = (rest[v, 2] + (u2 + w2)) - centroid[2]
    local[v, 0], local[v, 1], local[v, 2] = l0, l1, l2
    for a in range(3):
        X[v, a] = ((R[a, 0] * l0 + R[a, 1] * l1 + R[a, 2] * l2) + tau[a]) + centroid[a]


@_jit
def deform_all(rest, BJ, alpha, R, tau, centroid, local, X, done):
    """Deform every vertex not yet deformed (``done`` False), by ``_deform_vertex``."""
    for v in range(rest.shape[0]):
        if not done[v]:
            _deform_vertex(v, rest, BJ, alpha, R, tau, centroid, local, X)
            done[v] = True


@_jit
def _gap(p0, p1, p2, box, node):
    d = 0.0
    g = max(box[node, 0, 0] - p0, 0.0, p0 - box[node, 1, 0])
    d += g * g
    g = max(box[node, 0, 1] - p1, 0.0, p1 - box[node, 1, 1])
    d += g * g
    g = max(box[node, 0, 2] - p2, 0.0, p2 - box[node, 1, 2])
    d += g * g
    return d


@_jit
def closest(points, carried, start, faces, order, left, first, count, box, rest, BJ, alpha, R, tau, centroid, local,
            X, done):
    """face (N,) and barycentric weights (N, 3) of each point's closest point on the surface
    deformed at (α, R, τ), deforming (into ``local``, ``X``; ``done`` marks them) only the
    vertices of the triangles it tests. ``carried``: the points in the local frame, for the
    boxes (``boxes``); ``start`` (N,) a triangle per point to begin from (−1: none; speed
    only). The tie rule and the skip's margin are ``bvh.closest``'s. Face −1
    where no triangle has a finite distance."""
    N = points.shape[0]
    face = np.full(N, -1, np.int64)
    bary = np.zeros((N, 3))
    stack = np.empty(128, np.int64)
    gap = np.empty(128)
    for i in range(N):
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        c0, c1, c2 = carried[i, 0], carried[i, 1], carried[i, 2]
        best = np.inf
        bf = -1
        b1 = 0.0
        b2 = 0.0
        f = start[i]
        if f >= 0:  # a first bound from a likely triangle (the last state's): speed only
            for m in range(3):
                v = faces[f, m]
                if not done[v]:
                    _deform_vertex(v, rest, BJ, alpha, R, tau, centroid, local, X)
                    done[v] = True
            d, w1, w2 = pair(p0, p1, p2, X, faces, f)
            if d < best:
                best, bf, b1, b2 = d, f, w1, w2
        stack[0] = 0
        gap[0] = 0.0
        top = 1
        while top > 0:
            top -= 1
            node = stack[top]
            if gap[top] > best * (1.0 + 1e-9) + 1e-12:
                continue
            c = left[node]
            if c < 0:
                for j in range(first[node], first[node] + count[node]):
                    f = order[j]
                    for m in range(3):
                        v = faces[f, m]
                        if not done[v]:
                            _deform_vertex(v, rest, BJ, alpha, R, tau, centroid, local, X)
                            done[v] = True
                    d, w1, w2 = pair(p0, p1, p2, X, faces, f)
                    if d < best or (d == best and f < bf):
                        best, bf, b1, b2 = d, f, w1, w2
            else:
                g0 = _gap(c0, c1, c2, box, c)
                g1 = _gap(c0, c1, c2, box, c + 1)
                if g0 <= g1:
                    stack[top], gap[top], stack[top + 1], gap[top + 1] = c + 1, g1, c, g0
                else:
                    stack[top], gap[top], stack[top + 1], gap[top + 1] = c, g0, c + 1, g1
                top += 2
        face[i] = bf
        bary[i, 0] = 1.0 - b1 - b2
        bary[i, 1] = b1
        bary[i, 2] = b2
    return face, bary

"""The closest-point test of ``closest.closest_on_surface`` compiled by Numba.

LM tests every data point against the triangles incident to its nearest vertices at every
evaluation (~8,500 point–triangle pairs for the demo's stylus points alone). Written with
NumPy that is ~70 whole-array operations on temporaries of the pairs' length, 3.5–4.5 ms of
CPU a call; compiled, one pass over the pairs with nothing allocated (docs/decisions/speed.md,
"Closest points at the tracker's speed"). The arithmetic is ``closest.triangle_weights``'s,
operation for operation and in the same order, and the choice among the candidates is the
same (the smallest squared distance, ties to the lowest triangle index), so the answers are
the same to the bit (``tests/test_geometry.py``).

``surface_candidates`` is None where Numba is missing: ``closest`` then uses NumPy.
"""

import numpy as np

try:
    from numba import njit
except ImportError:  # pragma: no cover - only without numba
    njit = None


def _jit(fn):
    # module-level functions, so that Numba's on-disk cache finds them (closures recompile)
    return njit(cache=True, nogil=True)(fn) if njit is not None else None


@_jit
def _min_nan(x, y):  # np.minimum: NaN wins
    if x != x:
        return x
    if y != y:
        return y
    return x if x <= y else y


@_jit
def _clip01(x):  # np.clip(x, 0, 1): NaN stays
    if x < 0.0:
        return 0.0
    if x > 1.0:
        return 1.0
    return x


@_jit
def pair(p0, p1, p2, vertices, faces, f):
    """Squared distance from the point (p0, p1, p2) to triangle ``f`` and the barycentric
    weights (w1, w2) of its closest point: ``closest.triangle_weights``' arithmetic, operation
    for operation. NaN distance for a triangle with non-finite products."""
    tiny = 1e-300
    ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
    a0, a1, a2 = vertices[ia, 0], vertices[ia, 1], vertices[ia, 2]
    ab0, ab1, ab2 = vertices[ib, 0] - a0, vertices[ib, 1] - a1, vertices[ib, 2] - a2
    ac0, ac1, ac2 = vertices[ic, 0] - a0, vertices[ic, 1] - a1, vertices[ic, 2] - a2
    aa = ab0 * ab0 + ab1 * ab1 + ab2 * ab2
    ae = ab0 * ac0 + ab1 * ac1 + ab2 * ac2
    cc = ac0 * ac0 + ac1 * ac1 + ac2 * ac2
    bb = aa - 2 * ae + cc
    det = aa * cc - ae * ae
    ap0, ap1, ap2 = p0 - a0, p1 - a1, p2 - a2
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    pp = ap0 * ap0 + ap1 * ap1 + ap2 * ap2
    bd = d2 - d1 - ae + aa
    t_ab = _clip01(d1 / max(aa, tiny))
    t_ac = _clip01(d2 / max(cc, tiny))
    t_bc = _clip01(bd / max(bb, tiny))
    D_ab = pp - t_ab * (2 * d1 - t_ab * aa)
    D_ac = pp - t_ac * (2 * d2 - t_ac * cc)
    D_bc = pp - 2 * d1 + aa - t_bc * (2 * bd - t_bc * bb)
    s = (cc * d1 - ae * d2) / det if det != 0.0 else np.nan
    t = (aa * d2 - ae * d1) / det if det != 0.0 else np.nan
    r0 = ap0 - s * ab0 - t * ac0
    r1 = ap1 - s * ab1 - t * ac1
    r2 = ap2 - s * ab2 - t * ac2
    D_in = r0 * r0 + r1 * r1 + r2 * r2
    edge = _min_nan(_min_nan(D_ab, D_ac), D_bc)
    inside = s >= 0 and t >= 0 and s + t <= 1 and D_in <= edge
    if inside:
        d = D_in
        w1, w2 = s, t
    else:
        d = edge if edge != edge else max(edge, 0.0)
        if D_ab <= D_ac and D_ab <= D_bc:
            w1, w2 = t_ab, 0.0
        elif D_ac <= D_bc:
            w1, w2 = 0.0, t_ac
        else:
            w1, w2 = 1.0 - t_bc, t_bc
    return d, w1, w2


@_jit
def surface_candidates(points, vertices, faces, table, nearest):
    """face (N,) and barycentric weights (N, 3) of each point's closest point among the
    triangles incident to its ``nearest`` vertices; face −1 where no candidate had a
    finite distance (the caller falls back)."""
    N = points.shape[0]
    near = nearest.shape[1]
    m = table.shape[1]
    face = np.full(N, -1, np.int64)
    bary = np.zeros((N, 3))
    for i in range(N):
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        best = np.inf
        bf = -1
        b1 = 0.0
        b2 = 0.0
        for j in range(near):
            v = nearest[i, j]
            for slot in range(m):
                f = table[v, slot]
                if f < 0:
                    break
                d, w1, w2 = pair(p0, p1, p2, vertices, faces, f)
                if d < best or (d == best and f < bf):
                    best, bf, b1, b2 = d, f, w1, w2
        face[i] = bf
        bary[i, 0] = 1.0 - b1 - b2
        bary[i, 1] = b1
        bary[i, 2] = b2
    return face, bary


@_jit
def surface_normals(points, vertices, faces, face, bary):
    """(N, 3) unit normals at the closest points (``closest.surface_normals``' rule): p/|p|
    with p = point − closest point, oriented like the face, where |p| > 1e-9 mm; the face's
    own normal on the surface. The closest point is summed as a CSR product S·X sums it
    (w_a x_a + w_b x_b, then + w_c x_c), so the bits are NumPy's."""
    N = points.shape[0]
    out = np.empty((N, 3))
    for i in range(N):
        f = face[i]
        ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
        a0, a1, a2 = vertices[ia, 0], vertices[ia, 1], vertices[ia, 2]
        u0, u1, u2 = vertices[ib, 0] - a0, vertices[ib, 1] - a1, vertices[ib, 2] - a2
        v0, v1, v2 = vertices[ic, 0] - a0, vertices[ic, 1] - a1, vertices[ic, 2] - a2
        n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
        ln = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        ln = max(ln, 1e-300)
        n0, n1, n2 = n0 / ln, n1 / ln, n2 / ln
        wa, wb, wc = bary[i, 0], bary[i, 1], bary[i, 2]
        q0 = wa * a0 + wb * vertices[ib, 0] + wc * vertices[ic, 0]
        q1 = wa * a1 + wb * vertices[ib, 1] + wc * vertices[ic, 1]
        q2 = wa * a2 + wb * vertices[ib, 2] + wc * vertices[ic, 2]
        p0, p1, p2 = points[i, 0] - q0, points[i, 1] - q1, points[i, 2] - q2
        d = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
        if d > 1e-9:
            s = -1.0 if p0 * n0 + p1 * n1 + p2 * n2 < 0 else 1.0
            n0, n1, n2 = s * p0 / d, s * p1 / d, s * p2 / d
        out[i, 0], out[i, 1], out[i, 2] = n0, n1, n2
    return out

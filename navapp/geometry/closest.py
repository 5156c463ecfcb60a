"""Closest points on triangle surfaces and polylines, vectorised.

Candidates come from a KD-tree on the vertices: the triangles (segments) incident to the
``near`` nearest vertices are tested exactly, which finds the true closest point for any
query whose nearest surface point lies on a triangle incident to one of its nearest
vertices (always the case for well-shaped meshes and queries near the surface). Skinny
triangles need more vertices: the decimated vessel surfaces use ``NEAR_DECIMATED``.

LM searches the model surfaces with ``bvh``'s hierarchy instead, refitted per evaluation:
exact everywhere and as fast or faster (docs/decisions/speed.md, "Closest points at the tracker's
speed"); this k-d path remains where Numba is missing, for the centerlines, and as the
benches' "before" (``kd_search``). pykdtree builds and queries the tree in half the time of
SciPy's cKDTree (same neighbours), so ``vertex_tree`` uses it where installed. The candidate
triangles' test is compiled by Numba where installed (``closest_compiled``: the same bits as
NumPy's).
"""

from contextlib import AbstractContextManager

import numpy as np
from scipy.spatial import cKDTree

from ..switches import Before
from ..threads import limit_threads


def _fast_tree():
    """pykdtree's KDTree: a declared dependency; None where it is missing (SciPy's then)."""
    try:
        from pykdtree.kdtree import KDTree
    except ImportError:  # pragma: no cover - only without pykdtree
        return None
    return KDTree


_FastTree = _fast_tree()

NEAR = 2  # nearest vertices whose incident cells are tested
# quadric-decimated surfaces (the vessels, ``registration.model.VESSEL_FACES``): with two
# nearest vertices 4 % of the portal contour points of the demo missed their closest
# triangle (by up to 0.28 mm), with three 0.3 %, with four none (docs/decisions/speed.md)
NEAR_DECIMATED = 4


def vertex_tree(vertices):
    """A k-d tree of ``vertices`` (V, 3) for ``nearest_vertices``, built to be used once (LM
    builds one per deformed feature and evaluation): pykdtree, else SciPy's cKDTree."""
    vertices = np.ascontiguousarray(vertices, dtype=float)
    if _FastTree is not None:
        return _FastTree(vertices)
    # unbalanced and not compacted: half the build time, queries as fast near the surface
    return cKDTree(vertices, balanced_tree=False, compact_nodes=False)


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


def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def triangle_weights(p, tri, index=None):
    """Barycentric weights (K, 3) of the closest points on triangles ``tri`` (K, 3, 3) to
    points ``p`` (K, 3), and the squared distances (K,). With ``index`` (K,), ``tri`` holds
    U distinct triangles (U, 3, 3) and point k is tested against ``tri[index[k]]``.

    The projection onto the triangle's plane is the answer when it falls inside; otherwise
    the closest point lies on the boundary and is the nearest of the three clamped edge
    projections. Everything is written with the dot products of ab, ac and ap on
    coordinate-major (3, K) arrays: this runs on ~16,000 candidate triangles per LM
    evaluation, and it is 2.5× faster than Ericson's region tests with (K, 3) rows. The
    products of ab and ac alone are made once per distinct triangle (LM's candidates test
    ~1,600 triangles ~8,500 times), by the same operations, so the answer is the same to
    the bit. Degenerate triangles (NaN/inf in the plane solve) fall through to their edges.
    """
    T = np.ascontiguousarray(np.transpose(tri, (1, 2, 0)))  # (vertex, coordinate, K or U)
    a = T[0]
    ab, ac = T[1] - a, T[2] - a
    aa, ae, cc = _dot(ab, ab), _dot(ab, ac), _dot(ac, ac)
    bb = aa - 2 * ae + cc  # |bc|²
    det = aa * cc - ae * ae
    if index is not None:
        a, ab, ac = a[:, index], ab[:, index], ac[:, index]
        aa, ae, cc, bb, det = aa[index], ae[index], cc[index], bb[index], det[index]
    ap = np.ascontiguousarray(np.transpose(p)) - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    pp = _dot(ap, ap)
    bd = d2 - d1 - ae + aa  # bc·(p − b)
    tiny = 1e-300
    t_ab = np.clip(d1 / np.maximum(aa, tiny), 0.0, 1.0)
    t_ac = np.clip(d2 / np.maximum(cc, tiny), 0.0, 1.0)
    t_bc = np.clip(bd / np.maximum(bb, tiny), 0.0, 1.0)
    D_ab = pp - t_ab * (2 * d1 - t_ab * aa)
    D_ac = pp - t_ac * (2 * d2 - t_ac * cc)
    D_bc = pp - 2 * d1 + aa - t_bc * (2 * bd - t_bc * bb)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (cc * d1 - ae * d2) / det
        t = (aa * d2 - ae * d1) / det
        r = ap - s * ab - t * ac
        D_in = _dot(r, r)
        in_plane = (s >= 0) & (t >= 0) & (s + t <= 1)
    edge = np.minimum(np.minimum(D_ab, D_ac), D_bc)
    # a nearly degenerate triangle gives a meaningless in-plane (s, t); its point is then
    # farther than the nearest edge point, so the comparison also guards it
    inside = in_plane & (D_in <= edge)
    use_ab = (D_ab <= D_ac) & (D_ab <= D_bc)
    use_ac = ~use_ab & (D_ac <= D_bc)
    w = np.empty((3, len(pp)))
    w[1] = np.where(inside, s, np.where(use_ab, t_ab, np.where(use_ac, 0.0, 1.0 - t_bc)))
    w[2] = np.where(inside, t, np.where(use_ab, 0.0, np.where(use_ac, t_ac, t_bc)))
    w[0] = 1.0 - w[1] - w[2]
    return w.T, np.where(inside, D_in, np.maximum(edge, 0.0))


def nearest_vertices(tree, points, near=NEAR):
    """Indices (N, near) of the ``near`` vertices nearest each point, from a k-d tree
    (``vertex_tree`` or a cKDTree)."""
    points = np.ascontiguousarray(points, dtype=float)
    # one OpenMP thread for pykdtree: a query of ~1,000 points ends before a second thread
    # pays, and OpenMP's waiting threads took CPU from the rest on 2 cores (a fresh
    # registration: 2.2 s CPU with two threads, 1.8 s with one; docs/decisions/speed.md)
    with limit_threads(1):
        found = tree.query(points, k=near)[1]
    found = np.asarray(found, np.int64).reshape(len(points), near)
    # a k-d tree answers "none" (the vertex count) for a point whose distance is not finite:
    # the compiled candidate test would read past its arrays with it (a crash of the process)
    n = getattr(tree, "n", None)
    if n is None:
        n = len(tree.data)
    if len(found) and int(found.max()) >= n:
        far = points[(found >= n).any(axis=1)]
        raise ValueError(f"closest points: {len(far)} of {len(points)} points lie too far from the surface to "
                         f"measure (up to {np.abs(far).max():.3g} mm from the origin, or not finite)")
    return found


_compiled: list = []  # the compiled candidate test, or None; imported on first use (Numba takes ~1 s to load)
_numpy_only = Before()  # ``numpy_test``
_kd_only = Before()  # ``kd_search``


def _surface_kernel():
    if _numpy_only:
        return None
    if not _compiled:
        from .closest_compiled import surface_candidates

        _compiled.append(surface_candidates)
    return _compiled[0]


def _normals_kernel():
    if _numpy_only or _surface_kernel() is None:
        return None
    from .closest_compiled import surface_normals as kernel

    return kernel


def numpy_test() -> AbstractContextManager[None]:
    """Within it, ``closest_on_surface`` tests the candidates with NumPy, as before the
    compiled test (``navapp bench live`` runs both in one sitting). Process-wide: for
    benchmarks, not for code that runs beside other registrations."""
    return _numpy_only.taken()


def kd_search() -> AbstractContextManager[None]:
    """Within it, LM searches the model surfaces by the k-d tree's candidate triangles
    (``closest_on_surface``), as before the refitted hierarchy (``bvh``); for the benches'
    "before", process-wide like ``numpy_test``."""
    return _kd_only.taken()


def hierarchy_search() -> bool:
    """Whether LM searches surfaces with the refitted hierarchy (``bvh``): where Numba is
    installed and outside ``kd_search`` / ``numpy_test``."""
    if _kd_only or _numpy_only:
        return False
    try:
        import numba  # noqa: F401
    except ImportError:  # pragma: no cover - only without numba
        return False
    return True


def closest_on_surface(points, vertices, faces, table, near=NEAR, tree=None, nearest=None):
    """Closest surface points. Returns face (N,), barycentric (N, 3), closest (N, 3).

    ``table`` is ``incidence(len(vertices), faces)``; ``tree`` an optional prebuilt
    cKDTree of ``vertices``, or ``nearest`` the points' nearest vertices already found
    (``nearest_vertices``).
    """
    points = np.asarray(points, float)
    vi = nearest if nearest is not None else nearest_vertices(tree or cKDTree(vertices), points, near)
    if (kernel := _surface_kernel()) is not None and len(points):
        # compiled: the same arithmetic and choice, without the pairs' temporaries
        vertices = np.ascontiguousarray(vertices, dtype=float)
        face, bary = kernel(np.ascontiguousarray(points), vertices, faces, table,
                                        np.ascontiguousarray(vi, dtype=np.int64))
        if (face >= 0).all():
            return face, bary, np.einsum("ij,ijk->ik", bary, vertices[faces[face]])
    return _closest_on_surface_numpy(points, vertices, faces, table, vi)


def surface_normals(points, vertices, faces, face, bary):
    """Unit normals (N, 3) at the closest points (``closest_on_surface``'s face, bary).

    Where the closest point lies inside a triangle the normal is the face's; where it lies
    on an edge or vertex (common for data off a convex patch) the face normal is
    ill-defined and the gradient of the distance field, p/|p| with p the point minus its
    closest point, is the normal of the surface's offset there. p/|p| oriented like the
    face covers both (it makes nᵀp the true point–surface distance); the face normal where
    |p| ≤ 1e-9 mm. Compiled where Numba is (``closest_compiled``, the same bits)."""
    points = np.asarray(points, float)
    if (kernel := _normals_kernel()) is not None and len(points):
        return kernel(np.ascontiguousarray(points), np.ascontiguousarray(vertices, dtype=float), faces,
                      np.ascontiguousarray(face, dtype=np.int64), np.ascontiguousarray(bary, dtype=float))
    return _surface_normals_numpy(points, vertices, faces, face, bary)


def _surface_normals_numpy(points, vertices, faces, face, bary):
    tri = faces[face]
    a, b, c = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    nrm = np.cross(b - a, c - a)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    # the closest point summed as a CSR product S·X sums it (``objective.correspond``'s S)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    p = points - q
    d = np.linalg.norm(p, axis=1)
    off = d > 1e-9
    sign = np.where(np.einsum("ij,ij->i", p, nrm) < 0, -1.0, 1.0)
    nrm[off] = sign[off, None] * p[off] / d[off, None]
    return nrm


def _closest_on_surface_numpy(points, vertices, faces, table, vi):
    """``closest_on_surface`` in NumPy: where Numba is missing, and the reference of its
    compiled test (``closest_compiled``)."""
    cand = np.sort(table[vi.reshape(len(points), -1)].reshape(len(points), -1), axis=1)  # (N, near*m)
    # test each distinct incident face once: the padding (-1) and the faces the near
    # vertices share are about half of the table's rows
    valid = cand >= 0
    valid[:, 1:] &= cand[:, 1:] != cand[:, :-1]
    r, c = np.nonzero(valid)
    f = cand[r, c]
    # each distinct candidate triangle's own products once (``triangle_weights``)
    seen = np.zeros(len(faces), bool)
    seen[f] = True
    distinct = np.flatnonzero(seen)
    w, dist2 = triangle_weights(points[r], vertices[faces[distinct]], (np.cumsum(seen) - 1)[f])
    d = np.full(cand.shape, np.inf)
    d[r, c] = dist2
    # a point with no finite distance to any candidate (squared distances overflow far off, or
    # not finite) has no closest point: said, where the pick below took another point's last
    # candidate or, with none at all, raised an IndexError (docs/decisions/live.md, "A start that
    # leaves the organ")
    lost = ~np.isfinite(d.min(axis=1)) if len(points) else np.zeros(0, bool)
    if lost.any():
        raise ValueError(f"closest points: {int(lost.sum())} of {len(points)} points lie too far from the surface "
                         f"to measure (up to {np.abs(points[lost]).max():.3g} mm from the origin, or not finite)")
    flat = np.full(cand.shape, -1)
    flat[r, c] = np.arange(len(r))
    sel = flat[np.arange(len(points)), np.argmin(d, axis=1)]
    face, bary = f[sel], w[sel]
    return face, bary, np.einsum("ij,ijk->ik", bary, vertices[faces[face]])


def closest_on_polyline(points, vertices, segments, table, near=NEAR, tree=None, nearest=None):
    """Closest points on polyline segments. Returns segment (N,), t (N,), closest (N, 3)."""
    points = np.asarray(points, float)
    vi = nearest if nearest is not None else nearest_vertices(tree or cKDTree(vertices), points, near)
    cand = table[vi.reshape(len(points), -1)].reshape(len(points), -1)
    valid = cand >= 0
    cs = np.where(valid, cand, 0)
    a = vertices[segments[cs, 0]]
    b = vertices[segments[cs, 1]]
    ab = b - a
    t = np.einsum("ncj,ncj->nc", points[:, None] - a, ab) / np.maximum(np.einsum("ncj,ncj->nc", ab, ab), 1e-300)
    t = np.clip(t, 0, 1)
    q = a + t[..., None] * ab
    d = np.linalg.norm(q - points[:, None], axis=2)
    d[~valid] = np.inf
    best = np.argmin(d, axis=1)
    rows = np.arange(len(points))
    return cs[rows, best], t[rows, best], q[rows, best]

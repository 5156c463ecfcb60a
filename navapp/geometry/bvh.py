"""Exact closest points on a triangle surface whose vertices move: a bounding-volume
hierarchy whose tree is built once, on the undeformed surface, and whose boxes are refitted
to the deformed vertices at every LM evaluation. Compiled by Numba.

LM deforms the model surfaces at every evaluation, so a search structure built on the
vertices (the k-d tree of ``closest``) is rebuilt each time, and its candidates (the
triangles around a point's nearest vertices) are exact only where the closest triangle
touches one of them. Here the tree's topology never changes: a refit is one pass over the
triangles (boxes of each leaf, then each parent from its children), and the query visits
the boxes nearest-first, skipping a box farther than the best triangle so far. The answer is
the closest triangle over the whole surface, by ``closest_compiled.pair``'s arithmetic and
its tie rule (the lowest triangle index among equal squared distances): the same bits as
an exhaustive search, and as the k-d path wherever that found the closest triangle. A
box is skipped only when it is farther than the best by more than a rounding margin, so
rounding in the boxes' distances never drops a tied or nearer triangle.
Measured against the alternatives: docs/decisions/speed.md, "Closest points at the tracker's speed".
"""

import numpy as np

from ..compiled import CHUNK, prange, split_jit
from ..threads import SPLIT_MIN, kernel_threads
from .closest_compiled import _jit, pair

LEAF = 4  # triangles per leaf at most


@_jit
def build(vertices, faces, leaf):
    """Tree over the triangles by median splits of their centroids along each box's longest
    side. Returns order (F,) the triangles in leaf order, and per node (at most 2F): left
    child (−1 for a leaf; the right child is left + 1), first slot in ``order`` and count.
    Children come after their parent, so a reverse sweep refits bottom-up."""
    F = faces.shape[0]
    cen = np.empty((F, 3))
    for f in range(F):
        for k in range(3):
            cen[f, k] = (vertices[faces[f, 0], k] + vertices[faces[f, 1], k] + vertices[faces[f, 2], k]) / 3.0
    order = np.arange(F)
    cap = max(2 * F, 1)
    left = np.full(cap, -1, np.int64)
    first = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
    count[0] = F
    n_nodes = 1
    stack = np.empty(cap, np.int64)
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        s, c = first[node], count[node]
        if c <= leaf:
            continue
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for j in range(s, s + c):
            for k in range(3):
                x = cen[order[j], k]
                lo[k] = min(lo[k], x)
                hi[k] = max(hi[k], x)
        axis = int(np.argmax(hi - lo))
        seg = order[s:s + c]
        order[s:s + c] = seg[np.argsort(cen[seg, axis], kind="mergesort")]
        half = c // 2
        left[node] = n_nodes
        first[n_nodes], count[n_nodes] = s, half
        first[n_nodes + 1], count[n_nodes + 1] = s + half, c - half
        stack[top] = n_nodes
        stack[top + 1] = n_nodes + 1
        top += 2
        n_nodes += 2
    return order, left[:n_nodes].copy(), first[:n_nodes].copy(), count[:n_nodes].copy()


@_jit
def refit(vertices, faces, order, left, first, count):
    """Boxes (nodes, 2, 3): each node's lowest and highest corner around its triangles at
    ``vertices``."""
    n = left.shape[0]
    box = np.empty((n, 2, 3))
    for node in range(n - 1, -1, -1):
        c = left[node]
        if c < 0:
            l0 = l1 = l2 = np.inf
            h0 = h1 = h2 = -np.inf
            for j in range(first[node], first[node] + count[node]):
                f = order[j]
                for v in range(3):
                    x = vertices[faces[f, v], 0]
                    y = vertices[faces[f, v], 1]
                    z = vertices[faces[f, v], 2]
                    l0, h0 = min(l0, x), max(h0, x)
                    l1, h1 = min(l1, y), max(h1, y)
                    l2, h2 = min(l2, z), max(h2, z)
            box[node, 0, 0], box[node, 0, 1], box[node, 0, 2] = l0, l1, l2
            box[node, 1, 0], box[node, 1, 1], box[node, 1, 2] = h0, h1, h2
        else:
            for k in range(3):
                box[node, 0, k] = min(box[c, 0, k], box[c + 1, 0, k])
                box[node, 1, k] = max(box[c, 1, k], box[c + 1, 1, k])
    return box


@_jit
def _box_d2(p0, p1, p2, box, node):
    d = 0.0
    g = max(box[node, 0, 0] - p0, 0.0, p0 - box[node, 1, 0])
    d += g * g
    g = max(box[node, 0, 1] - p1, 0.0, p1 - box[node, 1, 1])
    d += g * g
    g = max(box[node, 0, 2] - p2, 0.0, p2 - box[node, 1, 2])
    d += g * g
    return d


@_jit
def _nearest(points, i, vertices, faces, order, left, first, count, box, start, stack, gap, face, bary):
    """Point i's closest triangle (``closest``), into face[i] and bary[i]; ``stack`` and
    ``gap`` (128,): scratch for the descent."""
    p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
    best = np.inf
    bf = -1
    b1 = 0.0
    b2 = 0.0
    if start[i] >= 0:
        d, w1, w2 = pair(p0, p1, p2, vertices, faces, start[i])
        if d < best:
            best, bf, b1, b2 = d, start[i], w1, w2
    stack[0] = 0
    gap[0] = 0.0  # each stacked node's box distance, computed when it was pushed
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        # skipped only beyond a rounding margin of the best: a tie is never lost
        if gap[top] > best * (1.0 + 1e-9) + 1e-12:
            continue
        c = left[node]
        if c < 0:
            for j in range(first[node], first[node] + count[node]):
                f = order[j]
                d, w1, w2 = pair(p0, p1, p2, vertices, faces, f)
                if d < best or (d == best and f < bf):
                    best, bf, b1, b2 = d, f, w1, w2
        else:
            g0 = _box_d2(p0, p1, p2, box, c)
            g1 = _box_d2(p0, p1, p2, box, c + 1)
            # the nearer child on top, searched first
            if g0 <= g1:
                stack[top], gap[top], stack[top + 1], gap[top + 1] = c + 1, g1, c, g0
            else:
                stack[top], gap[top], stack[top + 1], gap[top + 1] = c, g0, c + 1, g1
            top += 2
    face[i] = bf
    bary[i, 0] = 1.0 - b1 - b2
    bary[i, 1] = b1
    bary[i, 2] = b2


@_jit
def closest(points, vertices, faces, order, left, first, count, box, start):
    """face (N,) and barycentric weights (N, 3) of each point's closest point on the
    surface; ``start`` (N,) a triangle per point to begin from (−1: none), e.g. the previous
    evaluation's: it only makes the first bound tight, the answer does not depend on it.
    Face −1 where no triangle has a finite distance."""
    N = points.shape[0]
    face = np.full(N, -1, np.int64)
    bary = np.zeros((N, 3))
    stack = np.empty(128, np.int64)
    gap = np.empty(128)
    for i in range(N):
        _nearest(points, i, vertices, faces, order, left, first, count, box, start, stack, gap, face, bary)
    return face, bary


def _closest_split(points, vertices, faces, order, left, first, count, box, start, face, bary):
    """``closest`` with the points split among Numba's threads (``threads.split_kernels``), in
    chunks of ``CHUNK``: each point searched as there, the same bits. ``face`` (N,) and ``bary``
    (N, 3) are filled (made by the caller: NumPy's constructors inside a parallel function
    become parallel loops of their own, each a hand-over to the threads)."""
    N = points.shape[0]
    for c in prange((N + CHUNK - 1) // CHUNK):
        stack = np.empty(128, np.int64)
        gap = np.empty(128)
        for i in range(c * CHUNK, min(N, (c + 1) * CHUNK)):
            _nearest(points, i, vertices, faces, order, left, first, count, box, start, stack, gap, face, bary)


closest_split = split_jit(_closest_split)


class SurfaceHierarchy:
    """The tree of one triangle surface, built once (on its undeformed vertices); ``refit``
    gives the boxes at any deformed vertices, ``closest`` the exact closest points there.

    Parameters
    ----------
    vertices : (V, 3) mm
        the surface's vertices when the tree is built (any deformed state is searched
        exactly; one far from it only visits more boxes).
    faces : (F, 3) int
        triangles.
    """

    def __init__(self, vertices, faces):
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.order, self.left, self.first, self.count = build(
            np.ascontiguousarray(vertices, dtype=float), self.faces, LEAF)

    def refit(self, vertices) -> np.ndarray:
        """The nodes' boxes (nodes, 2, 3) at ``vertices`` (V, 3) mm."""
        return refit(np.ascontiguousarray(vertices, dtype=float), self.faces, self.order, self.left, self.first,
                     self.count)

    def closest(self, points, vertices, boxes, start=None):
        """face (N,) and barycentric weights (N, 3) of the closest surface points of ``points``
        (N, 3) mm, at ``vertices`` whose ``boxes`` (``refit``) are given; ``start`` (N,):
        optional triangles to begin from (speed only). Face −1 where no distance is finite."""
        points = np.ascontiguousarray(points, dtype=float)
        start = np.full(len(points), -1, np.int64) if start is None else np.ascontiguousarray(start, dtype=np.int64)
        vertices = np.ascontiguousarray(vertices, dtype=float)
        if len(points) >= SPLIT_MIN and kernel_threads() > 1:
            face, bary = np.empty(len(points), np.int64), np.empty((len(points), 3))
            closest_split(points, vertices, self.faces, self.order, self.left, self.first, self.count, boxes, start,
                          face, bary)
            return face, bary
        return closest(points, vertices, self.faces, self.order, self.left, self.first, self.count, boxes, start)

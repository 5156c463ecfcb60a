"""Deform only the part of a model surface that the closest-point search reaches.

An LM evaluation deforms each model surface by eq. 8 and searches it for the data's closest
points. The whole deformation reads the surface's B·J_u (the liver's is 20 MB), yet a live
update's data touch a fifth of the liver and of the vessels. Here the surface's hierarchy
(``geometry.bvh``, built on the undeformed surface) gets boxes that bound its deformed
triangles at α without deforming them, and the search deforms a vertex only when it tests a
triangle of it: the answer is the exact closest triangle over the whole surface, as the
refitted hierarchy gives it, from the vertices it reached.

**The bound.** The hierarchy's nodes are grouped into chunks (the highest nodes of at most
``CHUNK`` triangles). Over a chunk c the basis rows are fitted once by a linear function of
the undeformed position z (local frame, z = x0 − x̄0):

    B_i J_u = m_c + G_c (z_i − z̄_c) + E_i      (each 3 × 3k; E_i the fit's remainder)

so at α a vertex's deformed local position z_i + B_i J_u α lies, for a node d of the chunk
whose undeformed box is z̄_d ± h_d,

    within  z̄_d + m_c α + (G_c α)(z̄_d − z̄_c)  ±  (|I + G_c α| h_d + e_c ‖α‖)

with e_c the largest row norm of E over the chunk, per axis. This holds for any α (it is an
inequality, not an approximation): a poor fit only loosens it. The modes are smooth, so over
a chunk the remainder is small and the boxes stay within a fraction of a mm of the
refitted ones. A parent above the chunks gets the union of its children's boxes.

The data are carried into the local frame, y_loc = Rᵀ(y − τ − x̄0), to meet the boxes; the
triangles are tested in tracker space on the vertices deformed as eq. 8 deforms them, so the
answer (triangle, barycentric weights) is the exhaustive search's over those vertices. A box
is skipped only beyond a rounding margin of the best distance (``bvh``'s rule) and the
bound carries its own margin, so no tie or nearer triangle is lost to rounding.
Measured: docs/decisions.md, "Deforming only what the search reaches".
"""

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..threads import limit_threads
from .rotation import rotation

if TYPE_CHECKING:
    from ..geometry.bvh import SurfaceHierarchy

RANK = 6
CHUNK = 64  # triangles per chunk at most (docs/decisions.md: 32 / 64 / 128 measured)


@dataclass(frozen=True)
class ChunkBounds:
    """What bounds a surface's deformed boxes at any α (see the module's doc), for the
    nodes of its ``bvh.SurfaceHierarchy``.

    Attributes
    ----------
    chunk : (nodes,) int
        the chunk each node lies in; −1 above the chunks.
    leaf_of : (F,) int
        the leaf node each triangle lies in.
    centre, half : (nodes, 3) mm
        each node's undeformed box in the local frame, as centre ± half.
    origin : (C, 3) mm
        z̄_c, each chunk's mean undeformed vertex (local frame).
    rows : (C, 12 + r, 3k)
        per chunk, what is multiplied by α: m_c (3 rows, mm per unit α), G_c (9 rows, output
        axis major, per unit α) and the remainder's r leading right singular vectors v_j.
    reach : (C, 3, r) mm
        per axis, the largest |(UΣ)_(i, a), j| of the remainder's leading part.
    rest : (C, 3) mm
        per axis, the largest norm of a row of what the leading part leaves (times ‖α‖).
    """

    chunk: np.ndarray
    leaf_of: np.ndarray
    centre: np.ndarray
    half: np.ndarray
    origin: np.ndarray
    rows: np.ndarray
    reach: np.ndarray
    rest: np.ndarray

    def products(self, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """m_c α (C, 3), G_c α (C, 3, 3) and v_j·α (C, r): one BLAS product."""
        P = (self.rows.reshape(-1, len(alpha)) @ alpha).reshape(len(self.rows), -1)
        return (np.ascontiguousarray(P[:, :3]), np.ascontiguousarray(P[:, 3:12]).reshape(-1, 3, 3),
                np.ascontiguousarray(P[:, 12:]))


def chunk_bounds(hierarchy: "SurfaceHierarchy", rest: np.ndarray, BJ: np.ndarray, centroid: np.ndarray,
                 chunk: int = CHUNK, rank: int = RANK) -> ChunkBounds:
    """The ``ChunkBounds`` of a surface: ``rest`` (V, 3) mm its undeformed vertices, ``BJ``
    (V, 3, 3k) the basis carried to them, ``centroid`` x̄0 (3,) mm."""
    from ..geometry.bvh import refit  # Numba: only where surfaces are searched

    z = np.asarray(rest, float) - centroid
    boxes = refit(np.ascontiguousarray(z), hierarchy.faces, hierarchy.order, hierarchy.left, hierarchy.first,
                  hierarchy.count)
    left, first, count = hierarchy.left, hierarchy.first, hierarchy.count
    which = np.full(len(left), -1, np.int64)
    heads = []
    for node in range(len(left)):  # children come after their parent
        if which[node] < 0 and count[node] <= chunk:
            which[node] = len(heads)
            heads.append(node)
        if which[node] >= 0 and left[node] >= 0:
            which[left[node]] = which[left[node] + 1] = which[node]
    n = BJ.shape[2]
    C = len(heads)
    origin = np.empty((C, 3))
    mean = np.empty((C, 3, n))
    grad = np.empty((C, 3, 3, n))
    remainder = np.empty((C, 3))
    r = min(rank, n)
    dirs = np.zeros((C, r, n))
    reach = np.zeros((C, 3, r))
    with limit_threads(1):  # small factorisations: threads only wait on each other
        for c, node in enumerate(heads):
            faces = hierarchy.faces[hierarchy.order[first[node]:first[node] + count[node]]]
            verts = np.unique(faces)
            zc = z[verts].mean(axis=0)
            design = np.column_stack([np.ones(len(verts)), z[verts] - zc])
            rows = BJ[verts].reshape(len(verts), 3 * n)
            # a patch of surface is nearly flat: the gradient across it is barely determined and
            # an exact fit would give it huge coefficients that cancel on the patch yet loosen
            # |G α| h. Directions below a tenth of the patch's extent are left to the remainder.
            size = max(float(np.abs(design[:, 1:]).max()), 1e-12)
            coef = np.linalg.lstsq(design / [1.0, size, size, size], rows, rcond=0.1)[0]
            coef[1:] /= size  # (4, 3n)
            E = (rows - design @ coef).reshape(len(verts), 3, n)
            origin[c] = zc
            mean[c] = coef[0].reshape(3, n)
            grad[c] = coef[1:].reshape(3, 3, n).transpose(1, 0, 2)
            # E's leading right singular directions: |E_i,a α| ≤ Σ_j |(UΣ)_(i,a),j| |v_j·α| + |tail_i,a| ‖α‖
            flat = E.reshape(-1, n)
            U, sv, Vt = np.linalg.svd(flat, full_matrices=False)
            k = min(r, len(sv))
            dirs[c, :k] = Vt[:k]
            US = (U[:, :k] * sv[:k]).reshape(len(verts), 3, k)
            reach[c, :, :k] = np.abs(US).max(axis=0)
            tail = (flat - (U[:, :k] * sv[:k]) @ Vt[:k]).reshape(len(verts), 3, n)
            # the tail as computed, and a margin for the rounding of computing it
            scale = np.abs(rows).max() if rows.size else 0.0
            remainder[c] = np.linalg.norm(tail, axis=2).max(axis=0) + 1e-12 * scale * np.sqrt(n)
    rows = np.concatenate([mean, grad.reshape(C, 9, n), dirs], axis=1)
    leaf_of = np.empty(len(hierarchy.faces), np.int64)
    for node in np.flatnonzero(left < 0):
        leaf_of[hierarchy.order[first[node]:first[node] + count[node]]] = node
    return ChunkBounds(which, leaf_of, (boxes[:, 0] + boxes[:, 1]) / 2, (boxes[:, 1] - boxes[:, 0]) / 2, origin, rows,
                       reach, remainder)


class ReachedSurface:
    """One model surface at one state β, deformed only where searched.

    ``local`` and ``X`` (V, 3) mm are eq. 8's x0 − x̄0 + J_u α and x(β) at the vertices
    deformed so far (``done``), NaN elsewhere: a product that reads an undeformed vertex
    gives NaN, never a silently stale number. A closest point's triangle is always deformed,
    so S·X and S·local over a correspondence's S are complete.

    Parameters
    ----------
    hierarchy : SurfaceHierarchy
        the surface's tree (``ModelFeature.search_tree``).
    bounds : ChunkBounds
        its bounds (``chunk_bounds``).
    rest : (V, 3) mm, BJ : (V, 3, 3k)
        the surface's undeformed vertices and the basis carried to them.
    beta : (3k + 6,)
        the state; centroid : (3,) mm, x̄0.
    previous : ReachedSurface, optional
        the same surface at an earlier state (the last evaluation's): its boxes, exact where
        it deformed a leaf whole, moved by the bound of the change of α are intersected with
        the bound from the undeformed surface. A live frame's α changes by a tenth of α or
        less, so this bound is the tighter one where the data are. Read, never written.
    """

    def __init__(self, hierarchy, bounds, rest, BJ, beta, centroid, previous=None):
        from .reach_compiled import boxes, deform_leaves

        self.hierarchy, self.bounds = hierarchy, bounds
        self.rest, self.BJ = np.ascontiguousarray(rest, dtype=float), np.ascontiguousarray(BJ, dtype=float)
        n = len(beta) - 6
        self.alpha = np.ascontiguousarray(beta[:n], dtype=float)
        self.R = np.ascontiguousarray(rotation(beta[n + 3:n + 6]))
        self.tau = np.ascontiguousarray(beta[n:n + 3], dtype=float)
        self.centroid = np.ascontiguousarray(centroid, dtype=float)
        V = len(rest)
        self.local, self.X = np.full((V, 3), np.nan), np.full((V, 3), np.nan)
        self.done = np.zeros(V, bool)
        self.products = bounds.products(self.alpha)
        self._queries: list = []  # (points, face) of this state's searches: the next state's first guesses
        self.starts: list = []
        if previous is not None and (previous.bounds is not bounds or previous.BJ is not BJ):
            previous = None
        if previous is None:
            change = (0.0, *self.products, np.empty((0, 2, 3)), np.empty((0, 3)), np.empty(0, bool))
        else:
            # the leaves of the last state's closest triangles are deformed first: the data are
            # mostly the same points, so those leaves get exact boxes and the search's pruning
            # is as tight there as over a refitted hierarchy
            self.starts = list(previous._queries)
            found = [f[f >= 0] for _p, f in self.starts]
            if found:
                h = hierarchy
                deform_leaves(np.unique(bounds.leaf_of[np.concatenate(found)]), h.first, h.count, h.order, h.faces,
                              self.rest, self.BJ, self.alpha, self.R, self.tau, self.centroid, self.local, self.X,
                              self.done)
            change = (float(np.linalg.norm(self.alpha - previous.alpha)),
                      *(x - y for x, y in zip(self.products, previous.products, strict=True)),
                      previous.boxes, previous.local, previous.done)
        b, h = bounds, hierarchy
        self.boxes = np.empty((len(h.left), 2, 3))
        boxes(self.boxes, float(np.linalg.norm(self.alpha)), *self.products, *change[:4], b.chunk, b.centre, b.half,
              b.origin, b.rest, b.reach, h.left, h.first, h.count, h.order, h.faces, self.local, self.done,
              previous is not None, *change[4:])

    def copy(self) -> "ReachedSurface":
        """The same state with its own arrays, to deform further apart from this one (an
        evaluation kept in the model's cache is never written to again)."""
        new = object.__new__(ReachedSurface)
        new.__dict__.update(self.__dict__)
        new.local, new.X, new.done = self.local.copy(), self.X.copy(), self.done.copy()
        new._queries = list(self._queries)
        return new

    def closest(self, points):
        """face (N,) and barycentric weights (N, 3) of the exact closest points of ``points``
        (N, 3) mm (tracker space) on the deformed surface; face −1 where none is finite."""
        from .reach_compiled import closest

        points = np.ascontiguousarray(points, dtype=float)
        carried = np.ascontiguousarray((points - self.tau - self.centroid) @ self.R)
        start = np.full(len(points), -1, np.int64)
        for p, f in self.starts:  # the same points searched at the last state: begin there
            m = min(len(p), len(points))
            if m and np.array_equal(p[:m], points[:m]):
                start[:m] = f[:m]
                break
        h = self.hierarchy
        face, bary = closest(points, carried, start, h.faces, h.order, h.left, h.first, h.count, self.boxes, self.rest,
                             self.BJ, self.alpha, self.R, self.tau, self.centroid, self.local, self.X, self.done)
        self._queries.append((points, face))
        return face, bary

    def deform_all(self) -> None:
        """Deform the vertices not deformed yet (a fallback that needs the whole surface)."""
        from .reach_compiled import deform_all

        deform_all(self.rest, self.BJ, self.alpha, self.R, self.tau, self.centroid, self.local, self.X, self.done)

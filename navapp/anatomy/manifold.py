"""Is a tet mesh's boundary a closed 2-manifold, and mending the pinches where it is not.

A mesher can return a valid tet mesh (no inverted tet, good angles) whose solid touches
itself along an edge or at a single vertex: two parts of the organ joined by a line or a
point. Its boundary is then not a closed manifold (an edge with four boundary faces, or a
vertex whose boundary faces form two fans), the surface the app draws has creases that
are not there, and the elastic model is hinged at the pinch. fTetWild can do this (its
output is not deterministic from run to run; seen once on a genus-one liver).

``boundary_defects`` finds both kinds of pinch. ``mend_pinches`` opens each one by
removing, among the tets that hold the pinched edge or vertex, every face-connected group
but the largest (by volume), and repeats until none is left; what remains is the largest
face-connected part of the solid. Opening a pinch removes a few tets at a contact the
surface never had, so the caller still checks the result against the input surface
(volume, Euler number).
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .tets import TetMesh, boundary_faces, simplex_keys, tet_volumes

_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


@dataclass(frozen=True)
class BoundaryDefects:
    """Pinches of a tet mesh's boundary.

    edges: (k, 2) int, node pairs with more than two boundary faces;
    vertices: (j,) int, boundary nodes whose boundary faces form more than one fan;
    parts: number of face-connected parts of the solid.
    """

    edges: np.ndarray
    vertices: np.ndarray
    parts: int

    @property
    def ok(self) -> bool:
        return len(self.edges) == 0 and len(self.vertices) == 0 and self.parts == 1

    def describe(self) -> str:
        bits = []
        if len(self.edges):
            bits.append(f"{len(self.edges)} pinched edges")
        if len(self.vertices):
            bits.append(f"{len(self.vertices)} pinched vertices")
        if self.parts != 1:
            bits.append(f"{self.parts} separate parts")
        return ", ".join(bits) or "a closed manifold"


def boundary_defects(mesh: TetMesh) -> BoundaryDefects:
    """The pinched edges and vertices of ``mesh``'s boundary and its number of parts."""
    faces = boundary_faces(mesh.tets, mesh.nodes)
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    _, first, inverse, counts = np.unique(simplex_keys(edges), return_index=True, return_inverse=True,
                                          return_counts=True)
    bad_edges = edges[first[counts != 2]]
    return BoundaryDefects(edges=bad_edges, vertices=_pinched_vertices(faces, inverse, counts),
                           parts=_parts(mesh.tets)[0])


def _pinched_vertices(faces, inverse, counts):
    """Boundary nodes whose incident faces form more than one fan: corners (face, node)
    are joined across each two-face edge at both its ends; a node is pinched when its
    corners fall into more than one connected group."""
    F = len(faces)
    corner = np.arange(3 * F).reshape(F, 3)  # corner id of (face f, local node i)
    face_of_edge = np.repeat(np.arange(F), 3)
    # for each edge occurrence (f, side s), the corners at its two end nodes
    start = corner[face_of_edge, np.tile([0, 1, 2], F)]
    end = corner[face_of_edge, np.tile([1, 2, 0], F)]
    node_start = faces.ravel()
    manifold = counts[inverse] == 2
    order = np.argsort(inverse, kind="stable")
    occ = order[manifold[order]].reshape(-1, 2)  # the two occurrences of each two-face edge
    a, b = occ[:, 0], occ[:, 1]
    # occurrence a runs p→q, b runs q→p (consistent winding) or p→q (not): match by node
    same = node_start[a] == node_start[b]
    a_start, a_end, b_start, b_end = start[a], end[a], start[b], end[b]
    u = np.concatenate([a_start, a_end])
    v = np.concatenate([np.where(same, b_start, b_end), np.where(same, b_end, b_start)])
    graph = sp.coo_matrix((np.ones(len(u)), (u, v)), shape=(3 * F, 3 * F))
    _, label = connected_components(graph, directed=False)
    node_of_corner = faces.ravel()
    pairs = np.unique(np.column_stack([node_of_corner, label]), axis=0)
    nodes, fans = np.unique(pairs[:, 0], return_counts=True)
    return nodes[fans > 1]


def _parts(tets):
    """(number, label per tet) of the face-connected parts of the solid."""
    _, inverse, counts = np.unique(simplex_keys(tets[:, _FACES].reshape(-1, 3)), return_inverse=True,
                                   return_counts=True)
    owner = np.repeat(np.arange(len(tets)), 4)
    shared = counts[inverse] == 2
    order = np.argsort(inverse[shared], kind="stable")
    pair = owner[shared][order].reshape(-1, 2)
    graph = sp.coo_matrix((np.ones(len(pair)), (pair[:, 0], pair[:, 1])), shape=(len(tets), len(tets)))
    return connected_components(graph, directed=False)


def _star_groups(tets, star, hold):
    """Face-connected groups among the tets ``star`` (indices) that all contain the node
    set ``hold``: two of them are joined when they share a face containing ``hold``."""
    sub = tets[star]
    keys, owners = [], []
    for i, t in enumerate(sub):
        for f in _FACES:
            face = t[f]
            if np.isin(hold, face).all():
                keys.append(tuple(sorted(face)))
                owners.append(i)
    first: dict = {}
    rows, cols = [], []
    for key, i in zip(keys, owners, strict=True):
        if key in first:
            rows.append(first[key])
            cols.append(i)
        else:
            first[key] = i
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(star), len(star)))
    return connected_components(graph, directed=False)


def mend_pinches(mesh: TetMesh, max_rounds: int = 20) -> tuple[TetMesh, int]:
    """Open every pinched edge and vertex of ``mesh`` (see module doc).

    Returns the mended mesh (orphan nodes dropped, nodes renumbered) and the number of
    tets removed. The result may still have defects if ``max_rounds`` was not enough:
    check it with ``boundary_defects``.
    """
    nodes, tets = mesh.nodes, mesh.tets
    vol = np.abs(tet_volumes(nodes, tets))
    removed = 0
    for _ in range(max_rounds):
        defects = boundary_defects(TetMesh(nodes, tets))
        if defects.ok:
            break
        drop = np.zeros(len(tets), bool)
        holds = [np.asarray(e) for e in defects.edges] + [np.array([v]) for v in defects.vertices]
        for hold in holds:
            star = np.flatnonzero(np.isin(tets, hold).sum(1) == len(hold))
            n, label = _star_groups(tets, star, hold)
            if n < 2:
                continue
            size = np.bincount(label, weights=vol[star], minlength=n)
            drop[star[label != np.argmax(size)]] = True
        if not drop.any():
            # no star splits (a pinch of another kind, or only separate parts): keep the largest part
            n, label = _parts(tets)
            if n < 2:
                break
            size = np.bincount(label, weights=vol, minlength=n)
            drop = label != np.argmax(size)
        removed += int(drop.sum())
        tets, vol = tets[~drop], vol[~drop]
        n, label = _parts(tets)
        if n > 1:
            size = np.bincount(label, weights=vol, minlength=n)
            keep = label == np.argmax(size)
            removed += int((~keep).sum())
            tets, vol = tets[keep], vol[keep]
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    return TetMesh(nodes=np.ascontiguousarray(nodes[used]), tets=np.ascontiguousarray(remap[tets])), removed

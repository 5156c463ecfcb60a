"""Control points on the liver surface and their tiles (paper §II-C).

Choice where the paper is open: tiles are *geodesic* Voronoi cells (nearest control point
by shortest path along the surface edges), not Euclidean ones, so that across the thin
left lobe a posterior node is never tiled to an anterior control point just millimetres
away through the parenchyma. Nodal areas are lumped (a third of each adjacent triangle).
"""

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree
from sklearn.cluster import KMeans

from ..threads import limit_threads


def surface_graph(nodes, faces, surface):
    """Sparse (S × S) edge-length graph of the surface triangles, in surface-local indices."""
    local = np.full(len(nodes), -1)
    local[surface] = np.arange(len(surface))
    f = local[faces]
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    w = np.linalg.norm(nodes[surface][e[:, 0]] - nodes[surface][e[:, 1]], axis=1)
    g = sp.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(len(surface),) * 2).tocsr()
    return g.maximum(g.T)


def nodal_areas(nodes, faces, surface):
    """Lumped area (S,) mm² of each surface node: a third of its triangles' areas."""
    tri = nodes[faces]
    a = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    acc = np.zeros(len(nodes))
    np.add.at(acc, faces.ravel(), np.repeat(a / 3.0, 3))
    return acc[surface]


def place_control_points(nodes, surface, k, seed=0):
    """k-means (k clusters) of the surface node positions, each centre snapped to its
    nearest surface node; returns k distinct global node indices, (k,)."""
    if k < 1 or k > len(surface):
        raise ValueError(f"k must be between 1 and the number of surface nodes ({len(surface)})")
    # One thread: a few thousand 3-D points take a fraction of a second, while OpenMP
    # threads spinning against other work on a 2-core machine took 8–10 s (measured).
    with limit_threads(1):
        km = KMeans(n_clusters=k, n_init=4, random_state=seed).fit(nodes[surface])
    return surface[snap_distinct(nodes[surface], km.cluster_centers_)]


def snap_distinct(points, centres, near=32) -> np.ndarray:
    """Each centre (k, 3) snapped to its nearest point (S, 3) not taken by an earlier
    centre: k distinct indices into ``points`` (k ≤ S). Centres that crowd together (more
    than ``near`` of them on one clump of points, e.g. k-means on duplicated nodes) fall
    back to the nearest free point of all."""
    points = np.asarray(points, float)
    if len(centres) > len(points):
        raise ValueError(f"{len(centres)} centres but only {len(points)} points to snap them to")
    tree = cKDTree(points)
    free = np.ones(len(points), bool)
    chosen = []
    for c in np.asarray(centres, float):
        _, idx = tree.query(c, k=min(len(points), near))
        idx = np.atleast_1d(idx)
        idx = idx[free[idx]]
        if len(idx):
            pick = int(idx[0])
        else:  # every one of the nearest points is taken
            rest = np.flatnonzero(free)
            pick = int(rest[np.argmin(np.linalg.norm(points[rest] - c, axis=1))])
        free[pick] = False
        chosen.append(pick)
    return np.array(chosen, int)


def geodesic_tiles(nodes, faces, surface, control):
    """Tile id (S,) in 0..k-1 of every surface node: its geodesically nearest control point."""
    g = surface_graph(nodes, faces, surface)
    local = np.searchsorted(surface, control)
    _, _, sources = dijkstra(g, directed=False, indices=local, min_only=True, return_predecessors=True)
    lookup = np.full(len(surface), -1)
    lookup[local] = np.arange(len(control))
    tiles = lookup[sources]
    if (tiles < 0).any():
        # a surface component without control point: fall back to Euclidean nearest
        miss = tiles < 0
        _, tiles[miss] = cKDTree(nodes[control]).query(nodes[surface][miss])
    return tiles

"""The linear tetrahedral mesh and its elementary queries (volumes, boundary faces, simplex
keys), below both the mesher (``meshing``) and the boundary mender (``manifold``)."""

from dataclasses import dataclass

import numpy as np


@dataclass
class TetMesh:
    """Linear tetrahedral mesh. nodes (M, 3) mm, tets (E, 4) int with positive volume."""

    nodes: np.ndarray
    tets: np.ndarray

    def boundary_faces(self) -> np.ndarray:
        """(F, 3) outward-oriented boundary triangles."""
        return boundary_faces(self.tets, self.nodes)

    def surface_nodes(self) -> np.ndarray:
        return np.unique(self.boundary_faces())


def tet_volumes(nodes, tets):
    """Signed volumes (E,) mm^3; positive for right-handed vertex order."""
    a, b, c, d = (nodes[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def simplex_keys(simplices: np.ndarray) -> np.ndarray:
    """One int64 per row of ``simplices`` (k, 2 or 3) node indices, equal for rows holding
    the same nodes in any order (a 1-D ``np.unique`` is several times faster than one over rows)."""
    s = np.sort(np.asarray(simplices, np.int64), axis=1)
    base = int(s.max()) + 1 if s.size else 1
    if base ** s.shape[1] >= 2 ** 63:  # would overflow (over 2 million nodes for faces): rank the rows instead
        return np.unique(s, axis=0, return_inverse=True)[1].ravel().astype(np.int64)
    key = s[:, 0]
    for j in range(1, s.shape[1]):
        key = key * base + s[:, j]
    return key


def boundary_faces(tets, nodes):
    """Faces used by exactly one tet, oriented with outward normals."""
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    _, idx, counts = np.unique(simplex_keys(faces), return_index=True, return_counts=True)
    # for a positively oriented tet these local faces wind outward, so boundary faces do too
    return faces[idx[counts == 1]]

"""Closest points on a triangle surface that deforms but keeps its triangles.

LM evaluates the closest points of fixed data on a model surface whose vertices move at every
evaluation. A bounding-volume hierarchy (FCPW's) is built once on a reference geometry (the
undeformed surface) and only refit when the vertices move (boxes recomputed bottom-up, the
tree kept): a refit costs a twentieth of a build, and the traversal stays exact whatever the
boxes' quality. The search itself runs in single precision (FCPW's); the barycentric weights
of the chosen triangle are recomputed in double precision, so an answer differs from the
exact one only where two triangles lie within single-precision rounding (~1e-5 mm) of each
other. The tree is always the reference geometry's and a refit depends only on the current
vertices, so an answer never depends on which geometries were searched before (ties between
triangles sharing the closest point resolve the same way every time). Measured against the
k-d tree on vertices it replaces: docs/decisions.md ("Closest points: a refit hierarchy").

Without FCPW (no wheel for the platform, e.g. Linux on ARM) the search falls back to the
k-d tree on the vertices and the triangles incident to the nearest ones (``closest``).
"""

import threading
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .closest import closest_on_surface, incidence, triangle_weights

try:  # optional at run time: see the module docstring
    import fcpw
except ImportError:  # pragma: no cover - exercised only where FCPW has no wheel
    fcpw = None


def available() -> bool:
    """FCPW is installed (otherwise ``SurfaceSearch`` uses the k-d tree fallback)."""
    return fcpw is not None


class SurfaceSearch:
    """Closest points on the triangles ``faces`` (F, 3) at whatever vertex positions each
    query gives, the hierarchy built once on ``reference`` (V, 3) and refit when the
    positions change.

    Safe to share between threads (one query at a time holds the structure).
    ``backend``: "fcpw" or "kdtree" (the fallback; also selectable for comparison).
    """

    def __init__(self, faces, reference, backend: str | None = None):
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.backend = backend or ("fcpw" if fcpw is not None else "kdtree")
        if self.backend == "fcpw" and fcpw is None:
            raise ImportError("fcpw is not installed")
        self._scene: Any = None
        self._at = None  # the vertex array the structure currently fits (held, compared by identity)
        self._table = None
        self._lock = threading.Lock()
        self.refits = 0  # how often the hierarchy was refit (for tests and benchmarks)
        if self.backend == "fcpw":
            scene = fcpw.scene_3D()
            scene.set_object_count(1)
            scene.set_object_vertices(np.asfortranarray(reference, dtype=np.float32), 0)
            scene.set_object_triangles(np.asfortranarray(self.faces, dtype=np.int32), 0)
            scene.build(fcpw.aggregate_type.bvh_surface_area, True)
            self._scene = scene

    def _fit(self, vertices):
        if self._at is vertices:
            return
        if self.backend == "kdtree":
            if self._table is None:
                self._table = incidence(len(vertices), self.faces)
            self._scene = cKDTree(vertices, balanced_tree=False, compact_nodes=False)
        else:
            # update_object_vertices keeps the primitives the tree points to (setting the
            # vertices anew would leave the tree pointing at freed ones)
            self._scene.update_object_vertices(fcpw.float_3D_list(np.asarray(vertices, dtype=np.float32)), 0)
            self._scene.refit()
            self.refits += 1
        self._at = vertices

    def prepare(self, vertices) -> None:
        """Fit the structure to ``vertices`` (V, 3) now (otherwise the next ``closest`` does)."""
        with self._lock:
            self._fit(vertices)

    def closest(self, points, vertices):
        """Closest points of ``points`` (N, 3) on the surface at ``vertices`` (V, 3), same
        length unit. Returns face (N,), barycentric weights (N, 3) and the points (N, 3)."""
        points = np.asarray(points, float)
        if len(points) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        with self._lock:
            self._fit(vertices)
            if self.backend == "kdtree":
                return closest_on_surface(points, vertices, self.faces, self._table, tree=self._scene)
            hits = fcpw.interaction_3D_list()
            self._scene.find_closest_points(np.asfortranarray(points, dtype=np.float32),
                                            np.full(len(points), np.inf, dtype=np.float32), hits)
            face = np.fromiter((h.primitive_index for h in hits), np.int64, len(points))
        tri = vertices[self.faces[face]]
        bary = triangle_weights(points, tri)[0]
        return face, bary, np.einsum("ij,ijk->ik", bary, tri)

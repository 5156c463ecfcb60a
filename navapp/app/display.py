"""The preoperative and true surfaces as the viewer draws them: a liver at most
``defaults.DISPLAY_FACES`` triangles, a vessel tree at most ``defaults.DISPLAY_VESSEL_FACES``
(quadric decimation), each made once and shared by every tab. The registered surfaces move
with every state, so theirs are drawn through a ``Follower``: a decimated copy whose vertices
are fixed barycentric combinations of the surface's own. Only the picture: the registration,
the error colours and the exports use the surfaces themselves. No viser here.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import trimesh

from ..defaults import DISPLAY_FACES, DISPLAY_VESSEL_FACES


@dataclass(frozen=True)
class Follower:
    """A moving surface as drawn: ``faces`` (f, 3) over drawn vertices that are ``weights``
    (n, V), barycentric weights on the surface's V vertices (None: the surface drawn whole)."""

    faces: np.ndarray
    weights: sp.csr_matrix | None

    def at(self, vertices: np.ndarray) -> np.ndarray:
        """The drawn vertices ``(n, 3) float32`` (mm) for the surface's ``(V, 3)`` vertices."""
        v = np.asarray(vertices, np.float64)
        return np.asarray(v if self.weights is None else self.weights @ v, np.float32)


def follower(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> Follower:
    """The ``Follower`` of a surface at ``vertices`` (V, 3) mm with ``faces`` (F, 3): its quadric
    decimation to ``max_faces`` triangles, each drawn vertex tied to the closest point of the
    surface (its triangle's three vertices, barycentric weights), so a deformed surface is
    drawn deformed alike."""
    faces = np.asarray(faces)
    if len(faces) <= max_faces:
        return Follower(faces.astype(np.int64), None)
    whole = trimesh.Trimesh(np.asarray(vertices, np.float64), faces, process=False)
    small = whole.simplify_quadric_decimation(face_count=max_faces)
    at, _, tri = trimesh.proximity.closest_point(whole, small.vertices)
    bary = trimesh.triangles.points_to_barycentric(whole.triangles[tri], at)
    n = len(at)
    weights = sp.csr_matrix((np.clip(bary, 0.0, 1.0).ravel(), (np.repeat(np.arange(n), 3), faces[tri].ravel())),
                            shape=(n, len(whole.vertices)))
    weights = sp.csr_matrix(weights.multiply(1.0 / np.asarray(weights.sum(axis=1))))  # rows sum to one
    return Follower(np.asarray(small.faces, np.int64), weights)


class DisplaySurfaces:
    """Decimated copies of surfaces, keyed by the surface object (its identity: a scene's
    surfaces are made once and never changed in place)."""

    def __init__(self, max_faces: int = DISPLAY_FACES, max_vessel_faces: int = DISPLAY_VESSEL_FACES):
        self.max_faces, self.max_vessel_faces = max_faces, max_vessel_faces
        self._lock = threading.Lock()
        self._made: dict[int, tuple[trimesh.Trimesh, np.ndarray, np.ndarray]] = {}
        self._followers: dict[int, tuple[np.ndarray, Follower]] = {}

    def follower(self, vertices: np.ndarray, faces: np.ndarray, vessel: bool = False) -> Follower:
        """How a registered surface with ``faces`` (F, 3), now at ``vertices`` (V, 3) mm, is
        drawn at any state: made once per surface (its ``faces`` array, the model's own) from
        the first state asked for, at most ``max_faces`` triangles (``max_vessel_faces`` for a
        vessel tree)."""
        with self._lock:
            made = self._followers.get(id(faces))
            if made is None or made[0] is not faces:
                made = (faces, follower(vertices, faces, self.max_vessel_faces if vessel else self.max_faces))
                self._followers[id(faces)] = made
            return made[1]

    def of(self, mesh: trimesh.Trimesh, vessel: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``(V, 3) float32`` vertices (mm) and ``(F, 3) int`` triangles of ``mesh`` as drawn:
        the mesh itself when it has at most ``max_faces`` triangles (``max_vessel_faces`` for a
        vessel tree), else its quadric decimation to that many."""
        budget = self.max_vessel_faces if vessel else self.max_faces
        with self._lock:  # tabs connect in viser's thread pool: each surface decimated once
            made = self._made.get(id(mesh))
            if made is None or made[0] is not mesh:
                if len(mesh.faces) > budget:
                    small = mesh.simplify_quadric_decimation(face_count=budget)
                    v, f = np.asarray(small.vertices), np.asarray(small.faces)
                else:
                    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
                made = (mesh, v.astype(np.float32), f.astype(np.int64))
                self._made[id(mesh)] = made
            return made[1], made[2]

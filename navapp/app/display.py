"""The preoperative and true surfaces as the viewer draws them: a liver at most
``defaults.DISPLAY_FACES`` triangles, a vessel tree at most ``defaults.DISPLAY_VESSEL_FACES``
(quadric decimation), each made once and shared by every tab. Only the picture: the
registration, the error colours and the exports use the surfaces themselves. No viser here.
"""

from __future__ import annotations

import threading

import numpy as np
import trimesh

from ..defaults import DISPLAY_FACES, DISPLAY_VESSEL_FACES


class DisplaySurfaces:
    """Decimated copies of surfaces, keyed by the surface object (its identity: a scene's
    surfaces are made once and never changed in place)."""

    def __init__(self, max_faces: int = DISPLAY_FACES, max_vessel_faces: int = DISPLAY_VESSEL_FACES):
        self.max_faces, self.max_vessel_faces = max_faces, max_vessel_faces
        self._lock = threading.Lock()
        self._made: dict[int, tuple[trimesh.Trimesh, np.ndarray, np.ndarray]] = {}

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

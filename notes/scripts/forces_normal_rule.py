"""Issue 47: the surface-forces study rows (``forces_study.py``) under another rule for the normal
at a closest point on an edge or vertex, to compare with the library's (the distance field's
gradient, ``geometry.closest.surface_normals``):

    python notes/scripts/forces_normal_rule.py RULE OUT.jsonl CASE_DIR...

RULE ``face``: the closest face's own normal for the residuals and the force directions (the code
before the mend, commit c459ce2: a tie's face is rounding's choice); ``vertex``: the residuals
as the library's, the force directions at the sites along the vertex-interpolated normal
(area-weighted vertex normals blended by the barycentric weights: continuous, but no longer the
residual's normal, so the fit leaves the data's own span). Prefix ``NAVAPP_SOLVER=superlu``
for SuperLU's nested dissection instead of PARDISO. Output: notes/forces_rounding_study.txt."""
import runpy
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from navapp.geometry.closest import closest_on_surface
from navapp.registration import forces


def face_normals(points, vertices, faces, face, bary):
    tri = faces[face]
    n = np.cross(vertices[tri[:, 1]] - vertices[tri[:, 0]], vertices[tri[:, 2]] - vertices[tri[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def vertex_correspondences(self, points, u):
    moved = self.nodes + u
    face, bary, _ = closest_on_surface(points, moved, self.faces, self.table)
    tri = self.faces[face]
    f = self.faces
    fn = np.cross(moved[f[:, 1]] - moved[f[:, 0]], moved[f[:, 2]] - moved[f[:, 0]])  # area-weighted
    vn = np.zeros_like(moved)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
    nrm = np.einsum("ij,ijk->ik", bary, vn[tri])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    A = sp.csr_matrix((bary.ravel(), (np.repeat(np.arange(len(points)), 3), tri.ravel())),
                      shape=(len(points), self.M))
    return A, nrm, np.einsum("ij,ij->i", points - A @ self.nodes, nrm)


rule = sys.argv[1]
if rule == "face":
    forces.surface_normals = face_normals
elif rule == "vertex":
    forces.SurfaceForces.correspondences = vertex_correspondences
else:
    sys.exit(f"{rule}: the rule is face or vertex")
script = str(Path(__file__).with_name("forces_study.py"))
sys.argv = [script, *sys.argv[2:]]
runpy.run_path(script, run_name="__main__")

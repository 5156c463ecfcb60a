"""Force-driven ground-truth deformation, independent of the registration basis.

The truth is solved on its own (finer) tet mesh with loads, not with prescribed control
point displacements, so it is not in the span of the LIBR basis (no inverse crime).
Linear elasticity (small deformation); the large-deformation, nonlinear solver of the
simulation issue is not built yet.

Loads (mm, Pa): gravity along ``gravity_dir`` (body force ρ g, ρ = 1060 kg/m³) and a
uniform pressure on the anterior surface (insufflation), with the posterior bare area
(surface nodes in the most posterior ``support_fraction`` of the liver's depth) fixed.
"""

from dataclasses import dataclass

import numpy as np

from ..anatomy.meshing import TetMesh
from ..mechanics.fem import Material, shape_gradients, stiffness
from ..mechanics.sparse import Factorisation

RHO = 1060.0  # kg/m³, liver density


@dataclass(frozen=True)
class Loading:
    gravity: float = 9.81  # m/s²
    gravity_dir: tuple = (0.0, -1.0, 0.0)  # supine patient: posterior
    pressure: float = 0.0  # Pa on the anterior surface (inward)
    support_fraction: float = 0.15


def solve_linear(mesh: TetMesh, loading: Loading, material: Material = Material()) -> np.ndarray:
    """Nodal displacements (M, 3) mm of the loaded, supported liver."""
    nodes, tets = mesh.nodes, mesh.tets
    M = len(nodes)
    K = stiffness(nodes, tets, material)  # Pa·mm = mN/mm with mm lengths
    _, vol = shape_gradients(nodes, tets)  # mm³
    # body force: ρ g [N/m³] · V [mm³] · 1e-9 m³/mm³ → N; in K's units forces are mN·… so use
    # Pa·mm² (= µN): N = 1e6 Pa·mm²  → f [Pa·mm²] = ρ g V 1e-9 · 1e6 = ρ g V 1e-3
    w = RHO * loading.gravity * vol * 1e-3
    f = np.zeros((M, 3))
    for a in range(4):
        np.add.at(f, tets[:, a], np.outer(w / 4, loading.gravity_dir))
    faces = mesh.boundary_faces()
    tri = nodes[faces]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) / 2  # area-weighted outward normal, mm²
    anterior = nrm[:, 1] / np.linalg.norm(nrm, axis=1) > 0.3
    if loading.pressure:
        for a in range(3):
            np.add.at(f, faces[anterior, a], -loading.pressure * nrm[anterior] / 3)
    surf = np.unique(faces)
    y = nodes[surf, 1]
    fixed = surf[y < y.min() + loading.support_fraction * (y.max() - y.min())]
    fd = (3 * fixed[:, None] + np.arange(3)).ravel()
    free = np.setdiff1d(np.arange(3 * M), fd)
    u = np.zeros(3 * M)
    with Factorisation(K[free][:, free]) as F:
        u[free] = F.solve(f.ravel()[free])
    return u.reshape(M, 3)

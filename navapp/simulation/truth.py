"""Force-driven ground-truth deformations, independent of the registration basis.

The truth is solved on its own (finer) tet mesh, driven by loads rather than by the
basis' prescribed control-point displacements, so it is not in the span of the LIBR
basis (no inverse crime).

Loads and supports (mm, Pa): gravity (ρ = 1060 kg/m³) along a direction tilted toward
the released side, optional uniform pressure on the anterior surface (insufflation); the
posterior bare area is always held, and so are the left and right triangular ligaments
and the falciform/coronary attachment unless a scene releases them (L, N or R).
Small deformation: linear elasticity. Large deformation (a scene's ``large = true``):
St-Venant–Kirchhoff hyperelasticity, total Lagrangian, Newton with load stepping.
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..anatomy.meshing import TetMesh
from ..errors import NavappError
from ..mechanics.fem import Material, shape_gradients, stiffness
from ..mechanics.sparse import Factorisation

RHO = 1060.0  # kg/m³, liver density


@dataclass(frozen=True)
class Loading:
    gravity: float = 9.81  # m/s²
    gravity_dir: tuple = (0.0, -1.0, 0.0)  # supine patient: toward posterior
    pressure: float = 0.0  # Pa on the anterior surface (inward)
    release: str = "N"  # which triangular ligament is released: "L", "N" or "R"


def supported_nodes(mesh: TetMesh, release: str = "N") -> dict:
    """Node sets held fixed, by name: bare area, left/right triangular ligaments,
    falciform attachment (as geometric regions of the boundary; see module doc)."""
    faces = mesh.boundary_faces()
    s = np.unique(faces)
    p = mesh.nodes[s]
    lo, hi = p.min(0), p.max(0)
    ext = hi - lo
    rel = (p - lo) / ext
    sets = {
        "bare_area": s[(rel[:, 1] < 0.12) & (rel[:, 2] > 0.35)],
        "left_triangular": s[(rel[:, 0] > 0.82) & (rel[:, 2] > 0.55) & (rel[:, 1] < 0.6)],
        "right_triangular": s[(rel[:, 0] < 0.12) & (rel[:, 2] > 0.6) & (rel[:, 1] < 0.45)],
        "falciform": s[(np.abs(rel[:, 0] - 0.6) < 0.05) & (rel[:, 2] > 0.5) & (rel[:, 1] > 0.6)],
    }
    if release == "L":
        sets.pop("left_triangular")
    elif release == "R":
        sets.pop("right_triangular")
    return sets


def _body_force(mesh, loading):
    _, vol = shape_gradients(mesh.nodes, mesh.tets)  # mm³
    # ρ g V: kg/m³ · m/s² · mm³ · 1e-9 m³/mm³ = N; K is in Pa·mm, forces in Pa·mm² = 1e-6 N
    w = RHO * loading.gravity * vol * 1e-9 * 1e6
    g = np.asarray(loading.gravity_dir, float)
    g = g / np.linalg.norm(g)
    f = np.zeros((len(mesh.nodes), 3))
    for a in range(4):
        np.add.at(f, mesh.tets[:, a], np.outer(w / 4, g))
    if loading.pressure:
        faces = mesh.boundary_faces()
        tri = mesh.nodes[faces]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) / 2  # area-weighted, mm²
        anterior = nrm[:, 1] / np.linalg.norm(nrm, axis=1) > 0.3
        for a in range(3):
            np.add.at(f, faces[anterior, a], -loading.pressure * nrm[anterior] / 3)
    return f.ravel()


def _free_dofs(mesh, loading):
    fixed = np.unique(np.concatenate(list(supported_nodes(mesh, loading.release).values())))
    fd = (3 * fixed[:, None] + np.arange(3)).ravel()
    return np.setdiff1d(np.arange(3 * len(mesh.nodes)), fd)


def solve_linear(mesh: TetMesh, loading: Loading, material: Material = Material()) -> np.ndarray:
    """Nodal displacements (M, 3) mm of the loaded, supported liver (linear elasticity)."""
    K = stiffness(mesh.nodes, mesh.tets, material)
    f = _body_force(mesh, loading)
    free = _free_dofs(mesh, loading)
    u = np.zeros(3 * len(mesh.nodes))
    with Factorisation(K[free][:, free]) as F:
        u[free] = F.solve(f[free])
    return u.reshape(-1, 3)


def svk_forces_and_tangent(nodes, tets, u, material: Material, tangent=True):
    """St-Venant–Kirchhoff internal forces (3M,) and tangent stiffness (3M × 3M) at
    displacement u (M, 3): F = I + ∇u, E = ½(FᵀF − I), S = λ tr E I + 2μE, P = FS;
    f_a = V P ∇N_a; K from ∂P/∂F = δ_ik S_lj + λ F_ij F_kl + μ(F_il F_kj + (FFᵀ)_ik δ_jl)."""
    lam, mu = material.lame()
    G, vol = shape_gradients(nodes, tets)  # (E, 4, 3)
    ue = u[tets]  # (E, 4, 3)
    F = np.eye(3) + np.einsum("eai,eaj->eij", ue, G)
    E = 0.5 * (np.einsum("eki,ekj->eij", F, F) - np.eye(3))
    S = lam * np.trace(E, axis1=1, axis2=2)[:, None, None] * np.eye(3) + 2 * mu * E
    P = F @ S
    fe = vol[:, None, None] * np.einsum("eij,eaj->eai", P, G)  # (E, 4, 3)
    M = len(nodes)
    f = np.zeros((M, 3))
    for a in range(4):
        np.add.at(f, tets[:, a], fe[:, a])
    if not tangent:
        return f.ravel(), None
    I3 = np.eye(3)
    FFt = F @ F.transpose(0, 2, 1)
    A = (np.einsum("ik,elj->eijkl", I3, S) + lam * np.einsum("eij,ekl->eijkl", F, F)
         + mu * (np.einsum("eil,ekj->eijkl", F, F) + np.einsum("eik,jl->eijkl", FFt, I3)))
    Ke = vol[:, None, None, None, None] * np.einsum("eaj,eijkl,ebl->eaibk", G, A, G)
    dof = 3 * tets[:, :, None] + np.arange(3)  # (E, 4, 3)
    rows = np.broadcast_to(dof[:, :, :, None, None], Ke.shape).ravel()
    cols = np.broadcast_to(dof[:, None, None, :, :], Ke.shape).ravel()
    K = sp.csr_matrix((Ke.ravel(), (rows, cols)), shape=(3 * M, 3 * M))
    return f.ravel(), K


def solve_svk(mesh: TetMesh, loading: Loading, material: Material = Material(), steps=4, tol=1e-8,
              max_newton=20, report=None) -> np.ndarray:
    """Large-deformation truth: Newton on St-Venant–Kirchhoff with ``steps`` load increments.

    Converged when the free-DOF residual norm falls below ``tol`` × the load norm.
    ``report(step, iteration, relative_residual)`` sees every Newton iteration.
    """
    f_ext = _body_force(mesh, loading)
    free = _free_dofs(mesh, loading)
    u = np.zeros(3 * len(mesh.nodes))
    scale = np.linalg.norm(f_ext[free])
    for step in range(1, steps + 1):
        load = f_ext * step / steps
        for it in range(1, max_newton + 1):
            fint, K = svk_forces_and_tangent(mesh.nodes, mesh.tets, u.reshape(-1, 3), material)
            r = (load - fint)[free]
            rel = np.linalg.norm(r) / scale
            if report:
                report(step, it, rel)
            if rel < tol:
                break
            with Factorisation(K[free][:, free]) as Fz:
                u[free] += Fz.solve(r)
        else:
            raise NavappError(f"large-deformation truth did not converge (load step {step}, residual {rel:.2e})")
    return u.reshape(-1, 3)

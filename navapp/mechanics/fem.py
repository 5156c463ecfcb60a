"""Linear-elastic finite elements on linear tetrahedra (paper eq. 1–2).

Units: node coordinates mm, displacements mm, Young's modulus E in Pa. Strains are then
dimensionless, stresses Pa, and K carries Pa·mm (= mN/mm); only ratios of K enter the
displacement-driven solves, so the mm/Pa mix is harmless there.
DOF order is node-major: DOF 3*i + d is node i, axis d (scikit-fem's interleaving).
Voigt order: xx, yy, zz, yz, xz, xy with engineering shear strains (γ = 2ε), so that
σ·ε (Voigt dot product) is the strain-energy density times two.
"""

from contextlib import AbstractContextManager
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..switches import Before

# Pa. The paper's text (and docs/design.md) say 2100 kPa; we use 2100 Pa. Displacement modes
# do not depend on E, but the strain-energy penalty w_E f_E² scales with E², and with the
# paper's w_E = 1e-8 Pa⁻² an E of 2.1 MPa makes the penalty dominate any millimetre-scale
# deformation; 2.1 kPa is the order of liver stiffness in the literature and gives the
# kind of gain the paper's Table II shows (the measurement: docs/decisions/registration.md, "Measured
# choices moved out of docstrings").
E_LIVER = 2100.0
NU_LIVER = 0.45


@dataclass(frozen=True)
class Material:
    E: float = E_LIVER  # Pa
    nu: float = NU_LIVER

    def lame(self):
        lam = self.E * self.nu / ((1 + self.nu) * (1 - 2 * self.nu))
        mu = self.E / (2 * (1 + self.nu))
        return lam, mu

    def voigt_matrix(self) -> np.ndarray:
        """6×6 isotropic elasticity matrix D (Pa) mapping engineering strain to stress."""
        lam, mu = self.lame()
        D = np.zeros((6, 6))
        D[:3, :3] = lam
        D[np.arange(3), np.arange(3)] += 2 * mu
        D[np.arange(3, 6), np.arange(3, 6)] = mu
        return D


def stiffness(nodes: np.ndarray, tets: np.ndarray, material: Material = Material()) -> sp.csr_matrix:
    """Global stiffness K (3M × 3M, CSR) of P1 tetrahedra (constant strain: one point is
    exact). Element blocks vol·(λ ∇φ_a ⊗ ∇φ_b + μ ∇φ_b ⊗ ∇φ_a + μ (∇φ_a·∇φ_b) I) in
    NumPy: the same matrix as scikit-fem's linear_elasticity (tests/test_basis.py).

    The 16 node-pair blocks of each element are summed per pair of nodes (one sort of the
    E·16 pairs, nine weighted counts) into a 3 × 3 block matrix, rather than the E·144
    entries sorted and summed by SciPy's COO → CSR: 0.65 against 2.0 CPU s at 22k nodes,
    the same pattern and values within rounding (docs/decisions/speed.md, session 38)."""
    Ke = _element_blocks(nodes, tets, material)  # (E, 4, 4, 3, 3): node a, node b, axis i, axis j
    if _coo_only:
        return _coo_assembly(Ke, tets, len(nodes))
    M = len(nodes)
    t = np.asarray(tets, np.int64)
    pairs, which = np.unique((t[:, :, None] * M + t[:, None, :]).ravel(), return_inverse=True)
    flat = Ke.reshape(-1, 9)
    blocks = np.empty((len(pairs), 9))
    for c in range(9):
        blocks[:, c] = np.bincount(which, flat[:, c], len(pairs))
    indptr = np.zeros(M + 1, np.int64)
    np.cumsum(np.bincount(pairs // M, minlength=M), out=indptr[1:])
    return sp.bsr_matrix((blocks.reshape(-1, 3, 3), pairs % M, indptr), shape=(3 * M, 3 * M)).tocsr()


def _element_blocks(nodes, tets, material):
    lam, mu = material.lame()
    g, vol = shape_gradients(nodes, tets)
    gv = g * vol[:, None, None]
    Ke = lam * np.einsum("eai,ebj->eabij", gv, g)
    Ke += mu * np.einsum("eaj,ebi->eabij", gv, g)
    gg = mu * np.einsum("eak,ebk->eab", gv, g)
    for i in range(3):
        Ke[:, :, :, i, i] += gg
    return Ke


def _coo_assembly(Ke, tets, M):
    """The assembly as before session 38: every entry to SciPy's COO → CSR."""
    dof = (3 * tets[:, :, None] + np.arange(3)).reshape(len(tets), 12)
    n = 3 * M
    rows = np.repeat(dof, 12, axis=1).ravel()
    cols = np.tile(dof, (1, 12)).ravel()
    return sp.csr_matrix((Ke.transpose(0, 1, 3, 2, 4).ravel(), (rows, cols)), shape=(n, n))


_coo_only = Before()


def coo_assembly() -> AbstractContextManager[None]:
    """Within it, ``stiffness`` assembles through SciPy's COO → CSR as before session 38:
    the benches' "before" (process-wide)."""
    return _coo_only.taken()


def shape_gradients(nodes, tets):
    """Gradients of the four P1 shape functions per tet, (E, 4, 3) in 1/mm, and volumes (E,)."""
    p = nodes[tets]  # (E, 4, 3)
    J = (p[:, 1:] - p[:, :1]).transpose(0, 2, 1)  # columns: edges from vertex 0
    Jinv = np.linalg.inv(J)  # rows: gradients of barycentric coords 1..3
    g = np.empty((len(tets), 4, 3))
    g[:, 1:] = Jinv
    g[:, 0] = -Jinv.sum(1)
    return g, np.abs(np.linalg.det(J)) / 6.0


VOIGT_TERMS = ((0, 0, 0), (1, 1, 1), (2, 2, 2), (3, 2, 1), (3, 1, 2), (4, 2, 0), (4, 0, 2), (5, 1, 0), (5, 0, 1))
"""(component, derivative axis, displacement axis) of each term of the engineering Voigt strain."""


def element_strain_operator(nodes, tets) -> sp.csr_matrix:
    """B (6E × 3M): engineering Voigt strain of each element from nodal displacements.

    Written straight into CSR (each element's six rows hold 4, 4, 4, 8, 8, 8 entries, in
    column order): the same matrix as through COO, bit for bit, in a fifth of the time."""
    g, _ = shape_gradients(nodes, tets)
    E = len(tets)
    t = np.asarray(tets, np.int64)
    order = np.argsort(t, axis=1, kind="stable")  # each row's nodes in column order
    ts = np.take_along_axis(t, order, 1)
    gs = np.take_along_axis(g, order[:, :, None], 1)  # (E, 4, 3)
    cols, vals = [], []
    for comp in range(6):
        terms = [(d, u) for c, d, u in VOIGT_TERMS if c == comp]
        terms.sort(key=lambda du: du[1])  # the two terms of a shear: lower displacement axis first
        cols.append(np.stack([3 * ts + u for _, u in terms], 2).reshape(E, -1))
        vals.append(np.stack([gs[:, :, d] for d, _ in terms], 2).reshape(E, -1))
    indptr = np.concatenate([[0], np.cumsum(np.tile([4, 4, 4, 8, 8, 8], E))])
    return sp.csr_matrix((np.concatenate(vals, 1).ravel(), np.concatenate(cols, 1).ravel(), indptr),
                         shape=(6 * E, 3 * len(nodes)))


def _element_strain_operator_coo(nodes, tets) -> sp.csr_matrix:
    """``element_strain_operator`` through COO, as before session 38 (its test's reference)."""
    g, _ = shape_gradients(nodes, tets)
    E = len(tets)
    rows, cols, vals = [], [], []
    for comp, dax, uax in VOIGT_TERMS:
        for a in range(4):
            rows.append(6 * np.arange(E) + comp)
            cols.append(3 * tets[:, a] + uax)
            vals.append(g[:, a, dax])
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(6 * E, 3 * len(nodes)))


def nodal_average_operator(nodes, tets) -> sp.csr_matrix:
    """A (6M × 6E): volume-weighted average of element values at each node (Voigt-blocked).

    This is the recovery used for nodal strain and stress: P1 strain is constant in each
    element, and a node takes the mean over the elements around it, weighted by volume.
    """
    _, vol = shape_gradients(nodes, tets)
    M, E = len(nodes), len(tets)
    W = sp.csr_matrix((np.repeat(vol, 4), (tets.ravel(), np.repeat(np.arange(E), 4))), shape=(M, E))
    W = sp.diags(1.0 / np.asarray(W.sum(1)).ravel()) @ W
    return sp.kron(W, sp.identity(6), format="csr")


def nodal_strain_operator(nodes, tets) -> sp.csr_matrix:
    """G (6M × 3M): nodal engineering strain (Voigt, dimensionless) from displacements (mm)."""
    return (nodal_average_operator(nodes, tets) @ element_strain_operator(nodes, tets)).tocsr()


def nodal_stress(strain: np.ndarray, material: Material = Material()) -> np.ndarray:
    """Stress (Pa) from engineering Voigt strain; ``strain`` shape (M, 6) or (M, 6, n)."""
    D = material.voigt_matrix()
    return np.einsum("ij,mj...->mi...", D, strain)


def strain_energy(K: sp.spmatrix, u: np.ndarray) -> float:
    """Total FE strain energy ½ uᵀKu (Pa·mm³ = 1e-9 J) of displacement u (3M,) mm."""
    return 0.5 * float(u @ (K @ u))

"""Point-load modes for a local dent: the Kelvin solution under a patch of surface.

The control-point basis (``basis``) is smooth at the scale of its tiles (k = 45 tiles on a
liver are 5–8 cm across): a 1–5 cm tool dent is not in its span, and a fit to data over
the dent bends the whole organ to share out the misfit. A point force at a depth under the
dent makes such a dent. Its displacement in an infinite linear-elastic body is Kelvin's
solution,

    u(x) = [(3 − 4ν) f / R + r (r · f) / R³] / (16 π μ (1 − ν)),   r = x − s,

here regularised over ``eps_mm`` (R = sqrt(|r|² + ε²), so it stays finite at the source)
and scaled, as the control-point modes are, to a fixed largest nodal displacement. The
infinite body ignores the organ's free surface and supports; what the modes are fitted to
(the data, with the strain-energy term of eq. 13 recomputed over them) decides how much of
them is used. Where they go and whether a fit keeps them is registration's choice
(``registration.local_modes``).
"""

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from .basis import Basis
from .fem import nodal_strain_operator

EPS_MM = 5.0  # regularisation radius of the point force (a tool tip is 1–5 cm across)
MODE_MM = 5.0  # each mode's largest nodal displacement, as the control-point modes' perturbation


def kelvin_modes(nodes: np.ndarray, source: np.ndarray, nu: float, eps_mm: float = EPS_MM,
                 scale_mm: float = MODE_MM) -> np.ndarray:
    """The regularised Kelvin displacement of a unit force along x, y and z at ``source``.

    Parameters
    ----------
    nodes : (M, 3) float, mm
        where the displacement is evaluated (the mesh nodes).
    source : (3,) float, mm
        the point force's position (inside the organ, under the surface it dents).
    nu : float
        Poisson's ratio.
    eps_mm, scale_mm : float
        the regularisation radius, and each mode's largest nodal displacement (mm).

    Returns
    -------
    (3M, 3) float
        mm per unit weight; rows x, y, z per node as ``Basis.Ju``; one column per force direction.
    """
    r = np.asarray(nodes, float) - np.asarray(source, float)
    R = np.sqrt((r ** 2).sum(1) + eps_mm ** 2)
    cols = []
    for j in range(3):
        u = (3 - 4 * nu) * np.eye(3)[j][None, :] / R[:, None] + r * r[:, j:j + 1] / R[:, None] ** 3
        cols.append((u * scale_mm / np.linalg.norm(u, axis=1).max()).reshape(-1))
    return np.stack(cols, 1)


def with_modes(basis: Basis, cols: np.ndarray, control: np.ndarray, G: sp.spmatrix | None = None) -> Basis:
    """``basis`` with the modes ``cols`` appended to J_u and the strain-energy matrix of
    eq. 13 extended to them exactly (the old block is kept; only the new rows are formed).

    Parameters
    ----------
    basis : Basis
    cols : (3M, m) float
        the new modes, mm per unit weight (e.g. ``kelvin_modes`` of m / 3 sources).
    control : (m / 3,) int
        the surface node each source lies under (appended to ``basis.control``).
    G : (6M, 3M) sparse, optional
        the basis mesh's ``nodal_strain_operator`` (about a second at 27k nodes), when the
        caller extends the same basis several times.

    Returns
    -------
    Basis
        J_u (3M, 3k + m), energy (3k + m, 3k + m) Pa; the nodes, mesh and material are shared.
    """
    G = nodal_strain_operator(basis.nodes, basis.tets) if G is None else G
    D = basis.material.voigt_matrix()
    M, m = basis.M, cols.shape[1]
    eps = np.asarray(G @ cols).reshape(M, 6, m)
    stress = np.einsum("ij,mjq->miq", D, eps).reshape(6 * M, m)
    GtS = np.asarray(sp.csr_matrix(G).T @ stress)  # (3M, m): Gᵀ D G · cols, the energy's bilinear form on them
    cross = basis.Ju.T @ GtS
    new = cols.T @ GtS
    energy = np.block([[basis.energy, cross], [cross.T, 0.5 * (new + new.T)]])
    return replace(basis, Ju=np.hstack([basis.Ju, cols]), energy=energy,
                   control=np.concatenate([basis.control, np.asarray(control, int)]))

"""Ground-truth solvers against analytic results and each other (the neo-Hookean one: test_hyperelastic.py)."""

import numpy as np
from skfem import MeshTet

from navapp.anatomy.meshing import TetMesh
from navapp.mechanics.fem import Material
from navapp.simulation.truth import Loading, _body_force, supported_nodes


def column(h=100.0, n=(4, 4, 26)):
    m = MeshTet.init_tensor(np.linspace(0, 10, n[0]), np.linspace(0, 10, n[1]), np.linspace(0, h, n[2]))
    return TetMesh(m.p.T.copy(), m.t.T.copy())


def hang(mesh, mat):
    """Column held at its top face (z = h) in z only, lateral motion suppressed everywhere:
    with ν = 0 the exact solution is the 1D one, u_z = −(ρ g / 2E)(h² − z²)."""
    from navapp.mechanics.fem import stiffness
    from navapp.mechanics.sparse import Factorisation

    f = _body_force(mesh, Loading(gravity_dir=(0.0, 0.0, -1.0)))
    K = stiffness(mesh.nodes, mesh.tets, mat)
    h = mesh.nodes[:, 2].max()
    top = np.flatnonzero(np.isclose(mesh.nodes[:, 2], h))
    allnodes = np.arange(len(mesh.nodes))
    fixed = np.concatenate([3 * top + 2, 3 * allnodes, 3 * allnodes + 1])
    free = np.setdiff1d(np.arange(3 * len(mesh.nodes)), fixed)
    u = np.zeros(3 * len(mesh.nodes))
    with Factorisation(K[free][:, free]) as F:
        u[free] = F.solve(f[free])
    rho_g = 1060 * 9.81 * 1e-9 * 1e6  # body force in K's units (Pa·mm² per mm³)
    exact = -(rho_g / (2 * mat.E)) * (h ** 2 - mesh.nodes[:, 2] ** 2)
    return u.reshape(-1, 3)[:, 2], exact


def test_column_under_its_own_weight():
    uz, exact = hang(column(), Material(E=5000.0, nu=0.0))
    # P1 is exact at the nodes for this 1D problem up to the lumping of the body force
    assert np.allclose(uz, exact, atol=2e-3 * np.abs(exact).max())


def test_linear_truth_converges_under_refinement():
    """Tip displacement of the hanging column approaches the analytic value under refinement."""
    errs = []
    for n in (6, 12):
        mesh = column(n=(3, 3, n))
        uz, exact = hang(mesh, Material(E=5000.0, nu=0.0))
        tip = np.argmin(mesh.nodes[:, 2])
        errs.append(abs(uz[tip] - exact[tip]))
    assert errs[1] < errs[0]


def test_supports_and_release(coarse_mesh):
    n = supported_nodes(coarse_mesh, "N")
    assert all(len(v) > 0 for v in n.values())
    assert "left_triangular" not in supported_nodes(coarse_mesh, "L")
    assert "right_triangular" not in supported_nodes(coarse_mesh, "R")

"""How firmly a declared support holds (issue 47, item 1): springs of a stiffness k_s (Pa/mm) at
the support's nodes instead of zero displacement, checked against a direct finite-element solve
assembled by scikit-fem, and tending to held as k_s grows and to free as it vanishes."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from navapp.mechanics.basis import BasisSettings, basis_key, compute_basis
from navapp.mechanics.fem import Material
from navapp.mechanics.supports import held_nodes, point_nodes

SUPPORT = "bare_area"


def _reference_stiffness(mesh, support, k_s):
    """K + springs assembled by scikit-fem alone: linear elasticity, and the spring term
    ∫ k_s u·v dA over the boundary, lumped by rows (a P1 triangle's consistent mass sums to a
    third of its area per node) and kept at the support's nodes."""
    from skfem import Basis, BilinearForm, ElementTetP1, ElementVector, FacetBasis, MeshTet, asm
    from skfem.helpers import dot
    from skfem.models.elasticity import linear_elasticity

    m = MeshTet(mesh.nodes.T.astype(float), mesh.tets.T)
    e = ElementVector(ElementTetP1())
    K = asm(linear_elasticity(*Material().lame()), Basis(m, e, intorder=1))

    @BilinearForm
    def spring(u, v, w):
        return k_s * dot(u, v)

    S = asm(spring, FacetBasis(m, e, facets=m.boundary_facets(), intorder=2))
    lumped = np.asarray(S.sum(axis=1)).ravel()
    keep = np.zeros(3 * len(mesh.nodes), bool)
    keep[(3 * support[:, None] + np.arange(3)).ravel()] = True
    return (K + sp.diags(np.where(keep, lumped, 0.0))).tocsr()


def _direct_point_load_modes(K, control, perturbation=5.0):
    """Mode 3c+d: u = perturbation·e_d at control c, 0 at the other control points, the rest free."""
    n = K.shape[0]
    cd = (3 * control[:, None] + np.arange(3)).ravel()
    free = np.setdiff1d(np.arange(n), cd)
    U = np.zeros((n, len(cd)))
    U[cd, np.arange(len(cd))] = perturbation
    U[free] = spla.spsolve(K[free][:, free].tocsc(), -(K[free][:, cd] @ U[cd]))
    return U


def test_a_spring_support_matches_a_direct_fe_solve(coarse_mesh):
    """The point-load modes on springs are the direct solve of scikit-fem's K + springs."""
    support = held_nodes(coarse_mesh, SUPPORT)
    basis = compute_basis(coarse_mesh, BasisSettings(k=12, supports=SUPPORT, stiffness=20.0, relax=False))
    ref = _direct_point_load_modes(_reference_stiffness(coarse_mesh, support, 20.0), basis.control)
    assert np.abs(basis.Ju - ref).max() < 1e-8 * np.abs(ref).max()
    U = basis.Ju.reshape(basis.M, 3, -1)
    assert np.abs(U[support]).max() > 0.05  # the springs give: the support moves


def test_a_stiff_spring_tends_to_held_and_a_weak_one_to_free(coarse_mesh):
    """The relaxed basis: the support's displacement falls as k_s rises, and at 10⁸ Pa/mm the
    basis is the held one; at k_s → 0 it is the basis with no springs at all (the same control
    points, the support free)."""
    support = held_nodes(coarse_mesh, SUPPORT)
    held = compute_basis(coarse_mesh, BasisSettings(k=12, supports=SUPPORT)).Ju
    at = {}
    for k_s in (0.0, 1e-6, 1.0, 100.0, 1e8):
        Ju = compute_basis(coarse_mesh, BasisSettings(k=12, supports=SUPPORT, stiffness=k_s)).Ju
        at[k_s] = Ju
    move = [np.abs(at[k].reshape(-1, 3, at[k].shape[1])[support]).max() for k in (1e-6, 1.0, 100.0, 1e8)]
    assert all(a > b for a, b in zip(move, move[1:], strict=False)), move
    assert move[0] > 0.5  # no spring: the support moves as freely as its surroundings
    assert np.abs(at[1e8] - held).max() < 1e-4 * np.abs(held).max()
    assert np.abs(at[1e-6] - at[0.0]).max() < 1e-6 * np.abs(at[0.0]).max()
    assert np.abs(at[1.0] - held).max() > 0.1  # a soft spring is not held


def test_surface_forces_on_springs_solve_k_plus_springs(coarse_mesh):
    """The surface-forces model on a spring support: (K + springs) u = f, the support moving."""
    from navapp.registration.forces import SurfaceForces

    support = held_nodes(coarse_mesh, SUPPORT)
    basis = compute_basis(coarse_mesh, BasisSettings(k=6, supports=SUPPORT, stiffness=20.0))
    sf = SurfaceForces(basis)
    try:
        assert np.isin(support, sf.surface).all()  # a force may act on a spring node
        f = np.random.default_rng(0).normal(size=(len(sf.surface), 3))
        u = sf.displacement(f)
        K = _reference_stiffness(coarse_mesh, support, 20.0)
        load = np.zeros((basis.M, 3))
        load[sf.surface] = f
        assert np.abs(K @ u.ravel() - load.ravel()).max() < 1e-8 * np.abs(f).max()
        assert np.abs(u[support]).max() > 1e-3
    finally:
        sf.close()


def test_support_points_hold_the_surface_around_them(coarse_mesh):
    """``supports = "points"``: every mode vanishes at the nodes within 5 mm of each point (and
    its nearest), exactly; the points are part of the cache key; the held key unchanged."""
    surface = np.unique(coarse_mesh.boundary_faces())
    pts = coarse_mesh.nodes[surface[[0, 40, 80]]] + 0.5
    nodes = point_nodes(coarse_mesh, pts)
    assert len(nodes) >= 3 and np.isin(nodes, surface).all()
    basis = compute_basis(coarse_mesh, BasisSettings(k=12, supports="points", points=tuple(map(tuple, pts))))
    U = basis.Ju.reshape(basis.M, 3, -1)
    assert np.abs(U[nodes]).max() == 0.0
    assert not np.isin(basis.control, nodes).any()
    one = basis_key(coarse_mesh, BasisSettings(k=12, supports="points", points=((1.0, 2.0, 3.0),)), Material())
    two = basis_key(coarse_mesh, BasisSettings(k=12, supports="points", points=((1.0, 2.0, 3.5),)), Material())
    assert one != two
    held = BasisSettings(k=12, supports=SUPPORT)
    assert basis_key(coarse_mesh, held, Material()) != basis_key(
        coarse_mesh, BasisSettings(k=12, supports=SUPPORT, stiffness=50.0), Material())


@pytest.mark.parametrize("stiffness", [0, -3.0, float("nan"), "stiff", True])
def test_a_bad_stiffness_is_one_line(stiffness):
    from navapp.errors import InputError
    from navapp.mechanics.supports import HeldSupports

    with pytest.raises(InputError, match="stiffness must be a positive number of Pa/mm"):
        HeldSupports.parse("posterior", "N", "case.toml", stiffness)


def test_a_stated_support_keeps_its_stiffness_and_points():
    """The viewer's record of a support (session.json) and its words carry how firmly and where."""
    from navapp.app.state import StatedSupports
    from navapp.mechanics.supports import HeldSupports

    held = HeldSupports.parse("points", "N", stiffness=40, points=[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    stated = StatedSupports(held)
    assert StatedSupports.from_json(stated.to_json()) == stated
    assert stated.words() == "held at 2 points on its surface, on springs of 40 Pa/mm"
    assert StatedSupports.from_json({"held": "posterior", "release": "N"}).held == HeldSupports.parse("posterior")
    with pytest.raises(ValueError, match="stiffness must be a positive number"):
        StatedSupports.from_json({"held": "posterior", "release": "N", "stiffness_pa_per_mm": -1})

"""The compressible neo-Hookean truth (simulation/truth.py) against finite differences,
the analytic homogeneous solutions, linear elasticity at small load and rigid motions."""

import numpy as np
import pytest
from scipy.optimize import brentq, fsolve
from scipy.spatial.transform import Rotation
from skfem import MeshTet

from navapp.anatomy.meshing import TetMesh
from navapp.errors import NavappError
from navapp.mechanics.fem import Material
from navapp.simulation.truth import (
    Loading,
    NeoHookean,
    solve_hyperelastic,
    solve_linear,
    solve_neo_hookean,
)

MAT = Material(E=3000.0, nu=0.45)


def cube(n=4, side=10.0):
    """A unit-ish cube of P1 tets from scikit-fem's tensor mesher (not navapp's)."""
    x = np.linspace(0, side, n)
    m = MeshTet.init_tensor(x, x, x)
    return TetMesh(m.p.T.copy(), m.t.T.copy())


def smooth_field(nodes, amplitude):
    """A smooth, finite (not infinitesimal) displacement field with stretch, shear and twist."""
    x = nodes / np.ptp(nodes, axis=0).max()
    return amplitude * np.column_stack([0.3 * x[:, 0] ** 2 + 0.2 * x[:, 1], np.sin(2 * x[:, 2]) * 0.25 - 0.1 * x[:, 1],
                                        0.2 * x[:, 0] * x[:, 1] - 0.15 * x[:, 2]])


def test_tangent_matches_finite_differences_of_forces():
    mesh = cube()
    rng = np.random.default_rng(0)
    u = smooth_field(mesh.nodes, 4.0) + rng.normal(size=mesh.nodes.shape) * 0.2
    f0, K = NeoHookean(mesh.nodes, mesh.tets, MAT).forces(u)
    for _ in range(3):
        du = rng.normal(size=u.shape) * 1e-5
        fp, _ = NeoHookean(mesh.nodes, mesh.tets, MAT).forces(u + du, tangent=False)
        fm, _ = NeoHookean(mesh.nodes, mesh.tets, MAT).forces(u - du, tangent=False)
        np.testing.assert_allclose(K @ du.ravel(), (fp - fm) / 2, rtol=1e-6, atol=1e-7 * np.abs(K @ du.ravel()).max())
    # and the tangent is symmetric (it is the Hessian of an energy)
    assert abs(K - K.T).max() < 1e-10 * abs(K).max()


def test_forces_are_the_gradient_of_the_energy():
    mesh = cube(3)
    u = smooth_field(mesh.nodes, 3.0)
    f, _ = NeoHookean(mesh.nodes, mesh.tets, MAT).forces(u, tangent=False)
    h = 1e-5
    fd = np.empty(u.size)
    for k in range(u.size):
        e = np.zeros(u.size)
        e[k] = h
        fd[k] = (NeoHookean(mesh.nodes, mesh.tets, MAT).energy(u + e.reshape(u.shape))
                 - NeoHookean(mesh.nodes, mesh.tets, MAT).energy(u - e.reshape(u.shape))) / (2 * h)
    np.testing.assert_allclose(f, fd, rtol=1e-5, atol=1e-6 * np.abs(f).max())


def _face_forces(mesh, axis, value, traction):
    """Consistent nodal forces (3M,) of a uniform dead-load traction (Pa, reference area)
    along ``axis`` on the cube face x_axis = value: a third of each triangle's area per vertex."""
    faces = mesh.boundary_faces()
    on = np.all(np.isclose(mesh.nodes[faces][:, :, axis], value), axis=1)
    tri = mesh.nodes[faces[on]]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2
    f = np.zeros((len(mesh.nodes), 3))
    for a in range(3):
        np.add.at(f[:, axis], faces[on, a], traction * area / 3)
    return f.ravel()


def _symmetry_free(mesh):
    """Rollers on the three faces through the origin: each holds its normal DOF."""
    held = [3 * np.flatnonzero(np.isclose(mesh.nodes[:, i], 0.0)) + i for i in range(3)]
    return np.setdiff1d(np.arange(mesh.nodes.size), np.concatenate(held))


@pytest.mark.parametrize("traction", [1500.0, -900.0])
def test_uniaxial_dead_load_matches_the_analytic_stretch(traction):
    """Cube on rollers, uniform nominal traction t on the x = L face, lateral faces free:
    F = diag(a, b, b) with P₁₁ = μ(a − 1/a) + λ ln(ab²)/a = t and P₂₂ = μ(b − 1/b) + λ ln(ab²)/b = 0."""
    mesh = cube()
    side = mesh.nodes[:, 0].max()
    lam, mu = MAT.lame()

    def eqs(s):
        a, b = s
        lnJ = np.log(a * b * b)
        return [mu * (a - 1 / a) + lam * lnJ / a - traction, mu * (b - 1 / b) + lam * lnJ / b]

    a, b = fsolve(eqs, [1.0, 1.0], xtol=1e-12)
    assert abs(a - 1) > 0.2  # a large deformation: linear elasticity would be far off
    u = solve_hyperelastic(mesh.nodes, mesh.tets, _face_forces(mesh, 0, side, traction), _symmetry_free(mesh), MAT)
    np.testing.assert_allclose(u, mesh.nodes * [a - 1, b - 1, b - 1], atol=1e-6 * side)


def test_hydrostatic_dead_load_matches_the_analytic_stretch():
    """Equal traction t on the three outer faces: F = a I with μ(a − 1/a) + 3λ ln a / a = t."""
    mesh = cube()
    side = mesh.nodes[:, 0].max()
    mat = Material(E=3000.0, nu=0.3)  # more compressible, so that the volume change is large
    lam, mu = mat.lame()
    # tension below ≈ 2μ: the homogeneous state of a cube under equal dead loads loses
    # stability (Rivlin's cube; the tangent stops being positive definite) in compression
    # near |t| ≈ μ and in tension near 2μ, and the solver rightly does not find a saddle
    t = 1500.0
    a = brentq(lambda a: mu * (a - 1 / a) + 3 * lam * np.log(a) / a - t, 1.0, 3.0, xtol=1e-15)
    assert a > 1.1
    f = sum(_face_forces(mesh, i, side, t) for i in range(3))
    u = solve_hyperelastic(mesh.nodes, mesh.tets, f, _symmetry_free(mesh), mat)
    np.testing.assert_allclose(u, mesh.nodes * (a - 1), atol=1e-6 * side)


def test_small_loads_agree_with_linear_elasticity(coarse_mesh):
    """The two models differ at second order in the load: the relative difference of the
    displacement is proportional to the load (tenfold load, about tenfold difference)."""
    rel = []
    for g in (0.02, 0.2):
        load = Loading(gravity=g)
        lin = solve_linear(coarse_mesh, load, MAT)
        nh = solve_neo_hookean(coarse_mesh, load, MAT, steps=1)
        rel.append(np.abs(nh - lin).max() / np.abs(lin).max())
    assert rel[0] < 1e-3
    assert 5 < rel[1] / rel[0] < 20


def test_newton_converges_quadratically(coarse_mesh):
    res = []
    solve_neo_hookean(coarse_mesh, Loading(gravity=2.0), MAT, steps=1, report=lambda t, i, r: res.append(r))
    assert res[-1] < 1e-8 and len(res) <= 6
    # once in the basin, each residual is at most about the square of the previous one
    tail = [r for r in res if r < 1e-2]
    assert all(b < 10 * a ** 2 for a, b in zip(tail, tail[1:], strict=False))


def test_progress_follows_the_converged_load(coarse_mesh):
    """The simulator's bar moves with each converged increment, up to the whole load."""
    seen = []
    solve_neo_hookean(coarse_mesh, Loading(gravity=4.0), MAT, steps=4, reached=seen.append)
    assert seen[-1] == pytest.approx(1.0) and len(seen) >= 2
    assert all(b > a for a, b in zip(seen, seen[1:], strict=False))


def test_rigid_motion_gives_no_internal_force_and_forces_are_objective():
    mesh = cube()
    R = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()  # a 75° rotation: far from infinitesimal
    x0 = mesh.nodes
    rigid = x0 @ R.T + [5.0, -2.0, 1.0] - x0
    f, _ = NeoHookean(x0, mesh.tets, MAT).forces(rigid, tangent=False)
    assert np.abs(f).max() < 1e-9 * MAT.E * 10.0 ** 2
    assert abs(NeoHookean(x0, mesh.tets, MAT).energy(rigid)) < 1e-9 * MAT.E * 10.0 ** 3
    # rotating a deformed state rotates its nodal forces
    u = smooth_field(x0, 3.0)
    fu, _ = NeoHookean(x0, mesh.tets, MAT).forces(u, tangent=False)
    fr, _ = NeoHookean(x0, mesh.tets, MAT).forces((x0 + u) @ R.T - x0, tangent=False)
    np.testing.assert_allclose(fr.reshape(-1, 3), fu.reshape(-1, 3) @ R.T, atol=1e-9 * np.abs(fu).max())


def test_inverted_element_has_infinite_energy_and_no_forces():
    mesh = cube(2)
    u = np.zeros_like(mesh.nodes)
    u[:, 0] = -2.5 * mesh.nodes[:, 0]  # x ↦ −1.5 x: every tet inverted
    nh = NeoHookean(mesh.nodes, mesh.tets, MAT)
    assert nh.energy(u) == np.inf
    with pytest.raises(ValueError, match="inverted"):
        nh.forces(u)


def test_no_convergence_is_one_clear_line(coarse_mesh):
    with pytest.raises(NavappError, match="did not converge") as e:
        solve_neo_hookean(coarse_mesh, Loading(gravity=9.81, pressure=600.0), MAT, steps=1, max_newton=2,
                          min_increment=0.4)
    assert "\n" not in str(e.value)


def test_indefinite_tangent_gives_a_shifted_descent_step():
    """Away from a stable equilibrium the tangent can be indefinite; the step taken is then
    that of a shifted tangent, and it descends the energy (r · step > 0)."""
    import scipy.sparse as sp

    from navapp.simulation.truth import _descent_step

    K = sp.csr_matrix(np.diag([4.0, -1.0, 2.0, 3.0]))
    r = np.array([1.0, 1.0, -1.0, 0.5])
    du, slope, tau = _descent_step(K, r)
    assert du is not None and slope > 0 and tau > 0
    np.testing.assert_allclose(slope, r @ du)
    # a positive definite tangent gives the plain Newton step
    du, _, tau = _descent_step(sp.csr_matrix(np.diag([4.0, 1.0, 2.0, 3.0])), r)
    assert tau == 0 and np.allclose(du, r / [4.0, 1.0, 2.0, 3.0])

"""FE checks against exact solutions: P1 reproduces linear fields exactly."""

import numpy as np
import pytest
from skfem import MeshTet

from navapp.mechanics.fem import Material, nodal_strain_operator, nodal_stress, stiffness, strain_energy
from navapp.mechanics.sparse import Factorisation


@pytest.fixture(scope="module")
def box():
    m = MeshTet.init_tensor(np.linspace(0, 40, 6), np.linspace(0, 10, 4), np.linspace(0, 10, 4))
    return m.p.T.copy(), m.t.T.copy()


def _solve_dirichlet(K, fixed_dofs, values):
    n = K.shape[0]
    free = np.setdiff1d(np.arange(n), fixed_dofs)
    u = np.zeros(n)
    u[fixed_dofs] = values
    with Factorisation(K[free][:, free]) as F:
        u[free] = F.solve(-(K[free][:, fixed_dofs] @ values))
    return u


def test_patch_test_linear_field_is_exact(box):
    nodes, tets = box
    K = stiffness(nodes, tets)
    A = np.array([[0.01, 0.002, -0.003], [0.004, -0.005, 0.001], [0.0, 0.003, 0.008]])
    exact = nodes @ A.T
    bnd = np.flatnonzero((np.isclose(nodes, nodes.min(0)) | np.isclose(nodes, nodes.max(0))).any(1))
    dofs = (3 * bnd[:, None] + np.arange(3)).ravel()
    u = _solve_dirichlet(K, dofs, exact[bnd].ravel())
    assert np.allclose(u.reshape(-1, 3), exact, atol=1e-10)
    eps = (nodal_strain_operator(nodes, tets) @ u).reshape(-1, 6)
    E = 0.5 * (A + A.T)
    voigt = np.array([E[0, 0], E[1, 1], E[2, 2], 2 * E[1, 2], 2 * E[0, 2], 2 * E[0, 1]])
    assert np.allclose(eps, voigt, atol=1e-12)


def test_bar_in_uniaxial_tension(box):
    """Ends pulled apart with lateral contraction free: u_x = εx, u_y = −νε y, u_z = −νε z,
    stress σ_xx = Eε and all other components zero."""
    nodes, tets = box
    mat = Material(E=5000.0, nu=0.3)
    K = stiffness(nodes, tets, mat)
    eps = 0.01
    L = nodes[:, 0].max()
    left = np.flatnonzero(nodes[:, 0] == 0)
    right = np.flatnonzero(np.isclose(nodes[:, 0], L))
    origin = np.flatnonzero((nodes == 0).all(1))
    fixed = [3 * left, 3 * right, 3 * origin + 1, 3 * origin + 2]
    # stop rigid rotations: a node on the y axis at x = 0 has no z motion, one on z has no y
    ynode = np.flatnonzero((nodes[:, 0] == 0) & (nodes[:, 2] == 0) & (nodes[:, 1] > 0))[:1]
    fixed.append(3 * ynode + 2)
    dofs = np.concatenate(fixed)
    vals = np.zeros(len(dofs))
    vals[len(left):len(left) + len(right)] = eps * L
    u = _solve_dirichlet(K, dofs, vals).reshape(-1, 3)
    assert np.allclose(u[:, 0], eps * nodes[:, 0], atol=1e-9)
    assert np.allclose(u[:, 1], -mat.nu * eps * nodes[:, 1], atol=1e-9)
    assert np.allclose(u[:, 2], -mat.nu * eps * nodes[:, 2], atol=1e-9)
    sig = nodal_stress((nodal_strain_operator(nodes, tets) @ u.ravel()).reshape(-1, 6), mat)
    assert np.allclose(sig[:, 0], mat.E * eps, rtol=1e-8)
    assert np.allclose(sig[:, 1:], 0, atol=1e-6 * mat.E * eps)


def test_rigid_motions_have_no_strain_or_energy(box):
    nodes, tets = box
    K = stiffness(nodes, tets)
    G = nodal_strain_operator(nodes, tets)
    W = np.array([[0, -1, 2], [1, 0, -3], [-2, 3, 0]]) * 1e-3  # infinitesimal rotation
    for u in (np.tile([1.0, -2.0, 0.5], len(nodes)), (nodes @ W.T).ravel()):
        assert np.abs(G @ u).max() < 1e-14
        assert abs(strain_energy(K, u)) < 1e-9 * np.abs(K).max()


def test_energy_proportional_to_E(box):
    nodes, tets = box
    u = np.random.default_rng(0).normal(size=3 * len(nodes))
    e1 = strain_energy(stiffness(nodes, tets, Material(E=1000.0)), u)
    e2 = strain_energy(stiffness(nodes, tets, Material(E=3000.0)), u)
    assert np.isclose(e2, 3 * e1, rtol=1e-12)


def test_a_refused_factorisation_gives_its_memory_back():
    """The neo-Hookean truth retries a tangent that is not positive definite with shifts, and
    each refusal left PARDISO's work memory behind (about 43 MB a time on this 64k-DOF
    matrix, over 24 GB in one tool simulation, which the kernel then killed)."""
    import os

    import scipy.sparse as sp

    from navapp.mechanics.sparse import Factorisation, backend

    if backend() != "pardiso" or not os.path.exists("/proc/self/statm"):
        pytest.skip("PARDISO's memory is what is measured; this runs on SuperLU, or without /proc")

    def rss_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    m = 40
    eye, d = sp.identity(m), sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(m, m))
    lap = sp.kron(sp.kron(d, eye), eye) + sp.kron(sp.kron(eye, d), eye) + sp.kron(sp.kron(eye, eye), d)
    indefinite = (lap - sp.identity(m ** 3)).tocsr()
    refused = 0
    for i in range(11):
        if i == 1:
            before = rss_mb()  # after the first: MKL's own one-off allocations
        try:
            Factorisation(indefinite)
        except Exception:  # noqa: BLE001 - the refusal itself is what is exercised
            refused += 1
    assert refused == 11
    assert rss_mb() - before < 100.0


def test_pardiso_found_in_a_venv_that_borrows_the_system_site_packages(tmp_path):
    """pypardiso looks for libmkl_rt only under ``sys.prefix``; in a virtual environment that
    borrows packages from outside its prefix (``--system-site-packages``, as a developer's is,
    or ``pip install --user``) the MKL wheel's library lies elsewhere, pypardiso failed to
    import, and every factorisation fell back to SuperLU without a word. navapp names the
    library from the wheel's file list. The venv here borrows this interpreter's
    site-packages through a .pth file, so it needs nothing installed outside (CI's own venv)."""
    import os
    import subprocess
    import sys
    import sysconfig
    import venv
    from importlib import metadata
    from pathlib import Path

    try:
        metadata.distribution("pypardiso")
        metadata.distribution("mkl")
    except metadata.PackageNotFoundError:
        pytest.skip("pypardiso and the mkl wheel are not both installed here")
    home = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(home)
    borrowed = [p for p in sys.path if p.endswith(("site-packages", "dist-packages")) and os.path.isdir(p)]
    purelib = Path(sysconfig.get_path("purelib", vars={"base": str(home), "platbase": str(home)}))
    (purelib / "borrowed.pth").write_text("\n".join(borrowed) + "\n")
    python = home / ("Scripts" if os.name == "nt" else "bin") / "python"
    root = str(Path(__file__).resolve().parents[1])
    env = {k: v for k, v in os.environ.items() if k not in ("PYPARDISO_MKL_RT", "NAVAPP_SOLVER", "PYTHONHOME")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
    code = "import sys; from navapp.mechanics.sparse import backend; print(sys.prefix != sys.base_prefix, backend())"
    out = subprocess.run([str(python), "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == ["True", "pardiso"], (out.stdout, out.stderr, sys.prefix)


def test_stiffness_summed_by_node_pair_blocks_is_the_coo_assembly(box):
    """The block assembly (session 38) stores the same entries as SciPy's COO → CSR (the old
    path, kept for the bench's "before") and sums them to the same values within rounding."""
    from navapp.mechanics.fem import coo_assembly

    nodes, tets = box
    K = stiffness(nodes, tets)
    with coo_assembly():
        ref = stiffness(nodes, tets)
    assert K.has_canonical_format and ref.has_canonical_format
    assert np.array_equal(K.indptr, ref.indptr) and np.array_equal(K.indices, ref.indices)
    assert abs(K - ref).max() <= 4e-16 * abs(ref).max()
    assert abs(K - K.T).max() <= 1e-15 * abs(K).max()


def test_element_strain_operator_written_as_csr_is_the_same_bits(box):
    from navapp.mechanics.fem import _element_strain_operator_coo, element_strain_operator

    nodes, tets = box
    rng = np.random.default_rng(3)
    tets = tets[rng.permutation(len(tets))][:, [2, 0, 3, 1]]  # node order not sorted within a tet
    B, ref = element_strain_operator(nodes, tets), _element_strain_operator_coo(nodes, tets)
    for part in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(B, part), getattr(ref, part)), part


def test_upper_triangle_is_scipys_triu():
    import scipy.sparse as sp

    from navapp.mechanics.sparse import upper_triangle

    rng = np.random.default_rng(0)
    A = sp.random(60, 60, 0.1, format="csr", random_state=rng)
    A = (A + A.T + sp.identity(60)).tocsr()
    A.indices[A.indptr[5]:A.indptr[6]] = A.indices[A.indptr[5]:A.indptr[6]][::-1].copy()  # one row unsorted
    A.data[A.indptr[5]:A.indptr[6]] = A.data[A.indptr[5]:A.indptr[6]][::-1].copy()
    A.has_sorted_indices = False
    U, ref = upper_triangle(A), sp.triu(A, format="csr")
    ref.sort_indices()
    for part in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(U, part), getattr(ref, part)), part

"""A force at every surface node: a deformation the organ's own elasticity makes from its supports.

LIBR's control-point modes are smooth and few (3k): a 4 cm dent under a tool is not among
their combinations. Where a case declares its supports (``prepare(supports=)``), the organ's
displacement under any surface load is u = K_ff⁻¹ P f — K the registration mesh's linear-elastic
stiffness with the held nodes removed, f (S, 3) a force at each of the S surface nodes, P
their scatter into the free DOFs — and that family holds every dent a tool can press. Its
size is fixed by the strain energy it stores, E(f) = ½ fᵀ Pᵀ u (the work of f), per unit
volume V. For surface points p_i matched to the deformed surface at fixed correspondences
(point-to-plane: the undeformed point y_i, its barycentric row a_i, the normal n_i),

    Φ(f) = (1/N) Σ_i (n_iᵀ(p_i − y_i) − n_iᵀ a_i u)²  +  λ E(f) / V,

quadratic in f. Its gradient by the adjoint: with g_u = −(2/N) Σ_i a_iᵀ r_i n_i,
∂Φ/∂f = Pᵀ K_ff⁻¹ g_u + (λ / V) Pᵀ u — two solves with one factorisation per evaluation,
whatever S is (``objective``; a finite-difference test). Its minimiser is found exactly in
the data's own space (``SurfaceForces.fit``: one normal force per data point, an N × N system
with the supported body's Green's matrix; the adjoint gradient vanishes there, a test); an
L-BFGS on the adjoint gradient took 1,400 solves for the same answer on tool0-b (docs/decisions.md).
The correspondences are then recomputed on the deformed surface (``ForceOptions.rounds``).

λ (mm² per Pa of mean strain-energy density) is chosen by held-out data, the criterion the
deformable-or-rigid decision already uses (``support``): the data cut into spatial blocks,
each predicted by the fit to the others at the full fit's correspondences (a sub-block of the
same Green's matrix: no further solve), the λ of least held-out RMS taken
(``choose_energy_weight``). The data are in the model frame (the rigid stage's pose applied).
"""

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..anatomy.tets import TetMesh, tet_volumes
from ..features import LIVER_SURFACE
from ..geometry.closest import closest_on_surface, incidence
from ..mechanics.basis import Basis
from ..mechanics.fem import stiffness
from ..mechanics.sparse import Factorisation
from ..mechanics.supports import held_nodes
from .support import blocks_of

ENERGY_WEIGHTS = (1e-3, 1e-2, 1e-1, 1.0, 10.0)
"""The λ (mm²/Pa) ``choose_energy_weight`` compares by held-out RMS, a decade apart."""


@dataclass(frozen=True)
class ForceOptions:
    """``energy_weight`` λ (mm²/Pa); ``rounds`` correspondence updates."""

    energy_weight: float = 0.1
    rounds: int = 3


@dataclass
class ForceFit:
    """u (M, 3) mm at the mesh nodes; f (S, 3) the surface forces (Pa·mm²); ``rms_mm`` the
    point-to-plane residual RMS at the end; ``solves`` factorised solves used."""

    u: np.ndarray
    f: np.ndarray
    rms_mm: float
    energy_density_pa: float
    solves: int
    seconds: float


class SurfaceForces:
    """The supported organ's response to surface forces: one factorisation of K_ff.

    ``basis``: a basis computed with ``BasisSettings.supports`` (its mesh, material and the
    held nodes); raises ValueError for a free-floating basis (K would be singular)."""

    def __init__(self, basis: Basis):
        if basis.settings.supports is None:
            raise ValueError("surface forces need declared supports: a free-floating organ has no unique "
                             "displacement under a load (prepare(..., supports=...))")
        mesh = TetMesh(basis.nodes, basis.tets)
        self.nodes, self.faces = basis.nodes, basis.surface_faces
        self.M = len(basis.nodes)
        held = held_nodes(mesh, basis.settings.supports, basis.settings.release)
        fixed = np.zeros(self.M, bool)
        fixed[held] = True
        self.surface = np.setdiff1d(basis.surface, held)  # the nodes a force may act on
        free_nodes = np.flatnonzero(~fixed)
        self.free = (3 * free_nodes[:, None] + np.arange(3)).ravel()
        K = stiffness(basis.nodes, basis.tets, basis.material).tocsr()
        self.F = Factorisation(K[self.free][:, self.free])
        pos = np.full(self.M, -1)
        pos[free_nodes] = np.arange(len(free_nodes))
        self._surface_rows = (3 * pos[self.surface][:, None] + np.arange(3)).ravel()  # in the free DOFs
        self._surface_dofs = (3 * self.surface[:, None] + np.arange(3)).ravel()  # in all 3M DOFs
        self.volume = float(tet_volumes(basis.nodes, basis.tets).sum())
        self.table = incidence(self.M, self.faces)
        self.solves = 0

    def close(self):
        self.F.free()

    def _solve(self, rhs_free: np.ndarray) -> np.ndarray:
        self.solves += 1
        return self.F.solve(rhs_free)

    def displacement(self, f: np.ndarray) -> np.ndarray:
        """u (M, 3) mm under forces f (S, 3) at ``surface``."""
        rhs = np.zeros(len(self.free))
        rhs[self._surface_rows] = np.asarray(f, float).ravel()
        u = np.zeros(3 * self.M)
        u[self.free] = self._solve(rhs)
        return u.reshape(self.M, 3)

    def objective(self, f_flat, A: sp.csr_matrix, normals, c, lam) -> tuple[float, np.ndarray]:
        """Φ and ∂Φ/∂f (module doc) at fixed correspondences: A (N, M) barycentric rows,
        ``normals`` (N, 3), c (N,) = n_iᵀ(p_i − y_i)."""
        u = self.displacement(f_flat.reshape(-1, 3))
        r = c - np.einsum("ij,ij->i", A @ u, normals)
        n = len(r)
        energy = 0.5 * float(f_flat @ u.ravel()[self._surface_dofs])
        phi = float(r @ r) / n + lam * energy / self.volume
        g_u = -(2.0 / n) * (A.T @ (r[:, None] * normals))  # (M, 3)
        adj = self._solve(g_u.ravel()[self.free])
        grad = adj[self._surface_rows] + lam / self.volume * u.ravel()[self._surface_dofs]
        return phi, grad

    def correspondences(self, points: np.ndarray, u: np.ndarray):
        """A (N, M), normals (N, 3), c (N,) of ``points`` (N, 3) on the surface deformed by u."""
        moved = self.nodes + u
        face, bary, _ = closest_on_surface(points, moved, self.faces, self.table)
        tri = self.faces[face]
        e1, e2 = moved[tri[:, 1]] - moved[tri[:, 0]], moved[tri[:, 2]] - moved[tri[:, 0]]
        nrm = np.cross(e1, e2)
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        rows = np.repeat(np.arange(len(points)), 3)
        A = sp.csr_matrix((bary.ravel(), (rows, tri.ravel())), shape=(len(points), self.M))
        y = A @ self.nodes
        return A, nrm, np.einsum("ij,ij->i", points - y, nrm)

    def green(self, A: sp.csr_matrix, normals: np.ndarray, chunk: int = 200) -> tuple[np.ndarray, sp.csr_matrix]:
        """G (N, N) = D K_ff⁻¹ Dᵀ, the normal displacement at point i under a unit normal force
        at point j, and D (N, free DOFs): row i = n_iᵀ a_i restricted to the free DOFs. Solved in
        blocks of ``chunk`` right-hand sides (memory: free DOFs × chunk)."""
        n = len(normals)
        rows = np.repeat(np.arange(n), 3 * 3)
        A = A.tocsr()
        A.sort_indices()
        cols_node = A.indices.reshape(n, 3)
        vals = (A.data.reshape(n, 3)[:, :, None] * normals[:, None, :])  # (N, 3 nodes, 3 axes)
        dof = (3 * cols_node[:, :, None] + np.arange(3)).reshape(n, 9)
        pos = np.full(3 * self.M, -1)
        pos[self.free] = np.arange(len(self.free))
        keep = pos[dof.ravel()] >= 0
        D = sp.csr_matrix((vals.ravel()[keep], (rows[keep], pos[dof.ravel()][keep])), shape=(n, len(self.free)))
        G = np.empty((n, n))
        DT = D.T.tocsc()
        for s0 in range(0, n, chunk):
            X = self.F.solve(DT[:, s0:s0 + chunk].toarray())
            self.solves += X.shape[1]
            G[:, s0:s0 + chunk] = D @ X
        return 0.5 * (G + G.T), D

    def fit(self, points: np.ndarray, options: ForceOptions = ForceOptions()) -> ForceFit:
        """Surface forces fitted to ``points`` (N, 3) mm in the model frame (module doc).

        At fixed correspondences Φ's minimiser is f = Dₛᵀ w with (G + μ I) w = c, μ = λ N / (2V)
        (the stationarity of Φ with the energy's metric Pᵀ K_ff⁻¹ P factored out: the forces lie
        on the data's own points, one per point, along its normal), so each round is N solves in
        blocks and one N × N system, and u = K_ff⁻¹ Dᵀ w one more solve. ``rounds`` rounds, the
        correspondences recomputed on the deformed surface before each."""
        t0, s0 = time.perf_counter(), self.solves
        u = np.zeros((self.M, 3))
        w = np.zeros(len(points))
        D = None
        for _ in range(options.rounds):
            A, nrm, c = self.correspondences(points, u)
            G, D = self.green(A, nrm)
            mu = options.energy_weight * len(points) / (2.0 * self.volume)
            w = np.linalg.solve(G + mu * np.eye(len(points)), c)
            u = self._field(D, w)
        A, nrm, c = self.correspondences(points, u)
        r = c - np.einsum("ij,ij->i", A @ u, nrm)
        assert D is not None
        f_free = D.T @ w
        energy = 0.5 * float(f_free @ u.ravel()[self.free])
        f = f_free[self._surface_rows].reshape(-1, 3)
        return ForceFit(u, f, float(np.sqrt(np.mean(r ** 2))), energy / self.volume, self.solves - s0,
                        time.perf_counter() - t0)

    def _field(self, D: sp.csr_matrix, w: np.ndarray) -> np.ndarray:
        u = np.zeros(3 * self.M)
        u[self.free] = self._solve(D.T @ w)
        return u.reshape(self.M, 3)


def surface_points(data: dict) -> np.ndarray:
    """The data on the liver's own surface (``features.LIVER_SURFACE``), (N, 3): the points a
    surface-force fit uses (vessel contours and centres are left to LIBR)."""
    parts = [np.asarray(p, float) for k, p in data.items() if k in LIVER_SURFACE and len(p)]
    return np.vstack(parts) if parts else np.zeros((0, 3))


def choose_energy_weight(forces: SurfaceForces, points: np.ndarray, weights=ENERGY_WEIGHTS, blocks: int = 5,
                         options: ForceOptions = ForceOptions()) -> tuple[float, dict]:
    """The λ of ``weights`` whose fits to all but one spatial block predict that block best
    (mean over blocks of the held-out point-to-plane RMS, mm), at the correspondences of the
    fit to all points at the middle λ; returns (λ, {λ: RMS})."""
    labels = blocks_of({"surface": points}, blocks)["surface"]
    mid = ForceOptions(weights[len(weights) // 2], options.rounds)
    fit = forces.fit(points, mid)
    A, nrm, c = forces.correspondences(points, fit.u)
    G, _ = forces.green(A, nrm)
    scores = {}
    for lam in weights:
        err = []
        for b in range(blocks):
            held, train = labels == b, labels != b
            if not held.any() or not train.any():
                continue
            mu = lam * int(train.sum()) / (2.0 * forces.volume)
            w = np.linalg.solve(G[np.ix_(train, train)] + mu * np.eye(int(train.sum())), c[train])
            r = c[held] - G[np.ix_(held, train)] @ w
            err.append(float(np.sqrt(np.mean(r ** 2))))
        scores[lam] = float(np.mean(err))
    return min(scores, key=lambda k: scores[k]), scores

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
whatever S is (``objective``; a finite-difference test). The normal n_i is the face's where
the closest point lies inside a triangle and the distance field's gradient where it lies on an
edge or vertex, so n_iᵀ(p_i − y_i) is the true distance, continuous in the data and the forces
(``correspondences``). At fixed correspondences Φ's minimiser lies in the data's own span
(one normal force per data point: an N × N system with the supported body's Green's matrix,
where the adjoint gradient vanishes, a test). So the
forces act at the data's undeformed correspondences along their normals — at ``sites`` of
them, spread by farthest-point sampling, one solve each (``responses``) — and the
correspondences are recomputed on the deformed surface by a monotone Levenberg–Marquardt on
the site weights whose Jacobian comes from the stored responses without a further solve
(``fit_weights``).

The answer is chosen by held-out data (``choose_deformation``): the surface data cut into
spatial blocks, each predicted by the fits to the others — no deformation, the supported
basis's LIBR fit, the forces at the λ (mm² per Pa of mean strain-energy density) the
one-standard-error rule takes from their path (``one_standard_error``) — as the held-out
points' distance to the surface each answer makes; the least wins, so the answer never
predicts the held-out data worse than not deforming. The data are in the model frame
(the rigid stage's pose applied).

Where the pose is declared (a ``PosePrior``), the forces carry their own rigid part q = (τ, θ)
of eq. 8, fitted with the weights under the prior's term (``PoseTerm``), as the basis's fit
carries its τ, θ: with the supports held, a tracker offset is no deformation the organ can make
cheaply, so the energy and the supports tell it from the dent. In the held-out choice the pose
is the fit to every block (as no deformation's is the rigid stage's); only the forces are
refitted per fold. That pose is kept only where its posterior tells it from the given pose
(``forces_pose_evidence``: the declared rigid stage's criterion, ``uncertainty.PoseEvidence``);
otherwise the forces are fitted at the given pose — a pose the prior lets slide takes up what
forces held stiff by λ leave of a dent, and moves the whole organ for it.
"""

import time
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..anatomy.tets import TetMesh, tet_volumes
from ..features import LIVER_SURFACE
from ..geometry.closest import NEAR, closest_on_surface, incidence, surface_normals
from ..mechanics.basis import Basis
from ..mechanics.fem import stiffness
from ..mechanics.sparse import Factorisation
from ..threads import limit_threads
from .libr import LMOptions, register_libr
from .model import RegistrationModel, deform
from .prior import PosePrior
from .rigid import beta_pose
from .rotation import rotation, rotation_derivatives
from .support import Block, HeldCheck, Support, SupportOptions, blocks_of, paired_gain, supports_not_borne_out
from .uncertainty import PoseEvidence, organ_nodes, point_sigma, pose_columns

MAX_SITES = 150
"""Force sites at most (``SurfaceForces.responses``): one solve each, and with SuperLU a solve of
the 4 mm liver costs ~0.1–0.3 s; 150 sites over a scan of 6–10 % of the surface are 3–6 mm apart,
finer than a tool's dent (docs/decisions/local-loads.md)."""

WARM_WITHOUT_FORCES = ("surface forces are not refitted in a warm re-registration: the basis's answer is shown "
                       "(LIBR's modes held at the declared supports) — register afresh to choose among no "
                       "deformation, the basis and the forces again")
"""The line of a warm re-registration asked for surface forces (``Registration.warm_without_forces``):
a live update must not switch from the forces to the basis silently."""

ENERGY_WEIGHTS = (1e-3, 1e-2, 1e-1, 1.0, 10.0)
"""The λ (mm²/Pa) ``choose_deformation`` compares by held-out RMS, a decade apart."""


def one_standard_error(block_mm: dict[float, np.ndarray], counts: np.ndarray) -> float:
    """The largest λ whose held-out RMS exceeds the least by no more than one standard error of
    that excess (Breiman's one-standard-error rule, the error paired block by block: the most
    regularised fit the held-out blocks cannot tell from the best). ``block_mm``: λ → the RMS
    (mm) of each held-out block; ``counts`` the blocks' points (the weights of their mean).

    Paired because every λ is judged on the same blocks, which differ in how hard they are to
    predict (a block over the dent against a flat one) far more than the λ do on any one
    block; the spread of the blocks' own RMS would accept every λ. Why not the least alone: 5
    blocks, neighbouring λ held out within the blocks' noise of each other, and a smaller λ
    lets the forces grow where no datum checks them (on the study set and draw 3 the least's
    λ = 10⁻³ gave three answers 2–4 mm worse than any other λ; docs/decisions/local-loads.md, session 34)."""
    p = np.asarray(counts, float) / np.sum(counts)
    mean = {k: float(p @ np.asarray(v)) for k, v in block_mm.items()}
    best = min(mean, key=lambda k: (mean[k], -k))
    n = len(p)
    ok = []
    for k, v in block_mm.items():
        d = np.asarray(v) - np.asarray(block_mm[best])
        excess = float(p @ d)
        se = float(np.sqrt(n / max(n - 1, 1) * np.sum(p ** 2 * (d - excess) ** 2)))
        if excess <= se:
            ok.append(k)
    return max(ok)


@dataclass(frozen=True)
class ForceOptions:
    """``energy_weight`` λ (mm²/Pa); the Levenberg–Marquardt of ``fit_weights``: at most
    ``iterations`` steps (each with the correspondences recomputed), stopped when Φ falls by
    less than ``tol`` of itself; ``max_damping_tries`` raises of the damping before a step is
    given up; ``blocks`` the held-out spatial blocks of ``choose_deformation``; ``sites`` the
    force sites at most (``responses``)."""

    energy_weight: float = 0.1
    iterations: int = 15
    tol: float = 1e-3
    max_damping_tries: int = 8
    blocks: int = 5
    sites: int = MAX_SITES


@dataclass(frozen=True)
class PoseTerm:
    """The declared pose in the forces' fit: the rigid part q = (τ mm, θ rad) of eq. 8 — x ↦
    R(θ)(x − x̄0) + τ + x̄0 after the forces' displacement, the rigid stage's pose before it —
    fitted with the forces under the declared prior's term σ_F² |(q − q_c) / σ|², the
    ``PosePrior`` of LIBR's Ω read for one surface feature (Ω / (w_ref u²); prior.py).

    Why: with the supports declared, a tracker offset is not a deformation — the organ cannot
    reach an offset patch without straining from its supports — so the forces alone, deforming
    from the rigid stage's pose (a fit of the undeformed organ to a dented patch), left the
    offset cases 4–8 mm off (docs/decisions/local-loads.md, issue 47 session 37)."""

    centroid: np.ndarray  # x̄0 (3,) mm, the rotation's centre (the mesh nodes' centroid)
    centre: np.ndarray  # q_c (6,): where the given pose lies from the rigid stage's
    sd: np.ndarray  # (6,) σ_τ mm ×3, σ_θ rad ×3
    weight: float  # σ_F² (mm²): the prior's weight against one feature's mean-square distance

    @classmethod
    def of(cls, prior: PosePrior, centroid) -> "PoseTerm":
        sd = np.array([prior.sd_mm] * 3 + [prior.sd_rad] * 3)
        return cls(np.asarray(centroid, float), np.asarray(prior.centre, float), sd, prior.feature_sd_mm ** 2)

    def to_model(self, points: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """R(θ)ᵀ (p − τ − x̄0) + x̄0 (N, 3) — ``points`` (N, 3) in the frame before the deformation
        — and R(θ): distances to the surface are the same in either frame."""
        R = rotation(q[3:])
        return (points - q[:3] - self.centroid) @ R + self.centroid, R

    def jacobian(self, points_model: np.ndarray, d: np.ndarray, nrm: np.ndarray, q: np.ndarray) -> np.ndarray:
        """−∂d/∂q (N, 6) of the signed distances d (N,) of the data to the posed surface
        (``to_model``'s points, their normals ``nrm`` there): d = n_wᵀ(p − x), x = R(θ) l + τ + x̄0
        with l the closest point less x̄0, n_w = R n — so −∂d/∂τ = n_w, −∂d/∂θ_j = n_wᵀ ∂R/∂θ_j l."""
        R = rotation(q[3:])
        nw = nrm @ R.T
        local = points_model - d[:, None] * nrm - self.centroid
        dR = rotation_derivatives(q[3:])
        return np.column_stack([nw] + [np.einsum("ij,ij->i", nw, local @ dR[j].T) for j in range(3)])

    def value(self, q: np.ndarray) -> float:
        return self.weight * float(np.sum(((q - self.centre) / self.sd) ** 2))


@dataclass
class ForceFit:
    """u (M, 3) mm at the mesh nodes; f (S, 3) the surface forces (Pa·mm²); ``rms_mm`` the
    point-to-surface RMS at the end; ``solves`` factorised solves used; ``iterations`` of the
    Levenberg–Marquardt, Φ at its end and at f = 0."""

    u: np.ndarray
    f: np.ndarray
    rms_mm: float
    energy_density_pa: float
    solves: int
    seconds: float
    iterations: int = 0
    phi: float = 0.0
    phi0: float = 0.0


class SurfaceForces:
    """The supported organ's response to surface forces: one factorisation of K_ff.

    ``basis``: a basis computed with ``BasisSettings.supports`` (its mesh, material and the
    held nodes); raises ValueError for a free-floating basis (K would be singular)."""

    def __init__(self, basis: Basis):
        cond = basis.settings.conditions(TetMesh(basis.nodes, basis.tets))
        if cond is None:
            raise ValueError("surface forces need declared supports: a free-floating organ has no unique "
                             "displacement under a load (prepare(..., supports=...))")
        self.nodes, self.faces = basis.nodes, basis.surface_faces
        self.M = len(basis.nodes)
        held = cond.held  # none on springs: K stiffened there instead
        fixed = np.zeros(self.M, bool)
        fixed[held] = True
        self.surface = np.setdiff1d(basis.surface, held)  # the nodes a force may act on
        free_nodes = np.flatnonzero(~fixed)
        self.free = (3 * free_nodes[:, None] + np.arange(3)).ravel()
        K = cond.stiffen(stiffness(basis.nodes, basis.tets, basis.material))
        self.F = Factorisation(K[self.free][:, self.free])
        pos = np.full(self.M, -1)
        pos[free_nodes] = np.arange(len(free_nodes))
        self._surface_rows = (3 * pos[self.surface][:, None] + np.arange(3)).ravel()  # in the free DOFs
        self._surface_dofs = (3 * self.surface[:, None] + np.arange(3)).ravel()  # in all 3M DOFs
        self._free_pos = np.full(3 * self.M, -1)
        self._free_pos[self.free] = np.arange(len(self.free))
        # every surface node, held ones included (their displacement stays 0): the surface a
        # data point's closest point is found on
        self.all_surface = np.asarray(basis.surface)
        self._surface_pos = np.full(self.M, -1)
        self._surface_pos[self.all_surface] = np.arange(len(self.all_surface))
        fp = self._free_pos[(3 * self.all_surface[:, None] + np.arange(3)).ravel()]
        self._all_surface_free_rows = np.flatnonzero(fp >= 0)  # rows of Xs that are free DOFs
        self._all_surface_free_pos = fp[fp >= 0]
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
        """A (N, M), normals (N, 3), c (N,) of ``points`` (N, 3) on the surface deformed by u.

        The normals are ``surface_normals``': the face's inside a triangle, the distance field's
        gradient where the closest point is on an edge or vertex, so c is the true distance and
        continuous in the points. A face's own normal there was the normal of whichever
        incident face won a tie of equal distances (rounding decides it), and the fit's answer
        moved by up to 4 mm with the data moved by 10⁻⁹ mm (docs/decisions/local-loads.md)."""
        moved = self.nodes + u
        face, bary, _ = closest_on_surface(points, moved, self.faces, self.table,
                                           nearest=self._nearest_surface(points, moved))
        tri = self.faces[face]
        nrm = surface_normals(points, moved, self.faces, face, bary)
        rows = np.repeat(np.arange(len(points)), 3)
        A = sp.csr_matrix((bary.ravel(), (rows, tri.ravel())), shape=(len(points), self.M))
        y = A @ self.nodes
        return A, nrm, np.einsum("ij,ij->i", points - y, nrm)

    def green(self, A: sp.csr_matrix, normals: np.ndarray, chunk: int = 200) -> tuple[np.ndarray, sp.csr_matrix]:
        """G (N, N) = D K_ff⁻¹ Dᵀ, the normal displacement at point i under a unit normal force
        at point j, and D (N, free DOFs): row i = n_iᵀ a_i restricted to the free DOFs. Solved in
        blocks of ``chunk`` right-hand sides (memory: free DOFs × chunk)."""
        n = len(normals)
        D = self._normal_rows(A, normals)
        G = np.empty((n, n))
        DT = D.T.tocsc()
        for s0 in range(0, n, chunk):
            X = self.F.solve(DT[:, s0:s0 + chunk].toarray())
            self.solves += X.shape[1]
            G[:, s0:s0 + chunk] = D @ X
        return 0.5 * (G + G.T), D

    def responses(self, points: np.ndarray, sites: int = MAX_SITES) -> "PointForces":
        """The Green's data of ``points`` (N, 3) mm in the model frame at their correspondences on
        the undeformed surface, with the forces at ``sites`` of them (all when N ≤ ``sites``;
        else spread over the data by farthest-point sampling): one solve per site in blocks,
        the only solves a fit and its held-out choice need (``fit_weights``,
        ``choose_deformation``)."""
        points = np.asarray(points, float)
        A, nrm, c = self.correspondences(points, np.zeros((self.M, 3)))
        n = len(points)
        at = spread_sites(points, sites)
        D = self._normal_rows(A, nrm)
        Ds = D[at]
        G = np.empty((n, len(at)))
        Xs = np.zeros((3 * len(self.all_surface), len(at)))
        DT = Ds.T.tocsc()
        for s0 in range(0, len(at), 200):
            with limit_threads(1):
                X = self.F.solve(DT[:, s0:s0 + 200].toarray())
            self.solves += X.shape[1]
            G[:, s0:s0 + 200] = D @ X
            Xs[self._all_surface_free_rows, s0:s0 + 200] = X[self._all_surface_free_pos]
        Gs = G[at]
        return PointForces(points, Ds, G, 0.5 * (Gs + Gs.T), Xs, c, at)

    def _normal_rows(self, A: sp.csr_matrix, normals: np.ndarray) -> sp.csr_matrix:
        """D (N, free DOFs): row i = n_iᵀ a_i restricted to the free DOFs."""
        n = len(normals)
        rows = np.repeat(np.arange(n), 3 * 3)
        A = A.tocsr()
        A.sort_indices()
        cols_node = A.indices.reshape(n, 3)
        vals = (A.data.reshape(n, 3)[:, :, None] * normals[:, None, :])  # (N, 3 nodes, 3 axes)
        dof = (3 * cols_node[:, :, None] + np.arange(3)).reshape(n, 9)
        keep = self._free_pos[dof.ravel()] >= 0
        return sp.csr_matrix((vals.ravel()[keep], (rows[keep], self._free_pos[dof.ravel()][keep])),
                             shape=(n, len(self.free)))

    def _surface_rows_of(self, A: sp.csr_matrix, normals: np.ndarray) -> sp.csr_matrix:
        """Row i = n_iᵀ a_i over the DOFs of ``all_surface`` (the Jacobian's left factor)."""
        n = len(normals)
        A = A.tocsr()
        A.sort_indices()
        node = self._surface_pos[A.indices.reshape(n, 3)]
        vals = A.data.reshape(n, 3)[:, :, None] * normals[:, None, :]
        cols = (3 * node[:, :, None] + np.arange(3)).reshape(n, 9)
        return sp.csr_matrix((vals.ravel(), (np.repeat(np.arange(n), 9), cols.ravel())),
                             shape=(n, 3 * len(self.all_surface)))

    def _nearest_surface(self, points: np.ndarray, moved: np.ndarray) -> np.ndarray:
        """The ``NEAR`` surface nodes nearest each of ``points`` (N, NEAR), among the surface nodes
        only: an interior node has no face to test, and a candidate set of interior nodes put a
        point's closest point on a far vertex (a point 4 mm off the surface matched 40 mm away;
        docs/decisions/local-loads.md, "interior nodes")."""
        near = cKDTree(moved[self.all_surface]).query(points, k=NEAR)[1].reshape(len(points), NEAR)
        return self.all_surface[near]

    def distances(self, points: np.ndarray, us: np.ndarray):
        """Signed distances (N,) of ``points`` to the surface moved by ``us`` (3 S_all,) at the
        surface nodes (the true distances: ``correspondences``' normals), with their barycentric
        rows and normals (the Jacobian's left factor)."""
        moved = self.nodes.copy()
        moved[self.all_surface] += us.reshape(-1, 3)
        face, bary, y = closest_on_surface(points, moved, self.faces, self.table,
                                           nearest=self._nearest_surface(points, moved))
        tri = self.faces[face]
        nrm = surface_normals(points, moved, self.faces, face, bary)
        rows = np.repeat(np.arange(len(points)), 3)
        A = sp.csr_matrix((bary.ravel(), (rows, tri.ravel())), shape=(len(points), self.M))
        return np.einsum("ij,ij->i", points - y, nrm), A, nrm

    def fit_weights(self, pf: "PointForces", lam: float, train: np.ndarray | None = None,
                    options: "ForceOptions | None" = None, pose: PoseTerm | None = None,
                    rigid_only: bool = False, held_q: np.ndarray | None = None,
                    w0: np.ndarray | None = None, q0: np.ndarray | None = None) -> "WeightFit":
        """The forces on the points ``train`` (indices into ``pf``; default all) minimising Φ
        (module doc) with the correspondences recomputed on the deformed surface: Levenberg–
        Marquardt on the point weights w (forces F = Dᵀw at the points' undeformed
        correspondences), Jacobian J = D_now K_ff⁻¹ Dᵀ from the stored responses (no solve),
        a step taken only where Φ at its own closest points falls (monotone), the damping
        raised until one does; stopped when Φ falls by less than ``tol`` (relative), no step
        lowers it, or after ``iterations``. The first undamped step from w = 0 is the exact
        minimiser at the undeformed correspondences (without ``pose``).

        ``pose``: the rigid part q of eq. 8 is fitted with the weights under the declared
        prior's term (``PoseTerm``); the points are then in the rigid stage's frame and the
        answer's pose is that frame's followed by q (``WeightFit.q``); ``rigid_only``: q alone,
        no force (the undeformed organ's pose under the prior: no deformation's own fold fit);
        ``w0``: the weights (one per site of ``train``) the fit starts from (default w = 0;
        ``WeightFit.phi0`` is then Φ there); ``q0``: the rigid part's start with ``pose`` (default
        q = 0, the rigid stage's pose): a probe of whether another pose's start reaches a lower Φ
        (notes/scripts/forces_pose_diagnosis.py; docs/decisions/local-loads.md, "the objective
        prefers the wrong pose")."""
        with limit_threads(1):  # small dense systems: on 2 shared cores threaded BLAS only waits
            return self._fit_weights(pf, lam, train, options or ForceOptions(energy_weight=lam), pose, rigid_only,
                                     held_q, w0, q0)

    def _fit_weights(self, pf: "PointForces", lam: float, train, o: "ForceOptions",
                     pose: PoseTerm | None = None, rigid_only: bool = False,
                     held_q: np.ndarray | None = None, w0: np.ndarray | None = None,
                     q0: np.ndarray | None = None) -> "WeightFit":
        idx = np.arange(len(pf.points)) if train is None else np.asarray(train)
        # the force sites among the training points (a held-out point's site is held out too)
        cols = np.flatnonzero(np.isin(pf.sites, idx)) if not rigid_only else np.zeros(0, int)
        P, X, G = pf.points[idx], pf.Xs[:, cols], pf.Gs[np.ix_(cols, cols)]
        if held_q is not None and pose is not None:  # the pose held where the fit to every block put it
            P, pose = pose.to_model(P, held_q)[0], None
        n, scale, s = len(idx), lam / self.volume, len(cols)

        def phi(x):
            w, q = x[:s], x[s:]
            if pose is None:
                Pm, prior = P, 0.0
            else:
                Pm, prior = pose.to_model(P, q)[0], pose.value(q)
            d, A, nrm = self.distances(Pm, X @ w)
            return float(d @ d) / n + 0.5 * scale * float(w @ G @ w) + prior, d, A, nrm, Pm

        # the pose starts where the rigid stage left it (q = 0), its prior centred on the given pose
        x = np.zeros(s + (6 if pose is not None else 0))
        if w0 is not None:  # the weights' own start (one per site among ``cols``), else w = 0
            x[:s] = w0
        if q0 is not None and pose is not None:  # the pose's own start, else the rigid stage's (q = 0)
            x[s:] = q0
        cur, d, A, nrm, Pm = phi(x)
        start, nu, iterations, accepted = cur, 0.0, 0, 0
        while iterations < o.iterations:
            iterations += 1
            w = x[:s]
            J = np.asarray(self._surface_rows_of(A, nrm) @ X)
            if pose is not None:
                J = np.hstack([J, pose.jacobian(Pm, d, nrm, x[s:])])
            H = (2.0 / n) * (J.T @ J)
            H[:s, :s] += scale * G
            g = -(2.0 / n) * (J.T @ d)
            g[:s] += scale * (G @ w)
            if pose is not None:
                H[s:, s:] += np.diag(2.0 * pose.weight / pose.sd ** 2)
                g[s:] += 2.0 * pose.weight * (x[s:] - pose.centre) / pose.sd ** 2
            diag = np.maximum(np.diag(H), 1e-300)
            step_taken = False
            for _ in range(o.max_damping_tries):
                try:
                    delta = -np.linalg.solve(H + nu * np.diag(diag), g)
                except np.linalg.LinAlgError:
                    delta = None
                if delta is not None and np.isfinite(delta).all():
                    trial = phi(x + delta)
                    if trial[0] < cur:
                        x, step_taken = x + delta, True
                        done = cur - trial[0] < o.tol * cur
                        cur, d, A, nrm, Pm = trial
                        nu = nu / 3.0 if nu > 1e-6 else 0.0
                        break
                nu = max(1e-4, 4.0 * nu)
            if not step_taken:
                break
            accepted += 1
            if done:
                break
        return WeightFit(cols, x[:s], cur, start, float(np.sqrt(np.mean(d ** 2))), iterations, accepted,
                         x[s:] if pose is not None else held_q)

    def field(self, pf: "PointForces", fit: "WeightFit") -> np.ndarray:
        """u (M, 3) mm at every node under the fitted forces (one solve)."""
        u = np.zeros(3 * self.M)
        u[self.free] = self._solve(pf.D[fit.index].T @ fit.w)
        return u.reshape(self.M, 3)

    def fit(self, points: np.ndarray, options: "ForceOptions | None" = None) -> ForceFit:
        """Surface forces fitted to ``points`` (N, 3) mm in the model frame at λ =
        ``options.energy_weight`` (``responses`` then ``fit_weights``)."""
        o = options or ForceOptions()
        t0, s0 = time.perf_counter(), self.solves
        pf = self.responses(points, o.sites)
        wf = self.fit_weights(pf, o.energy_weight, options=o)
        u = self.field(pf, wf)
        f_free = pf.D[wf.index].T @ wf.w
        energy = 0.5 * float(f_free @ u.ravel()[self.free])
        f = f_free[self._surface_rows].reshape(-1, 3)
        return ForceFit(u, f, wf.rms_mm, energy / self.volume, self.solves - s0, time.perf_counter() - t0,
                        wf.iterations, wf.phi, wf.phi0)


@dataclass
class PointForces:
    """``SurfaceForces.responses``: the points (N, 3); D (s, free DOFs) the normal rows of the
    s force sites at their undeformed correspondences; G (N, s) the normal displacement at each
    point under a unit normal force at each site, Gs (s, s) its rows at the sites (the energy's
    metric); Xs (3 S_all, s) the displacement of every surface node under each; c (N,) the
    points' undeformed distances; ``sites`` (s,) the points the forces act at."""

    points: np.ndarray
    D: sp.csr_matrix
    G: np.ndarray
    Gs: np.ndarray
    Xs: np.ndarray
    c: np.ndarray
    sites: np.ndarray


@dataclass
class WeightFit:
    """``fit_weights``: the force sites used (columns of ``PointForces.Xs``), their weights w,
    Φ at the end and at w = 0, the RMS distance (mm), iterations and accepted steps."""

    index: np.ndarray
    w: np.ndarray
    phi: float
    phi0: float
    rms_mm: float
    iterations: int
    accepted: int
    q: np.ndarray | None = None  # the fitted rigid part (τ mm, θ rad) of eq. 8 (``fit_weights``' pose)


def spread_sites(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` of ``points`` (N, 3) spread over them by farthest-point sampling
    from the one nearest their centroid (all, in order, when N ≤ count)."""
    n = len(points)
    if n <= count:
        return np.arange(n)
    chosen = [int(np.argmin(np.linalg.norm(points - points.mean(0), axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(count - 1):
        j = int(np.argmax(dist))
        chosen.append(j)
        dist = np.minimum(dist, np.linalg.norm(points - points[j], axis=1))
    return np.sort(np.array(chosen))


def surface_points(data: dict) -> np.ndarray:
    """The data on the liver's own surface (``features.LIVER_SURFACE``), (N, 3): the points a
    surface-force fit uses (vessel contours and centres are left to LIBR)."""
    parts = [np.asarray(p, float) for k, p in data.items() if k in LIVER_SURFACE and len(p)]
    return np.vstack(parts) if parts else np.zeros((0, 3))


class Answer(Enum):
    """What ``choose_deformation`` shows: no deformation (the rigid pose), the basis's fit
    (LIBR), or the surface forces."""

    NONE = "none"
    BASIS = "basis"
    FORCES = "forces"


@dataclass
class ForceChoice:
    """``choose_deformation``: the answer, the held-out RMS (mm, point-weighted mean over the
    blocks) of no deformation, of the basis's fit (None where there was none) and of the
    forces at each λ (and each block's); the λ the one-standard-error
    rule takes (``one_standard_error``) and the forces' answer there, u (M, 3) mm (model
    frame) and its fit (kept whichever answer is shown)."""

    answer: Answer
    none_mm: float
    basis_mm: float | None
    forces_mm: dict[float, float]
    energy_weight: float | None = None
    forces_blocks_mm: dict[float, np.ndarray] = field(default_factory=dict)  # λ → each block's held-out RMS
    block_points: np.ndarray | None = None  # the points of each held-out block (the blocks' weights)
    u: np.ndarray | None = None
    fit: ForceFit | None = None
    seconds: float = 0.0
    solves: int = 0
    free_mm: float | None = None  # the free-floating basis's held-out RMS (mm) on the same folds
    # the forces' rigid part (τ mm, θ rad) of eq. 8, fitted with them under the declared pose's
    # prior (``PoseTerm``); None: they deform from the rigid stage's pose
    pose: np.ndarray | None = None
    # that pose against the given one by the posterior (``forces_pose_evidence``): not told apart, the
    # forces are fitted at the given pose (``pose`` is then its centre)
    pose_evidence: PoseEvidence | None = None
    # each held-out block's RMS (mm) of no deformation, the basis's fits and the free-floating basis's
    # fits (None where not fitted), and the blocks' centres (B, 3) mm: the paired comparisons of ``held_check``
    none_blocks_mm: np.ndarray | None = None
    basis_blocks_mm: np.ndarray | None = None
    free_blocks_mm: np.ndarray | None = None
    block_centres: np.ndarray | None = None

    @property
    def shown_blocks_mm(self) -> np.ndarray | None:
        """Each held-out block's RMS (mm) of the answer shown."""
        if self.answer is Answer.BASIS:
            return self.basis_blocks_mm
        if self.answer is Answer.FORCES:
            return self.forces_blocks_mm.get(self.energy_weight) if self.energy_weight is not None else None
        return self.none_blocks_mm

    @property
    def shown_mm(self) -> float:
        """The held-out RMS (mm) of the answer shown."""
        if self.answer is Answer.BASIS and self.basis_mm is not None:
            return self.basis_mm
        if self.answer is Answer.FORCES and self.forces_mm:
            return self.forces_mm[self.energy_weight] if self.energy_weight in self.forces_mm \
                else min(self.forces_mm.values())
        return self.none_mm

    @property
    def supports_contradicted(self) -> bool:
        """The free-floating basis predicts the held-out blocks better than the answer shown
        with the declared supports (the same criterion the choice uses: no margin)."""
        return self.free_mm is not None and self.free_mm < self.shown_mm

    @property
    def supports_warning(self) -> str | None:
        if not self.supports_contradicted:
            return None
        assert self.free_mm is not None
        return supports_not_borne_out(self.free_mm, self.shown_mm, "the answer held at them is shown")

    def held_check(self, supports: str, margin: float, paired: bool) -> HeldCheck | None:
        """The answer held at the declared ``supports`` against the free-floating basis's fits on
        the same folds, as a held basis's answer is judged (``support.HeldCheck``): the held
        answer's gain over the free fits paired block by block, and whether the free fits earn a
        deformation over no deformation by the undeclared registration's own rule (``margin``, or
        the paired gain against its standard error where ``paired``; ``support.verdict_rule``).
        No deformation at the rigid stage's pose is one surface in either model, so it is the
        free fits' rigid answer too. None where the free basis was not fitted, or where it
        contradicts the supports (``supports_warning`` says that, and the held answer stays)."""
        shown = self.shown_blocks_mm
        if self.free_mm is None or self.supports_contradicted or shown is None or self.free_blocks_mm is None \
                or self.none_blocks_mm is None or self.block_points is None or self.block_centres is None:
            return None
        rows = list(zip(self.block_centres, self.block_points, self.free_blocks_mm, shown, self.none_blocks_mm,
                        strict=True))
        gain, se = paired_gain([Block(c, int(n), float(f), float(h)) for c, n, f, h, _ in rows])
        free = [Block(c, int(n), float(r), float(f)) for c, n, f, _, r in rows]
        earns = Support(self.none_mm, self.free_mm, free, margin, se_mm=paired_gain(free)[1], paired=paired).predicts
        return HeldCheck(supports, self.shown_mm, self.free_mm, held_deforms=self.answer is not Answer.NONE,
                         free_rigid_mm=self.none_mm, free_earns=earns, gain_mm=gain, gain_se_mm=se)

    @property
    def warning(self) -> str | None:
        if self.answer is not Answer.NONE:
            return None
        return (f"deformation not supported by the data: neither surface forces ({min(self.forces_mm.values()):.2f} "
                f"mm) nor the basis predict held-out data better than no deformation ({self.none_mm:.2f} mm) — "
                "the rigid pose fitted within the declared prior without deformation is shown; add data where "
                "the organ moved")

    def as_dict(self) -> dict:
        return {"answer": self.answer.value, "heldout_none_mm": round(self.none_mm, 3),
                "heldout_basis_mm": None if self.basis_mm is None else round(self.basis_mm, 3),
                "heldout_forces_mm": {f"{k:g}": round(v, 3) for k, v in self.forces_mm.items()},
                "heldout_forces_blocks_mm": {f"{k:g}": [round(float(x), 3) for x in v]
                                             for k, v in self.forces_blocks_mm.items()},
                "heldout_free_mm": None if self.free_mm is None else round(self.free_mm, 3),
                "pose_fitted": None if self.pose is None else
                {"translation_mm": round(float(np.linalg.norm(self.pose[:3])), 3),
                 "rotation_deg": round(float(np.degrees(np.linalg.norm(self.pose[3:]))), 3)},
                "pose_evidence": None if self.pose_evidence is None else self.pose_evidence.as_dict(),
                "supports_contradicted": self.supports_contradicted,
                "energy_weight": self.energy_weight, "seconds": round(self.seconds, 2), "solves": self.solves}


def _basis_surface(model: RegistrationModel, beta: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """The displacement (3 S,) of the surface nodes under the basis's state β (x(β) of eq. 8)."""
    n = model.basis.Ju.shape[1]
    x = model.basis.nodes[surface]
    u = (model.basis.Ju @ beta[:n]).reshape(-1, 3)[surface]
    return (deform(x, u, beta, model.centroid)[1] - x).ravel()


def _posed_surface(forces: SurfaceForces, us: np.ndarray, q: np.ndarray | None, pose: PoseTerm | None) -> np.ndarray:
    """The surface nodes' displacement (3 S,) under forces' ``us`` (3 S,) and the rigid part q
    of eq. 8 (``fit_weights``' pose; None: ``us`` itself)."""
    if q is None or pose is None:
        return us
    x = forces.nodes[forces.all_surface]
    return (beta_pose(q, pose.centroid).apply(x + us.reshape(-1, 3)) - x).ravel()


def forces_pose_evidence(forces: SurfaceForces, pf: "PointForces", fit: "WeightFit", pose: PoseTerm,
                         nodes: np.ndarray) -> PoseEvidence:
    """Is the forces' fitted pose (``fit.q``, ``fit_weights`` with ``pose``) told apart from the
    given pose (q = ``pose.centre``)? The declared rigid stage's criterion
    (``uncertainty.PoseEvidence``; docs/decisions/registration.md, "A declared rigid move judged
    at the scale of the misfit it leaves") read for the forces' fit: ``moved_mm`` the mean over
    ``nodes`` (``organ_nodes``) of |T_q x − T_c x|; σ_pose = sqrt(tr(G Σ_q Gᵀ)) there, Σ_q the
    posterior covariance of q with the forces held (as ``pose_covariance`` holds α),

        Σ_q = (J_qᵀ J_q / (N s²) + Σ_P⁻¹)⁻¹,

    J_q (N, 6) the distances' pose Jacobian at the fit's end (``PoseTerm.jacobian``), Σ_P the
    declared prior's, s = σ_F (the fit's settled scale, ``PoseTerm.weight``: Φ's pose term is
    LIBR's Ω_P read for one feature) and, for ``misfit_sigma_mm``, s = the RMS the forces leave
    (floored at σ_F). Within the clinical goal a move within the larger σ is not told from the
    misfit: a stiff fit (large λ) leaves part of a dent, and the pose, free within its prior,
    takes it up by moving the whole organ (tooldraw3_1-c: 1.3 mm against σ 2.8 mm, TRE 1.52 mm
    against 0.94 at the given pose; docs/decisions/local-loads.md, session 41)."""
    assert fit.q is not None
    q, P = fit.q, pf.points
    Pm = pose.to_model(P, q)[0]
    d, A, nrm = forces.distances(Pm, pf.Xs[:, fit.index] @ fit.w)
    Jq = pose.jacobian(Pm, d, nrm, q)
    G = pose_columns(forces.nodes[nodes] - pose.centroid, np.zeros(3))  # ∂(T_q x)/∂q at q = 0
    moved = np.linalg.norm(beta_pose(q, pose.centroid).apply(forces.nodes[nodes])
                           - beta_pose(pose.centre, pose.centroid).apply(forces.nodes[nodes]), axis=1)
    sf = float(np.sqrt(pose.weight))
    rms = float(np.sqrt(np.mean(d ** 2))) if len(d) else 0.0

    def sigma(s: float) -> float:
        cov = np.linalg.inv(Jq.T @ Jq / (len(P) * s ** 2) + np.diag(1.0 / pose.sd ** 2))
        return float(point_sigma(G, cov=cov).mean())

    prior = float(point_sigma(G, cov=np.diag(pose.sd ** 2)).mean())
    return PoseEvidence(float(moved.mean()), sigma(sf), prior, misfit_sigma_mm=sigma(max(sf, rms)))


def choose_deformation(forces: SurfaceForces, model: RegistrationModel | None, local: dict,
                       basis_beta: np.ndarray | None, libr_options: LMOptions | None,
                       options: ForceOptions = ForceOptions(),
                       weights=ENERGY_WEIGHTS, cancel=None, free: RegistrationModel | None = None,
                       pose: PoseTerm | None = None) -> ForceChoice:
    """No deformation, the basis's answer or surface forces: the one whose fits to all but
    one spatial block of the surface data predict that block best (the points' distance to
    the surface each fold's answer makes, RMS per block, point-weighted mean over blocks).

    ``local``: feature → (N, 3) mm in the model frame (the rigid pose applied); ``model`` the
    supported basis's model (``forces`` made from its basis) and ``basis_beta`` its full fit
    (None: not a candidate), refitted per fold with ``libr_options`` (at most
    ``SupportOptions.iterations``); the forces at each λ of ``weights`` (``fit_weights``; no
    solve beyond the N of ``responses``). No deformation is a candidate judged the same way,
    so the choice is never one that predicts the held-out data worse than not deforming.

    ``free``: the same mesh's free-floating model (``pipeline.free_model``), whose basis's fits
    to the same folds are scored the same way (``ForceChoice.free_mm``): not a candidate (its
    answer is another model's), but the test of the declared supports — where it predicts the
    held-out data better than the answer shown, the supports are contradicted by the data
    (``ForceChoice.supports_warning``).

    ``pose``: the declared pose's prior (``PoseTerm``): the forces' rigid part is fitted with
    them to every block at each λ, as the basis's fits carry their own τ, θ under the same
    prior, and kept where its posterior tells it from the given pose (``forces_pose_evidence``), else
    held at the given pose; held so in every fold and in the answer (``ForceChoice.pose``,
    ``ForceChoice.pose_evidence``). The answer held at the given pose is fitted from w = 0 and
    from the forces fitted with the pose at that λ, the lower Φ kept: the same objective from two
    starts, since from w = 0 the fit can stop on a deep dent far above the Φ those forces reach."""
    t0, s0 = time.perf_counter(), forces.solves
    names = [k for k in local if k in LIVER_SURFACE and len(local[k])]
    points = surface_points(local)
    labels = blocks_of({"surface": points}, options.blocks)["surface"]
    pf = forces.responses(points, options.sites)
    held_of = [np.flatnonzero(labels == b) for b in range(options.blocks)]
    folds = [(h, np.flatnonzero(labels != b)) for b, h in enumerate(held_of) if len(h) and len(h) < len(points)]

    counts = np.array([len(held) for held, _ in folds])

    def blocks(us_of_fold) -> np.ndarray:
        """The held-out RMS of each block (mm)."""
        return np.array([float(np.sqrt(np.mean(forces.distances(points[held], us_of_fold(b, held, train))[0] ** 2)))
                         for b, (held, train) in enumerate(folds)])

    def mean(per_block: np.ndarray) -> float:
        return float(np.average(per_block, weights=counts))

    zero = np.zeros(3 * len(forces.all_surface))
    none_blocks = blocks(lambda b, h, t: zero)
    none_mm = mean(none_blocks)
    basis_mm = free_mm = basis_blocks = free_blocks = None
    if libr_options is not None:
        fold_opts = replace(libr_options, max_iterations=min(libr_options.max_iterations, SupportOptions.iterations))
        sizes = np.cumsum([0] + [len(local[k]) for k in names])
        others = {k: p for k, p in local.items() if k not in names}

        def basis_fold(b, held, train, on: RegistrationModel):
            keep = labels != b
            data = {**others, **{k: local[k][keep[sizes[i]:sizes[i + 1]]] for i, k in enumerate(names)
                                 if keep[sizes[i]:sizes[i + 1]].any()}}
            fitted = register_libr(on, data, None, fold_opts, None, cancel)
            return _basis_surface(on, fitted.beta, forces.all_surface)

        if basis_beta is not None and model is not None:
            basis_blocks = blocks(lambda b, h, t: basis_fold(b, h, t, model))
            basis_mm = mean(basis_blocks)
        if free is not None:
            free_blocks = blocks(lambda b, h, t: basis_fold(b, h, t, free))
            free_mm = mean(free_blocks)
    forces_blocks = {}
    evidence: dict[float, PoseEvidence] = {}
    joint: dict[float, WeightFit] = {}  # each λ's forces fitted with their pose to every block
    organ = organ_nodes(model) if model is not None else np.arange(forces.M)
    for lam in weights:
        o = replace(options, energy_weight=lam)
        # the pose, where it is fitted with the forces, from every block, as no deformation's is
        # (the rigid stage's); only the forces are refitted per fold. A pose the posterior does
        # not tell from the given one is the given one (``forces_pose_evidence``)
        q = None
        if pose is not None:
            fitted = joint[lam] = forces.fit_weights(pf, lam, None, o, pose)
            evidence[lam] = forces_pose_evidence(forces, pf, fitted, pose, organ)
            q = pose.centre if evidence[lam].kept_given else fitted.q

        def force_fold(b, held, train, lam=lam, o=o, q=q):
            fw = forces.fit_weights(pf, lam, train, o, pose, held_q=q)
            return _posed_surface(forces, pf.Xs[:, fw.index] @ fw.w, fw.q, pose)

        forces_blocks[lam] = blocks(force_fold)
    forces_mm = {k: float(np.average(v, weights=counts)) for k, v in forces_blocks.items()}
    best = one_standard_error(forces_blocks, counts)
    scores = {Answer.NONE: none_mm, Answer.FORCES: forces_mm[best]}
    if basis_mm is not None:
        scores[Answer.BASIS] = basis_mm
    answer = min(scores, key=lambda a: (scores[a], a is not Answer.NONE))  # a tie: no deformation
    choice = ForceChoice(answer, none_mm, basis_mm, forces_mm, forces_blocks_mm=forces_blocks, block_points=counts,
                         free_mm=free_mm, none_blocks_mm=none_blocks, basis_blocks_mm=basis_blocks,
                         free_blocks_mm=free_blocks,
                         block_centres=np.array([points[held].mean(0) for held, _ in folds]))
    # the force answer at its λ is kept whichever is shown: a study compares the three
    o = replace(options, energy_weight=best)
    held = pose.centre if pose is not None and evidence[best].kept_given else None
    wf = from_zero = forces.fit_weights(pf, best, None, o, pose, held_q=held)
    if held is not None:
        # at the given pose the fit from w = 0 can end far above the Φ the same λ's forces reach:
        # on tool2-d at S + all (a 45 mm neo-Hookean dent) no damped step lowered Φ after two, at
        # 1.78 mm² (TRE 3.87 mm), where the forces fitted with the pose (0.06 mm from the given one,
        # not told apart) stood at 0.64. Those forces are a second start of the same objective, and
        # the lower Φ is the fit (docs/decisions/local-loads.md, "the given pose from two starts")
        warm = forces.fit_weights(pf, best, None, o, pose, held_q=held, w0=joint[best].w)
        if warm.phi < wf.phi:
            wf = warm
    u = forces.field(pf, wf)
    choice.pose, choice.pose_evidence = wf.q, evidence.get(best)
    f_free = pf.D[wf.index].T @ wf.w
    fit = ForceFit(u, f_free[forces._surface_rows].reshape(-1, 3), wf.rms_mm,
                   0.5 * float(f_free @ u.ravel()[forces.free]) / forces.volume, 0, 0.0, wf.iterations, wf.phi,
                   from_zero.phi0)
    choice.energy_weight, choice.u, choice.fit = best, u, fit
    choice.seconds, choice.solves = time.perf_counter() - t0, forces.solves - s0
    return choice

"""The LIBR deformation basis: Saint-Venant-relaxed control-point modes (paper §II-C,
eq. 3–5; docs/design.md §1).

Given a tet mesh, this computes
- ``control`` (k,): control-point nodes; ``tiles`` (S,): tile of each surface node;
- ``Ju`` (3M × 3k): relaxed displacement modes, mm per unit mode weight α;
- ``energy`` (3k × 3k): J_σᵀ J_ε in Pa, so that the mean nodal strain-energy density is
  f_E = αᵀ energy α / (2M)  (eq. 13).
The 6M × 3k matrices J_ε and J_σ are never stored: only their product is used.

Choices where the paper is open (each tested in tests/test_basis.py):
1. Point-load modes: u = ``perturbation`` (5 mm) e_d at control point c, u = 0 at the
   other k−1 control points, every other node free (one factorisation, 3k solves).
2. Relaxation of mode (c, d): the nodes of c's tile and all interior nodes are free; the
   surface nodes outside the tile are held at the mode's own displacement (the far field
   is kept); the reaction force r that held c in the point-load mode is applied instead
   as a load spread over the tile in proportion to lumped nodal area (its resultant is
   exactly r). One sparse factorisation per tile, shared by its 3 modes.
   With all of the load put back on c the relaxed mode equals the point-load mode — a
   consistency check the tests use. Solved for the correction (relaxed − point-load),
   whose load is self-equilibrated, on the tile plus ``relax_layers`` rings of the node
   graph with the correction held at zero beyond (``None``: on the whole mesh, one
   factorisation of nearly all of K per tile). The error of the local solve against the
   exact one and its effect on TRE are measured in docs/decisions/mechanics.md.
3. Nodal strain and stress are volume-weighted averages of the (constant) element values.
"""

import os
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp

from .. import cache, progress
from ..anatomy.meshing import TetMesh
from ..budget import check_basis
from ..defaults import K
from ..switches import Before
from .controlpoints import geodesic_tiles, nodal_areas, place_control_points
from .fem import Material, nodal_strain_operator, stiffness
from .sparse import Factorisation, backend, one_mkl_thread
from .supports import Conditions, conditions

BASIS_VERSION = "basis-2"  # bump when the computation changes: it is part of the cache key


@dataclass(frozen=True)
class BasisSettings:
    """How the deformation basis is built (paper §II-B–C, eq. 3–5).

    Attributes
    ----------
    k : int
        control points on the surface (k-means of the surface nodes); the basis has 3k modes.
    perturbation : float
        displacement imposed at the active control point, mm.
    seed : int
        k-means seed.
    relax : bool
        Saint-Venant relaxation of the point-load modes over each control point's tile.
    relax_layers : int or None
        the relaxation subdomain: the tile plus this many node rings (None: the whole mesh).
    supports : str or None
        a declared support (``mechanics.supports.Supports``: ligaments, posterior, bare_area):
        its nodes are held at zero displacement in every mode, and no control point lies on
        them. None: the free-floating basis of the paper.
    release : str
        with ``supports = "ligaments"``: the side released (L, N or R).
    stiffness : float or None
        how firmly the supports hold, Pa/mm: on springs this stiff (every mode moves there
        elastically; ``mechanics.supports.conditions``). None: held (zero displacement).
    points : tuple
        with ``supports = "points"``: the support points ((x, y, z), …) mm.
    """

    k: int = K
    perturbation: float = 5.0  # mm imposed at the active control point
    seed: int = 0  # k-means seed
    relax: bool = True  # False: keep the raw point-load modes (for comparison studies)
    # Relaxation subdomain: the tile plus this many rings of the node graph (Saint-Venant:
    # the correction decays away from the tile); None solves on the whole mesh (exact).
    relax_layers: int | None = 6
    supports: str | None = None  # a ``Supports`` name: zero displacement there in every mode
    release: str = "N"
    stiffness: float | None = None  # Pa/mm: springs at the supports instead of zero displacement
    points: tuple = ()  # with supports = "points": ((x, y, z), …) mm

    def conditions(self, mesh: TetMesh) -> Conditions | None:
        """The declared supports as boundary conditions on ``mesh`` (None: free-floating)."""
        if self.supports is None:
            return None
        return conditions(mesh, self.supports, self.release, self.points, self.stiffness)


@dataclass
class Basis:
    """The linear-elastic deformation basis of one tet mesh: u = J_u α (eq. 3–5).

    ``Ju`` (3M, 3k) maps the mode weights α to nodal displacements (mm per unit α, rows
    x, y, z per node); ``energy`` (3k, 3k) = J_σᵀ J_ε (Pa) gives the strain-energy density
    f_E = αᵀ·energy·α / (2M) of eq. 13 (``strain_energy_density``).
    """

    nodes: np.ndarray  # (M, 3) mm
    tets: np.ndarray  # (E, 4)
    surface_faces: np.ndarray  # (F, 3) outward boundary triangles
    control: np.ndarray  # (k,) node indices
    surface: np.ndarray  # (S,) surface node indices
    tiles: np.ndarray  # (S,) tile id of each surface node
    Ju: np.ndarray  # (3M, 3k) mm per unit α
    energy: np.ndarray  # (3k, 3k) Pa, J_σᵀ J_ε
    settings: BasisSettings = field(default_factory=BasisSettings)
    material: Material = field(default_factory=Material)
    timings: dict = field(default_factory=dict)

    @property
    def k(self) -> int:
        return len(self.control)

    @property
    def M(self) -> int:
        return len(self.nodes)

    def modes_at(self, B: sp.spmatrix) -> np.ndarray:
        """Modes carried to points by an interpolation matrix B (P × M): (P, 3, 3k)."""
        n = self.Ju.shape[1]
        return np.asarray(B @ self.Ju.reshape(self.M, 3 * n)).reshape(-1, 3, n)

    def strain_energy_density(self, alpha) -> float:
        """f_E (Pa) for mode weights α (3k,), eq. 13."""
        return float(alpha @ self.energy @ alpha) / (2 * self.M)


def _dofs(nodes_idx):
    return (3 * np.asarray(nodes_idx)[:, None] + np.arange(3)).ravel()


def point_load_modes(K, control, perturbation, held=None):
    """Point-load modes U (3M × 3k) and the reactions R (3k × 3k) at the control DOFs.

    Column 3c+d has u = perturbation·e_d at control c, 0 at the other control points and at
    the ``held`` nodes (H,) of a declared support.
    """
    n = K.shape[0]
    cd = _dofs(control)
    fixed = cd if held is None or len(held) == 0 else np.union1d(cd, _dofs(held))
    free = np.setdiff1d(np.arange(n), fixed)
    U = np.zeros((n, len(cd)))
    U[cd, np.arange(len(cd))] = perturbation
    Kf = K[free]
    with Factorisation(Kf[:, free]) as F:
        U[free] = F.solve(-(Kf[:, cd] @ U[cd]))
    R = K[cd] @ U
    return U, R


def node_adjacency(K) -> sp.csr_matrix:
    """Node graph (M × M, boolean CSR) of the stiffness: i ~ j when they share an element."""
    C = K.tocoo()
    M = K.shape[0] // 3
    A = sp.csr_matrix((np.ones(C.nnz, bool), (C.row // 3, C.col // 3)), shape=(M, M))
    A.sum_duplicates()
    return A


def grow(A, mask, layers):
    """``mask`` (M,) bool grown by ``layers`` rings of the node graph A."""
    mask = mask.copy()
    for _ in range(layers):
        mask |= (A @ mask.astype(np.int8)) > 0
    return mask


def relax_modes(K, U, R, control, surface, tiles, areas, on_tile=None, layers=None, held=None, support=None,
                workers=1):
    """Saint-Venant relaxation of every point-load mode (choice 2 of the module doc).

    K (3M × 3M); U (3M × 3k) point-load modes; R (3k × 3k) their control reactions;
    surface (S,), tiles (S,), areas (S,) lumped nodal areas. Returns relaxed modes (3M × 3k).

    Solved for the correction d = relaxed − point-load, whose load (area-spread reaction
    minus the point reaction, i.e. K U on the free DOFs) is self-equilibrated: by
    Saint-Venant d decays away from the tile. ``layers=None`` solves on the whole mesh
    (exact). ``layers=n`` solves only on the tile plus n rings of the node graph, with
    d = 0 beyond them (and, as in the exact problem, on the held surface nodes).
    ``on_tile(i)`` is called after each tile (progress). ``held`` (H,): nodes of a declared
    support, fixed at zero in every solve; a tile's load is spread over its other nodes.
    ``support`` (default ``held``): the nodes no load is spread on — a support on springs
    (its springs in K) takes none either, so that a stiff spring tends to held.
    ``workers`` > 1: the tiles' solves (independent) in a pool of that many threads, each
    factorisation on one MKL thread (``sparse.one_mkl_thread``); the same answer to the bit
    as one worker, which runs them on one MKL thread too (``relax_workers``).
    """
    n = K.shape[0]
    M = n // 3
    K = K.tocsr()
    out = U.copy()
    movable = np.ones(M, bool)  # interior nodes and, per tile, the tile's own surface nodes
    movable[surface] = False
    is_held = np.zeros(M, bool)
    if held is not None:
        is_held[held] = True
    movable &= ~is_held
    on_support = is_held.copy()
    if support is not None:
        on_support[support] = True
    A = node_adjacency(K) if layers is not None else None

    def tile(c):
        tile_nodes = surface[(tiles == c) & ~is_held[surface]]  # free in this solve (springs move)
        loaded = (tiles == c) & ~on_support[surface]  # the tile's load goes on these
        w = areas[loaded] / areas[loaded].sum()
        free_nodes = movable.copy()
        free_nodes[tile_nodes] = True
        if layers is not None:
            region = np.zeros(M, bool)
            region[surface[loaded]] = True  # grown from where the load is: a spring node adds no ring
            free_nodes &= grow(A, region, layers)
        free = _dofs(np.flatnonzero(free_nodes))
        cols = 3 * c + np.arange(3)
        r = R[3 * c:3 * c + 3][:, cols]  # (3 force axes, 3 modes)
        Kf = K[free]
        rhs = -(Kf @ U[:, cols])  # minus the point-load forces: the reaction at c (and solver residue)
        pos = np.searchsorted(free, 3 * surface[loaded])  # loaded nodes are free: their x DOF rows
        for a in range(3):
            rhs[pos + a] += np.outer(w, r[a])
        with nullcontext() if _relax_as_before else one_mkl_thread(), Factorisation(Kf[:, free]) as F:
            return free, cols, F.solve(rhs)

    workers = 1 if _relax_as_before else workers
    with ThreadPoolExecutor(workers) if workers > 1 else nullcontext() as pool:
        solved = pool.map(tile, range(len(control))) if pool is not None else map(tile, range(len(control)))
        for c, (free, cols, d) in enumerate(solved):  # in tile order, whatever the pool's
            out[np.ix_(free, cols)] += d
            if on_tile:
                on_tile(c)
    return out


RELAX_WORKERS = 2
"""Threads for the relaxation's tiles: each tile's factorisation is its own and PARDISO
releases the GIL, so two run side by side on navapp's two cores, for the same bits as one
after another (docs/decisions/speed.md, "Issue 49, session 40"); more would only queue."""

_relax_as_before = Before()


def relax_as_before() -> AbstractContextManager[None]:
    """Within it, the relaxation runs its tiles one after another on MKL's default threads,
    as before session 40: the benches' "before" (process-wide)."""
    return _relax_as_before.taken()


def relax_workers() -> int:
    """Threads for the relaxation's tiles: ``RELAX_WORKERS``, or fewer where this process may
    use fewer cores."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(RELAX_WORKERS, cores))


def energy_matrix(nodes, tets, Ju, material):
    """J_σᵀJ_ε (3k × 3k, Pa). The nodal strains of all modes (6M × 3k, ≈120 MB at the
    paper's scale) exist only inside this call; stresses are formed and contracted node by
    node through D, so neither J_ε nor J_σ outlives it."""
    G = nodal_strain_operator(nodes, tets)
    D = material.voigt_matrix()
    M, n = len(nodes), Ju.shape[1]
    eps = (G @ Ju).reshape(M, 6, n)
    out = np.einsum("mip,ij,mjq->pq", eps, D, eps, optimize=True)
    return 0.5 * (out + out.T)


def compute_basis(mesh: TetMesh, settings: BasisSettings = BasisSettings(), material: Material = Material(),
                  label="basis") -> Basis:
    """Assemble, place control points, solve point-load modes, relax them, and form the
    strain-energy matrix. Progress is shown per stage; seconds per stage in ``timings``."""
    timings = {}
    t = time.perf_counter()
    faces = mesh.boundary_faces()
    surface = np.unique(faces)
    cond = settings.conditions(mesh)
    held = np.zeros(0, int) if cond is None else cond.held  # on springs: none held, K stiffened
    with progress.stage(f"{label}: assemble"):
        K = stiffness(mesh.nodes, mesh.tets, material)
        if cond is not None:
            K = cond.stiffen(K)
    timings["assemble"] = time.perf_counter() - t
    t = time.perf_counter()
    # no control point on a support, held or on springs: a stiff spring then tends to held
    support = np.zeros(0, int) if cond is None else cond.nodes
    control = place_control_points(mesh.nodes, np.setdiff1d(surface, support), settings.k, settings.seed)
    tiles = geodesic_tiles(mesh.nodes, faces, surface, control)
    areas = nodal_areas(mesh.nodes, faces, surface)
    timings["control_points"] = time.perf_counter() - t
    t = time.perf_counter()
    with progress.stage(f"{label}: point-load modes (factorise + {3 * settings.k} solves, {backend()})"):
        U, R = point_load_modes(K, control, settings.perturbation, held)
    timings["modes"] = time.perf_counter() - t
    t = time.perf_counter()
    if settings.relax:
        with progress.bar(settings.k, f"{label}: relax tiles", "tile") as pb:
            Ju = relax_modes(K, U, R, control, surface, tiles, areas, on_tile=lambda c: pb.update(1),
                             layers=settings.relax_layers, held=held, support=support, workers=relax_workers())
    else:
        Ju = U
    timings["relax"] = time.perf_counter() - t
    t = time.perf_counter()
    energy = energy_matrix(mesh.nodes, mesh.tets, Ju, material)
    timings["energy"] = time.perf_counter() - t
    return Basis(nodes=mesh.nodes, tets=mesh.tets, surface_faces=faces, control=control, surface=surface,
                 tiles=tiles, Ju=Ju, energy=energy, settings=settings, material=material, timings=timings)


def basis_key(mesh: TetMesh, settings: BasisSettings, material: Material) -> str:
    d = asdict(settings)
    if d["supports"] is None:  # the free-floating basis keeps the key it had before supports existed
        del d["supports"], d["release"]
    for name in ("stiffness", "points"):  # and a held one the key it had before springs and points
        if d[name] is None or d[name] == ():
            del d[name]
    return cache.content_key(BASIS_VERSION, mesh.nodes, mesh.tets, d, asdict(material))


def load_or_compute_basis(mesh: TetMesh, settings: BasisSettings = BasisSettings(), material: Material = Material(),
                          cache_root=None, label="basis") -> tuple[Basis, bool]:
    """The basis from the cache if a valid entry exists, else computed and cached.
    Returns (basis, loaded_from_cache)."""
    root = cache.cache_dir() if cache_root is None else cache_root
    path = root / f"{basis_key(mesh, settings, material)}.npz"
    t = time.perf_counter()
    hit = cache.load(path)
    if hit is not None:
        b = Basis(nodes=hit["nodes"], tets=hit["tets"], surface_faces=hit["surface_faces"], control=hit["control"],
                  surface=hit["surface"], tiles=hit["tiles"], Ju=hit["Ju"], energy=hit["energy"],
                  settings=settings, material=material, timings={"load": time.perf_counter() - t})
        return b, True
    check_basis(len(mesh.nodes), settings.k)  # before the work: a basis too large for memory ends in one line
    b = compute_basis(mesh, settings, material, label)
    cache.save(path, {name: getattr(b, name) for name in
                      ("nodes", "tets", "surface_faces", "control", "surface", "tiles", "Ju", "energy")})
    return b, False

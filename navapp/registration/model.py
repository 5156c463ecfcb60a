"""The model side of registration: which deformable geometry each data feature slides on.

Every model feature is a set of points carried by the tet mesh (``B`` maps nodal values
to them, so they deform as B·(x0 + J_u α)) plus its cells: triangles for sliding surfaces,
segments for centerlines, none for fiducials.

Data feature → model feature (a choice where the paper is open; ``navapp.features`` holds
the table): anterior and posterior points slide on the whole liver surface (restricting
posterior iUS points to the labelled posterior region was measured worse — the region's
edges stop points sliding; docs/decisions/registration.md); falciform and ridge points only on their
own labelled region (salient features); iUS contours on the PV/HV surfaces; centerline
points on the centerline polylines; fiducials on their preoperative counterparts, row by row.
"""

import warnings
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..anatomy.meshing import MeshProvenance
from ..anatomy.model import REGION_NAMES, VESSELS, PreopModel
from ..errors import InputError
from ..features import SALIENT, data_to_model, weights_si
from ..geometry.closest import NEAR, NEAR_DECIMATED, incidence
from ..geometry.interpolation import interpolation_matrix
from ..geometry.transforms import apply_rigid
from ..mechanics.basis import Basis
from ..threads import both, kernel_threads
from .rotation import rotation

if TYPE_CHECKING:
    from ..geometry.bvh import SurfaceHierarchy

# the data features' weights (m⁻², paper §II-D), salient features and model targets come
# from the one feature table, ``navapp.features``
WEIGHTS_SI = weights_si()
W_ENERGY_SI = 1e-8  # Pa⁻², the strain-energy weight w_E of eq. 7

DATA_TO_MODEL = data_to_model()


@dataclass
class ModelFeature:
    kind: str  # "surface" | "centerline" | "fiducial"
    B: sp.csr_matrix  # (V, M): nodal values → this feature's points
    cells: np.ndarray | None  # (F, 3) triangles, (S, 2) segments, or None
    table: np.ndarray | None  # vertex → incident cells (see geometry.closest.incidence)
    rest: np.ndarray  # (V, 3) undeformed points, mm
    BJ: np.ndarray  # (V, 3, 3k): the basis carried to these points, B·J_u (mm per unit α)
    near: int = NEAR  # nearest vertices whose incident cells LM tests (``geometry.closest``)
    # a labelled region's points are some of the liver surface's: the model feature they belong
    # to and their rows there (``rest`` and ``BJ`` are those rows'), so that an evaluation that
    # deforms the liver takes them from it instead of reading their B·J_u again
    part_of: str | None = None
    part_rows: np.ndarray | None = field(default=None, repr=False, compare=False)
    # a surface's bounding-volume tree (``geometry.bvh``), built on first use by ``search_tree``
    hierarchy: "SurfaceHierarchy | None" = field(default=None, repr=False, compare=False)
    # (B·J_u, its single-precision copy (3V, 3k)), made by ``single_basis`` on first use; kept with
    # the B·J_u it was made from, so a copy of the feature with other modes makes its own
    single: tuple | None = field(default=None, repr=False, compare=False)

    def single_basis(self) -> np.ndarray:
        """B·J_u in single precision, (3V, 3k), made once per B·J_u: what eq. 8 multiplies by α
        (``RegistrationModel.positions``)."""
        kept = self.single
        if kept is None or kept[0] is not self.BJ:
            kept = self.single = (self.BJ, np.ascontiguousarray(self.BJ.reshape(-1, self.BJ.shape[2]), np.float32))
        return kept[1]

    def search_tree(self) -> "SurfaceHierarchy":
        """The surface's ``bvh.SurfaceHierarchy`` on its undeformed points, built once."""
        if self.hierarchy is None:
            from ..geometry.bvh import SurfaceHierarchy as Hierarchy  # imports Numba: only where surfaces are searched

            self.hierarchy = Hierarchy(self.rest, self.cells)
        return self.hierarchy


@dataclass
class ModelCache:
    """What registration derives from a model and keeps with it, one typed entry each.

    Thread-safety: the viewer's live follower, the next-plane suggestion and other fits run
    on the same model in other threads, without a lock. So an entry is only ever replaced
    whole (``cache.x = new``, a keyed map by a new dict ``{**cache.x, key: value}``), never
    mutated in place: a reader holds the old value or the new one, never half of each. Two
    threads writing at once may lose one entry, which is then computed again."""

    # multi-start ICP (``rigid``): id(ModelFeature) → (KD-tree of its rest vertices, the
    # vertices (V, 3) mm, their normals (V, 3) or None)
    screen: dict[int, tuple] = field(default_factory=dict)
    # ``coverage.data_coverage``: data feature → (its points Y (N, 3), rows L kept from the
    # last call, nodes covered by Y[:L] (V,) bool, nodes covered by Y (V,) bool)
    coverage: dict[str, tuple] = field(default_factory=dict)
    # ``pose.pose_determinacy``'s last answer: (R (3, 3), t (3,), surface data, Determinacy)
    determinacy: tuple | None = None
    # ``objective.evaluate``'s most recent evaluation (beta, geometry, data and correspondence),
    # and fits' last ones (``objective.keep_end``), newest first
    evaluation: tuple | None = None
    ends: tuple = ()
    # ``local_modes.with_sources``: the mesh's nodal strain operator (sparse, ≈ 28 MB at 18.5k nodes)
    strain_operator: Any = None
    # ``pipeline.undetermined_pose``: (the nodes it was measured on, the model's extent mm)
    extent_mm: tuple[np.ndarray, float] | None = None
    # ``next_plane.anterior_surface_mask``: (regions' hash, vertex count) → (S,) bool
    anterior: dict[tuple, np.ndarray] = field(default_factory=dict)
    # ``uncertainty.surface_estimate``: (vertices' shape, sum) → nearest surface node (V,)
    surface_map: dict[tuple, np.ndarray] = field(default_factory=dict)

    def copy(self) -> "ModelCache":
        """A cache holding the same entries, written to apart from this one (a benchmark's
        model that must not warm, or be warmed by, another's); entries are shared, which is
        safe as none is mutated in place."""
        return replace(self)


@dataclass
class RegistrationModel:
    """The preoperative geometry carried by the basis' mesh: each model feature (liver
    surface, labelled regions, vessel surfaces, centerlines, fiducials) deforms by eq. 8;
    ``feature_for`` says which one a data feature slides on (``navapp.features``)."""

    basis: Basis
    features: dict  # model feature name → ModelFeature
    centroid: np.ndarray  # x̄0 (3,), centroid of the mesh nodes
    # derived data kept with the model (``ModelCache``: e.g. the multi-start ICP's vertex KD-trees)
    cache: ModelCache = field(default_factory=ModelCache, repr=False, compare=False)
    # which mesher made the basis' mesh and why (``prepare`` sets it; results report it)
    mesher: MeshProvenance | None = field(default=None, compare=False)

    def feature_for(self, data_name: str) -> ModelFeature:
        """The model feature a data feature slides on; a salient region the model has no
        labels for falls back to the whole liver surface (``usable_data`` warns)."""
        target = DATA_TO_MODEL[data_name]
        if target not in self.features and target in SALIENT:
            target = "liver"
        return self.features[target]

    def positions(self, feat: ModelFeature, beta) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 8 at a feature's points: (x0 − x̄0 + J_u α) and x(β), both (V, 3) mm; J_u α
        from B·J_u in single precision (``displacement``)."""
        n = len(beta) - 6
        alpha = beta[:n]
        kernel = _place_kernel() if alpha.any() else None
        if kernel is None:
            return deform(feat.rest, displacement(feat.BJ, alpha, feat.single_basis()), beta, self.centroid)
        # the same product as ``displacement``'s, eq. 8 then in one compiled pass (``deform_compiled``)
        u = _product(feat.single_basis(), alpha.astype(np.float32))
        local, x = np.empty_like(feat.rest), np.empty_like(feat.rest)
        kernel(feat.rest, u, self.centroid, rotation(beta[n + 3:n + 6]), np.ascontiguousarray(beta[n:n + 3]), local, x)
        return local, x


SPLIT_ROWS = 4096  # B·J_u rows from which the single-precision product is split among two threads
_BLOCK = 64  # rows: where the product is cut (``_product``)


def _product(single: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """single (3V, 3k) @ α (3k,) in single precision: inside ``threads.split_kernels`` with two
    threads, the rows cut in two at a multiple of 64 and each half multiplied by BLAS on its own
    thread (``threads.both``). BLAS makes each row's sum alone, by a kernel that takes rows in
    fixed groups, so a cut at a multiple of the group gives the whole product's bits (checked
    by ``tests/test_split_kernels.py``); a product across 2 BLAS threads does not (it sums
    otherwise: docs/decisions/speed.md, "The live update on two cores")."""
    rows = single.shape[0]
    if rows < SPLIT_ROWS or kernel_threads() < 2:
        return single @ alpha
    cut = (rows // 2) // _BLOCK * _BLOCK
    u = np.empty(rows, np.float32)
    both(lambda: np.matmul(single[:cut], alpha, out=u[:cut]), lambda: np.matmul(single[cut:], alpha, out=u[cut:]))
    return u


_place_kernels: list = []  # ``deform_compiled.place`` or None, imported on first use (Numba takes ~1 s to load)


def _place_kernel():
    if not _place_kernels:
        from .deform_compiled import place

        _place_kernels.append(place)
    return _place_kernels[0]


def displacement(BJ: np.ndarray, alpha: np.ndarray, single: np.ndarray | None = None) -> np.ndarray:
    """J_u α carried to a feature's points, (V, 3) mm, from its B·J_u (V, 3, 3k) or S·B·J_u.

    ``single``: B·J_u in single precision (3V, 3k) (``ModelFeature.single_basis``), multiplied
    instead. Reading B·J_u is an LM evaluation's largest cost (the liver's is 20 MB in double
    precision, every evaluation); in single precision it is half the bytes and twice the
    width of each vector instruction, and J_u α comes out within ~1e-5 mm of the double
    product (docs/decisions/speed.md, "Eq. 8 in single precision"): the positions, in double
    precision, are x0 + that. S·B·J_u (a few rows) stays in double precision.

    At α = 0 (every fit from β = 0 starts there: the continuation's first fit, the basin
    screening's, each cross-validation fold's deformable and rigid fits, and a rigid fit
    never leaves it) the product is zero without reading B·J_u: the same bits, as x0 + 0 is
    x0 and ``deform`` then subtracts x̄0."""
    if not alpha.any():
        return np.zeros((BJ.shape[0] * BJ.shape[1] // 3, 3))
    if single is not None:
        return (single @ alpha.astype(np.float32)).astype(float).reshape(-1, 3)
    return (BJ.reshape(-1, len(alpha)) @ alpha).reshape(-1, 3)


def deform(rest, u, beta, centroid) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 8, the one implementation: x(β) = R(θ) (x0 − x̄0 + u) + τ + x̄0.

    Parameters
    ----------
    rest : (P, 3) mm
        undeformed positions x0.
    u : (P, 3) mm
        their displacement J_u α, however the caller carried the basis to them (a feature's
        B·J_u, interpolation in the mesh, or held correspondences' S·B·J_u).
    beta : (3k + 6,)
        the state (α, τ, θ): τ in mm, θ in radians (``rotation``).
    centroid : (3,) mm
        x̄0, the centroid of the mesh nodes: the rotation acts about it.

    Returns
    -------
    local : (P, 3) mm
        x0 − x̄0 + u, the deformed points before the rigid part (what ∂x/∂θ needs).
    x : (P, 3) mm
        x(β).
    """
    n = len(beta) - 6
    local = rest + u - centroid
    return local, apply_rigid(rotation(beta[n + 3:n + 6]), beta[n:n + 3], local) + centroid


# Vessel surfaces are decimated to this many triangles for registration: both vessels are
# deformed and searched at every LM evaluation, and the decimation error stays far below
# the 4 mm tet mesh (measurements: docs/decisions/registration.md, "Measured choices moved out of docstrings").
VESSEL_FACES = 4000


def _feature(kind, B, cells, basis, BJ=None, near=NEAR):
    B = sp.csr_matrix(B)
    rest = np.asarray(B @ basis.nodes)
    table = None if cells is None else incidence(B.shape[0], cells)
    if BJ is None:
        BJ = basis.modes_at(B)
    return ModelFeature(kind, B, cells, table, rest, BJ, near)


def build_model(basis: Basis, preop: PreopModel, fiducials: np.ndarray | None = None) -> RegistrationModel:
    """Carry the preoperative geometry onto the basis' mesh."""
    nodes, M = basis.nodes, basis.M
    feats = {}
    # liver surface = the tet mesh boundary (so it deforms exactly with the FE nodes)
    surf = basis.surface
    local = np.full(M, -1)
    local[surf] = np.arange(len(surf))
    sel = sp.csr_matrix((np.ones(len(surf)), (np.arange(len(surf)), surf)), shape=(len(surf), M))
    faces = local[basis.surface_faces]
    feats["liver"] = _feature("surface", sel, faces, basis)
    if preop.regions is not None:
        _, near = cKDTree(preop.liver.vertices).query(nodes[surf])
        labels = preop.regions[near]
        for name in SALIENT:
            code = REGION_NAMES.index(name)
            keep = (labels[faces] == code).sum(1) >= 2
            if keep.any():
                verts = np.unique(faces[keep])  # the region as its own compact surface patch
                remap = np.full(len(surf), -1)
                remap[verts] = np.arange(len(verts))
                feats[name] = replace(_feature("surface", sel[verts], remap[faces[keep]], basis,
                                               feats["liver"].BJ[verts]), part_of="liver", part_rows=verts)
    for v in VESSELS:
        mesh = preop.vessel(v)
        if mesh is not None:
            if len(mesh.faces) > VESSEL_FACES:
                # quadric decimation (see VESSEL_FACES for what it costs in accuracy)
                mesh = mesh.simplify_quadric_decimation(face_count=VESSEL_FACES)
            feats[v] = _feature("surface", interpolation_matrix(nodes, basis.tets, mesh.vertices),
                                np.asarray(mesh.faces), basis, near=NEAR_DECIMATED)
        cl = preop.centerline(v)
        if cl is not None:
            feats[f"{v}_centerline"] = _feature("centerline", interpolation_matrix(nodes, basis.tets, cl.points),
                                                cl.segments(), basis)
    if fiducials is not None:
        feats["fiducials"] = _feature("fiducial", interpolation_matrix(nodes, basis.tets, fiducials), None, basis)
    return RegistrationModel(basis=basis, features=feats, centroid=nodes.mean(0))


def extended_model(model: RegistrationModel, basis: Basis) -> RegistrationModel:
    """``model`` on ``basis``, the same mesh with modes appended after the model's own
    (``mechanics.local_modes.with_modes``): every feature keeps its points and cells and
    gets the new modes carried to them. The cache starts empty."""
    n = model.basis.Ju.shape[1]
    new = replace(basis, Ju=basis.Ju[:, n:])
    feats = {name: replace(f, BJ=np.concatenate([f.BJ, new.modes_at(f.B)], axis=2))
             for name, f in model.features.items()}
    return RegistrationModel(basis=basis, features=feats, centroid=model.centroid, mesher=model.mesher)


def rebased_model(model: RegistrationModel, basis: Basis) -> RegistrationModel:
    """``model`` on another ``basis`` of the same mesh (e.g. the free-floating one of a model
    held at declared supports): every feature keeps its points and cells and carries the new
    basis's modes. The cache starts empty."""
    if basis.nodes.shape != model.basis.nodes.shape or not np.array_equal(basis.tets, model.basis.tets):
        raise ValueError("rebased_model: the basis is of another mesh")
    feats = {name: replace(f, BJ=basis.modes_at(f.B)) for name, f in model.features.items()}
    return RegistrationModel(basis=basis, features=feats, centroid=model.centroid, mesher=model.mesher)


def usable_data(model: RegistrationModel, data: dict) -> dict:
    """The data features the model can match, as float64 arrays; warns about the rest and
    raises for non-finite input (before any solving)."""
    out = {}
    for name, pts in data.items():
        pts = np.asarray(pts, dtype=float)
        if pts.size == 0:
            continue
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"feature {name!r}: expected (N, 3) points, got shape {pts.shape}")
        if not np.isfinite(pts).all():
            raise InputError(f"feature {name!r}: NaN or infinite coordinates")
        target = DATA_TO_MODEL.get(name)
        if target is None:
            raise InputError(f"unknown feature {name!r}")
        if target not in model.features:
            if target in SALIENT and "liver" in model.features:
                warnings.warn(f"no '{target}' region in the model (regions.csv missing?): "
                              f"{name} points slide on the whole liver surface", stacklevel=2)
            elif name == "fiducials":
                raise InputError("intraoperative fiducials need preop/fiducials.csv (their preoperative positions)")
            else:
                warnings.warn(f"feature {name!r} ignored: the case has no preoperative {target}", stacklevel=2)
                continue
        if name == "fiducials" and len(pts) != model.features["fiducials"].B.shape[0]:
            raise InputError(f"{len(pts)} intraoperative fiducials but "
                             f"{model.features['fiducials'].B.shape[0]} preoperative ones")
        out[name] = pts
    return out

"""Residuals, closed-form Jacobians and the objective Ω (paper eq. 7–13, Table I).

State β = (α, τ, θ), length 3k + 6. A model point deforms as (eq. 8)
    x(β) = R(θ) (x0 − x̄0 + J_u α) + τ + x̄0,
and each data point y_i gets p_i = y_i − S_i x(β), S_i its closest point on the deformed
model feature (recomputed at every evaluation; normals and tangents held fixed within it).
Residuals f_i are in mm internally (centerline and fiducial points as three component
rows, see ``residuals``); weights are converted so that Ω equals the paper's SI
value: w_F [m⁻²] · (unit_m)² / N_F per squared residual, and w_E [Pa⁻²] on f_E [Pa].
"""

import time
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..geometry.closest import (
    closest_on_polyline,
    closest_on_surface,
    hierarchy_search,
    nearest_vertices,
    surface_normals,
    vertex_tree,
)
from ..switches import Before
from ..threads import SPLIT_MIN, kernel_threads
from .barycentric import Barycentric
from .model import W_ENERGY_SI, WEIGHTS_SI, RegistrationModel, deform, displacement
from .prior import PosePrior
from .rotation import rotation, rotation_derivatives

if TYPE_CHECKING:
    from ..geometry.bvh import SurfaceHierarchy


@dataclass(frozen=True)
class Rejection:
    """Outlier rejection on every data feature, by the same reweighting as the Huber
    thresholds: at each evaluation a point whose residual f exceeds

        cut = max(floor_mm, k × the median f of all data points)

    gets weight 0 (its feature keeps w_F / N_F per remaining point). One wrong click on an
    image (a posterior vertex 40 mm below the wall) rasterises into a spike of hundreds of
    points, more than half of its feature: a cut from the feature's own residuals, or a
    Huber weight, still lets it pull; the median over all data is set by the many good
    points. ``k`` keeps the cut loose while the fit is far off (after the rigid pose of a
    large deformation the good points too are several mm off), ``floor_mm`` once it has
    converged; below the cut a Huber δ (``robust_weights``) bounds the pull of the spike's
    foot. Measured: docs/decisions/registration.md, "Outliers"."""

    floor_mm: float = 10.0
    k: float = 5.0

    def cut_mm(self, residuals: np.ndarray) -> float:
        """The cut for these per-point residuals f (all data points), mm."""
        return max(self.floor_mm, self.k * float(np.median(residuals))) if len(residuals) else float("inf")

    def beyond(self, residuals: np.ndarray) -> np.ndarray:
        """(N,) bool: the residuals (mm) beyond their own cut. A drawn vessel contour's vertices
        are judged so before the fit, by their distance from the contour's centre
        (``app.contours.stray_vertices``): a vessel tree has a branch near most places, so a
        stray vertex's residual to the model does not show it."""
        residuals = np.asarray(residuals, float)
        return residuals > self.cut_mm(residuals)


@dataclass
class Weights:
    """The weights of Ω (eq. 7): w_F per data feature (m⁻², ``navapp.features``), w_E on the
    strain energy (Pa⁻²), optional Huber thresholds (mm) per feature and an optional
    outlier rejection on every feature."""

    features: dict = field(default_factory=lambda: dict(WEIGHTS_SI))  # m⁻²
    energy: float = W_ENERGY_SI  # Pa⁻²
    unit_m: float = 1e-3  # metres per model length unit (mm)
    # feature → Huber threshold δ (mm): a point whose residual f exceeds δ has its weight
    # scaled by δ / f (iteratively reweighted least squares), so a salient feature whose
    # labels are approximate pulls linearly rather than quadratically. Empty: plain Ω.
    huber_mm: dict = field(default_factory=dict)
    # outlier rejection on every feature (``Rejection``), in the same weight factors; None: off
    reject: Rejection | None = None
    # the pose prior's term of Ω (``prior.PosePrior``: τ, θ about the rigid stage's pose); None: no prior
    pose_prior: PosePrior | None = None

    def scaled(self, factor: float) -> "Weights":
        return Weights({k: v * factor for k, v in self.features.items()}, self.energy * factor, self.unit_m,
                       dict(self.huber_mm), self.reject, self.pose_prior)

    def robust_factors(self, distances: dict, rows: dict) -> dict:
        """Feature → (R,) weight factors of its residual rows from its per-point residuals f
        (``distances``: feature → (N,) mm; ``rows``: feature → (R,) the point of each row):
        δ / max(f, δ) on a feature with a Huber δ, times 0 beyond the rejection cut. Only
        features with a factor other than 1 possible are listed (none: plain Ω)."""
        out = {}
        cut = self.reject.cut_mm(np.concatenate(list(distances.values()))) if self.reject and distances else None
        for name, dist in distances.items():
            factor = None
            if name in self.huber_mm:
                delta = self.huber_mm[name]
                factor = delta / np.maximum(dist, delta)
            if cut is not None:
                factor = (np.ones(len(dist)) if factor is None else factor) * (dist <= cut)
            if factor is not None:
                out[name] = factor[rows[name]]
        return out


HUBER_MM = 2.0  # Huber δ (mm) on the features without their own, in ``robust_weights``


def robust_weights(salient_mm: float) -> Weights:
    """Weights robust on every feature: Huber δ ``salient_mm`` on the salient features (the
    pipeline's ``RobustOptions.huber_salient_mm``), ``HUBER_MM`` on every other, and outlier
    rejection (``Rejection``). The viewer fits with these (a click can go wrong);
    ``pipeline.register``'s default is the salient Huber alone (docs/decisions/registration.md, "Outliers")."""
    from ..features import NAMES, SALIENT

    return Weights(huber_mm={n: salient_mm if n in SALIENT else HUBER_MM for n in NAMES},
                   reject=Rejection())


@dataclass
class Evaluation:
    omega: float
    # (R + P + 1,) residual rows (see ``residuals``): data (mm), the pose prior's P = 6 rows when
    # ``Weights.pose_prior`` is set (else P = 0; dimensionless), then f_E (Pa)
    f: np.ndarray
    w: np.ndarray  # (R + P + 1,) weights of f² in Ω
    J: np.ndarray | None  # (R + P + 1, 3k + 6); None until asked for (``jacobian=True`` or ``add_jacobian``)
    features: dict  # name → {"n", "rms_mm", "mean_abs_mm", "max_abs_mm", "omega"}
    timings: dict
    correspondence: dict  # name → Correspondence: reuse with ``frozen=`` to hold them fixed
    beta: np.ndarray  # (3k + 6,) the state evaluated
    terms: list  # per data feature (name, feature, S, q, rows, local): what ``add_jacobian`` needs
    scales: dict | None = None  # feature → (R,) robust weight factors of its rows (``Weights.robust_factors``)
    pose_prior: PosePrior | None = None  # the prior whose P rows f holds (``Weights.pose_prior``)
    # (β, geometry, data and correspondences) for a later evaluation at the same β (``keep_end``)
    reusable: tuple | None = field(default=None, repr=False)
    # √W·J (each row of J times √w), made with J by ``add_jacobian`` for LM's JᵀWJ; None when J
    # was assembled otherwise (``points_of``: the weights are made again there)
    Js: np.ndarray | None = field(default=None, repr=False)

    @property
    def jacobian(self) -> np.ndarray:
        """J (R + 1, 3k + 6); evaluate with ``jacobian=True`` or call ``add_jacobian`` first."""
        if self.J is None:
            raise ValueError("this evaluation has no Jacobian (evaluate with jacobian=True or add_jacobian)")
        return self.J


def _stats(f, wF) -> dict:
    """Per-feature statistics of the per-point residuals f (N,), mm. Three reductions (every
    evaluation makes these for every feature, ~26 a live update; np.mean's wrapper cost more
    than its sums)."""
    ff = float(f @ f)
    a = np.abs(f)
    return {"n": int(len(f)), "rms_mm": float(np.sqrt(ff / len(f))), "mean_abs_mm": float(a.sum()) / len(f),
            "max_abs_mm": float(a.max()), "omega": wF * ff}


@dataclass(frozen=True)
class FittedSurface:
    """A surface's hierarchy (``bvh.SurfaceHierarchy``) with its boxes refitted at one
    evaluation's deformed points: what ``correspond`` searches instead of a k-d tree."""

    hierarchy: "SurfaceHierarchy"
    boxes: np.ndarray


def _place(model, feat, beta, geometry, placed) -> tuple[np.ndarray, np.ndarray]:
    """(local, x) of eq. 8 at a model feature's points at β within one evaluation: from
    ``geometry`` (id → (local, X, tree)) when searched already, a region's rows of the
    feature it is part of (``ModelFeature.part_of``: the liver's product read once), or
    ``model.positions``; kept in ``placed`` (id → (local, X))."""
    key = id(feat)
    if key in geometry:
        return geometry[key][0], geometry[key][1]
    if key not in placed:
        whole = model.features.get(feat.part_of) if feat.part_of is not None else None
        if whole is not None and feat.part_rows is not None:
            local, X = _place(model, whole, beta, geometry, placed)
            placed[key] = (local[feat.part_rows], X[feat.part_rows])
        else:
            placed[key] = model.positions(feat, beta)
    return placed[key]


def _tree(feat, X):
    """The search structure of a model feature at its deformed points X: a surface's
    hierarchy refitted (exact closest points; ``geometry.bvh``), else a k-d tree of X rebuilt
    (``vertex_tree``: the fastest to build)."""
    if feat.kind == "surface" and hierarchy_search():
        h = feat.search_tree()
        return FittedSurface(h, h.refit(X))
    return vertex_tree(X)


def _apply(S, X):
    """S @ X for a dense X (V, 3): compiled where Numba is (the same bits as SciPy's product)."""
    kernel = _alpha_kernel()
    if kernel is None:
        return S @ X
    out = np.empty((S.shape[0], X.shape[1]))
    kernel[2](S.indptr, S.indices, S.data, np.ascontiguousarray(X, dtype=float), out)
    return out


def _carried(SBJ, alpha):
    """J_u α at held closest points, (N, 3) mm, from their S·B·J_u (N, 3, 3k): the compiled α
    kernel keeps it in single precision, summed here in double (``jacobian_compiled.carried``);
    NumPy's double product for the double S·B·J_u of the SciPy/NumPy Jacobian."""
    if SBJ.dtype != np.float32:
        return displacement(SBJ, alpha)
    if not alpha.any():
        return np.zeros((len(SBJ), 3))
    out = np.empty((len(SBJ), 3))
    _jacobian_kernel[0][3](SBJ, np.ascontiguousarray(alpha, dtype=float), out)  # made it: it is loaded
    return out


@dataclass
class Correspondence:
    """Where one data feature's N points meet its model feature, held fixed within an LM
    iteration (eq. 9–10: S_i and the normals or tangents of Table I).

    Attributes
    ----------
    S : Barycentric, (N, V)
        row i: the barycentric weights of point i's closest point on the model feature's
        V points (a triangle's three, a segment's two, or the fiducial itself).
    direction : (N, 3) array or None
        unit normals (surfaces) or tangents (centerlines) at the closest points; None for
        fiducials.
    SBJ : (N, 3, 3k) array or None
        S·B·J_u, the basis carried to the closest points (mm per unit α; single precision
        where the Jacobian was compiled, as eq. 8's whole-feature product is: J's α columns are
        made from its double-precision sum, ``jacobian_compiled``), and
    S_rest : (N, 3) array or None
        S·x0 (mm): both added with the Jacobian (``add_jacobian``). When present, x(β) at the
        closest points costs N·3·3k instead of deforming the whole feature (the held fast path).
        A pose-only Jacobian (``add_jacobian(alpha=False)``, at α = 0) adds S·x0 alone: the
        held fast path then applies at α = 0, where S·B·J_u α is zero.
    face : (N,) int array or None
        a surface's closest triangle per point (the hierarchy's search): the next search of
        the same points starts from it (``evaluate(warm=)``; speed only, the answer is exact).
    """

    S: Barycentric
    direction: np.ndarray | None
    SBJ: np.ndarray | None = None
    S_rest: np.ndarray | None = None
    face: np.ndarray | None = None

    @property
    def carries_basis(self) -> bool:
        """S·B·J_u and S·x0 are known: the held fast path applies."""
        return self.SBJ is not None

    def held_fast(self, alpha: np.ndarray) -> bool:
        """x(β) at the closest points can be made from S·x0 (and S·B·J_u) at this α."""
        return self.S_rest is not None and (self.SBJ is not None or not alpha.any())

    def without_basis(self) -> "Correspondence":
        """The same correspondence without S·B·J_u and S·x0 (x(β) then from the whole feature)."""
        return Correspondence(self.S, self.direction, face=self.face)


def correspond(feat, X, Y, tree=None, nearest=None, start=None) -> Correspondence:
    """Closest points of data Y (N, 3) mm on the model feature ``feat`` at its current
    geometry X (V, 3) mm: S and the direction data (normals for surfaces, tangents for
    centerlines). ``tree``/``nearest``: a surface's ``FittedSurface`` at X (exact closest
    points), a KD-tree of X, or Y's nearest vertices of X when already found. ``start``
    (N,): a triangle per point for the hierarchy's search to begin from (the last search's
    ``Correspondence.face``): a tight first bound, the same answer."""
    N = len(Y)
    kind = feat.kind
    if kind == "surface":
        face = None
        hierarchy = isinstance(tree, FittedSurface)
        if hierarchy:
            face, bary = tree.hierarchy.closest(Y, X, tree.boxes, start)
            if not (face >= 0).all():  # a non-finite surface: the candidates' path says what it can
                face = None
                tree = None
                hierarchy = False
        if face is None:
            face, bary, _ = closest_on_surface(Y, X, feat.cells, feat.table, feat.near,
                                               tree=tree, nearest=nearest)
        # the normal at the closest point: the face's inside a triangle, p/|p| on an edge or
        # vertex (``surface_normals``), which makes f the true point–surface distance
        S = Barycentric.of(bary, feat.cells[face], len(X))
        return Correspondence(S, surface_normals(Y, X, feat.cells, face, bary), face=face if hierarchy else None)
    if kind == "centerline":
        seg, t, _ = closest_on_polyline(Y, X, feat.cells, feat.table, tree=tree, nearest=nearest)
        ends = feat.cells[seg]
        S = Barycentric.of(np.column_stack([1 - t, t]), ends, len(X))
        tan = X[ends[:, 1]] - X[ends[:, 0]]
        tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-300)
        return Correspondence(S, tan)
    return Correspondence(Barycentric.identity(N), None)


def _kept_points(seen: tuple, Y: np.ndarray) -> int:
    """How many of ``Y``'s first points (N, 3) are ``seen``'s first points, row for row
    (``seen``: a kept evaluation's (points, correspondence, residual rows) of the feature);
    0 within ``search_whole``."""
    if _search_whole:
        return 0
    Y0 = seen[0]
    m = min(len(Y0), len(Y))
    if not m or Y0.ndim != 2 or np.ndim(Y) != 2 or Y0.shape[1] != np.shape(Y)[1]:
        return 0
    same = (Y0[:m] == Y[:m]).all(axis=1)
    return m if same.all() else int(np.argmin(same))


def _joined(seen: tuple, kept: int, c: "Correspondence | None", made: tuple | None, n_columns: int):
    """The correspondence and residual rows (r, q, rows, dist) of a feature's points whose
    first ``kept`` are ``seen``'s (the same β) and the rest searched now (``c``, ``made``:
    the rest's correspondence and ``residuals``; None when there is no rest): what one
    search of them all gives, to the bit, as every row belongs to one point and is made
    from it alone (the S rows, the normal or tangent, the residual rows, the distance)."""
    _, c0, (r0, q0, rows0, dist0) = seen
    per_point = 1 if len(r0) == len(dist0) else 3  # surfaces: one row a point; centerlines: three
    head = kept * per_point
    data, cols = c0.S.weights[:kept], c0.S.columns[:kept]
    direction, face = c0.direction[:kept], None if c0.face is None else c0.face[:kept]
    r, q, rows, dist = r0[:head], q0[:head], rows0[:head], dist0[:kept]
    if c is not None and made is not None:
        r1, q1, rows1 = made
        data, cols = np.concatenate([data, c.S.weights]), np.concatenate([cols, c.S.columns])
        direction = np.concatenate([direction, c.direction])
        face = None if face is None or c.face is None else np.concatenate([face, c.face])
        dist = np.concatenate([dist, point_distances(r1, rows1, len(r1) // per_point)])
        r, q, rows = np.concatenate([r0[:head], r1]), np.concatenate([q0[:head], q1]), \
            np.concatenate([rows0[:head], rows1 + kept])
    S = Barycentric.of(data, cols, n_columns)
    return Correspondence(S, direction, face=face), (r, q, rows, dist)


def residuals(kind, p, direction):
    """Residual rows of Table I for N points with p (N, 3) mm.

    Returns r (R,), q = ∂r/∂p (R, 3) and the point each row belongs to (R,). Surfaces give
    one row per point: r = nᵀp, q = n. Centerlines and fiducials give three: the components
    of the rejection (I − ttᵀ)p (q = the rows of I − ttᵀ), resp. of p itself (q = I).

    Why three rows where Table I has one (f = ‖(I − ttᵀ)p‖, ‖p‖, q = rejection / f): Σ r² =
    f² per point, so Ω (eq. 7) is the same, but a norm's linearisation f + qᵀΔp misses the
    part of Δp perpendicular to q, which only ever increases f. With held tangents the
    components are linear in p, so the Gauss–Newton model of these terms is exact; the
    norm form made the warm-started demo reject its first three LM steps (two centerline
    points carry the whole feature weight) and has no derivative at f = 0, where the
    components have one.
    """
    N = len(p)
    if kind == "surface":
        return np.einsum("ij,ij->i", direction, p), direction, np.arange(N)
    if kind == "centerline":
        P = np.eye(3) - direction[:, :, None] * direction[:, None, :]  # (N, 3, 3), symmetric
        r = np.einsum("iab,ib->ia", P, p)
        q = P
    else:
        r, q = p, np.broadcast_to(np.eye(3), (N, 3, 3))
    return r.ravel(), q.reshape(3 * N, 3), np.repeat(np.arange(N), 3)


def point_distances(r, rows, n_points):
    """Per-point residual f (N,) from residual rows: |r| for surfaces, the norm of the
    three components for centerlines and fiducials (Table I's f)."""
    if len(r) == n_points:
        return np.abs(r)
    return np.sqrt(np.bincount(rows, r * r, minlength=n_points))


def evaluate(model: RegistrationModel, data: dict, beta: np.ndarray, weights: Weights, jacobian=True,
             frozen: dict | None = None, scales: dict | None = None, alpha_columns: bool = True,
             warm: dict | None = None) -> Evaluation:
    """Ω(β) with residuals, per-feature statistics and (optionally) the Jacobian J = ∂f/∂β.

    Correspondences S_i and their normals/tangents are recomputed at β unless ``frozen``
    (a previous evaluation's ``correspondence``) is given: then they are held fixed,
    which makes Ω a smooth function of β within an LM iteration. Without the Jacobian,
    ``add_jacobian`` can add it later at the same correspondences (LM decides whether to
    go on only once it knows Ω, and the Jacobian of the last state is never needed).
    ``scales``: robust weight factors to hold (a previous evaluation's ``scales``), so that
    with held correspondences Ω is one fixed weighted least-squares problem; otherwise
    they are computed here from the residuals (``Weights.robust_factors``: Huber δ,
    outlier rejection). ``alpha_columns``: as for ``add_jacobian``. ``warm``: an earlier
    evaluation's ``correspondence`` of the same data (LM's last state): each surface's search
    starts from the triangles found there (``correspond(start=)``; the same answer, fewer boxes
    visited), where a feature's points are the same count (off within ``cold_search``).
    """
    basis = model.basis
    n = basis.Ju.shape[1]
    alpha = beta[:n]
    tim = {"deform": 0.0, "kdtree": 0.0, "closest": 0.0, "jacobian": 0.0}
    fs, ws, stats, corr, terms = [], [], {}, {}, []
    dists, row_of = {}, {}  # feature → per-point residual f (N,), the point of each row (R,)
    made = {}  # feature → (r, q, rows, dist)
    placed: dict[int, tuple] = {}  # model features deformed without a search structure (``_place``)
    geometry = {}  # model feature → (local, X, KD-tree): anterior and posterior share the liver
    # a warm re-registration per frame starts at the β the last one ended at, where the model
    # was just deformed and searched, and most of its data (the kept stylus points and planes)
    # are the same: that evaluation's geometry and the correspondences of data equal element
    # for element are the ones this one would compute
    last = _at(model, beta) if frozen is None else None
    if last is not None:
        geometry = dict(last[1])
    for name, Y in data.items():
        feat = model.feature_for(name)
        key = id(feat)
        local = None
        held = None  # (r, q, rows, dist) kept from an evaluation at the same β and data
        if frozen is not None and frozen[name].held_fast(alpha) and not jacobian:
            # held correspondences carry S·B·J_u and S·x0 from the evaluation that made them:
            # x at the corresponded points costs N·3·3k instead of deforming the whole
            # feature (S's rows sum to one, so S commutes with the rigid part of eq. 8)
            t0 = time.perf_counter()
            c = corr[name] = frozen[name]
            S, direction = c.S, c.direction
            u = np.zeros((len(c.S_rest), 3)) if c.SBJ is None else _carried(c.SBJ, alpha)
            p = Y - deform(c.S_rest, u, beta, model.centroid)[1]
            tim["deform"] += time.perf_counter() - t0
        else:
            if key not in geometry:
                t0 = time.perf_counter()
                local, X = _place(model, feat, beta, geometry, placed)
                tim["deform"] += time.perf_counter() - t0
                t0 = time.perf_counter()
                tree = _tree(feat, X) if frozen is None and feat.kind != "fiducial" else None
                tim["kdtree"] += time.perf_counter() - t0
                geometry[key] = (local, X, tree)
            local, X, tree = geometry[key]
            seen = last[2].get(name) if last is not None else None
            if seen is not None and seen[0].shape == np.shape(Y) and np.array_equal(seen[0], Y):
                # the same β, the same data: the same correspondence and residual rows
                c = corr[name] = seen[1]
                held = seen[2]
            else:
                # the same β, the feature's first points the same (the kept data come first,
                # ``live.merge``): their rows are kept and only the points after them searched
                kept = _kept_points(seen, Y) if seen is not None and feat.kind != "fiducial" else 0
                new = Y[kept:] if kept else Y
                c = None
                if len(new) or not kept:
                    t0 = time.perf_counter()
                    kd = tree is not None and not isinstance(tree, FittedSurface)
                    nearest = nearest_vertices(tree, new, feat.near) if kd else None
                    tim["kdtree"] += time.perf_counter() - t0
                    t0 = time.perf_counter()
                    before = warm.get(name) if warm is not None and not _cold_search else None
                    start = before.face if before is not None and before.face is not None else None
                    start = start[kept:] if start is not None and len(start) == len(Y) else None
                    c = (frozen[name] if frozen is not None
                         else correspond(feat, X, new, tree=None if kd else tree, nearest=nearest, start=start))
                    tim["closest"] += time.perf_counter() - t0
                if kept:
                    assert seen is not None
                    t0 = time.perf_counter()
                    made_new = None
                    if c is not None:
                        made_new = residuals(feat.kind, new - _apply(c.S, X), c.direction)
                    c, held = _joined(seen, kept, c, made_new, len(X))
                    tim["closest"] += time.perf_counter() - t0
                corr[name] = c
            S, direction = c.S, c.direction
            if held is None:
                p = Y - _apply(S, X)
        t0 = time.perf_counter()
        if held is None:
            r, q, rows = residuals(feat.kind, p, direction)
            held = (r, q, rows, point_distances(r, rows, len(Y)))
        r, q, rows, dist = made[name] = held
        wF = weights.features[name] * weights.unit_m ** 2 / len(Y)
        fs.append(r)
        ws.append(np.full(len(r), wF))
        dists[name], row_of[name] = dist, rows
        stats[name] = _stats(dist, wF)
        terms.append((name, feat, S, q, rows, local))
        tim["jacobian"] += time.perf_counter() - t0
    reusable = None
    if frozen is None:  # replaced whole: an evaluation in another thread reads the old or the new
        reusable = model.cache.evaluation = (np.array(beta, float), geometry, {
            name: (np.array(Y, float), corr[name], made[name]) for name, Y in data.items()})
    # robust weight factors (Huber, outlier rejection): held when given, so that with held
    # correspondences Ω is one fixed weighted least-squares problem
    robust = dict(scales) if scales is not None else weights.robust_factors(dists, row_of)
    for i, name in enumerate(data):
        if name in robust:
            ws[i] = ws[i] * robust[name]
    if (prior := weights.pose_prior) is not None:  # rows between the data's and f_E's (``add_jacobian``)
        JP = prior.jacobian(n)
        fP, sP = prior.residual(JP, beta), prior.scale(weights.unit_m)
        fs.append(fP)
        ws.append(np.full(6, sP))
        moved = fP * np.repeat([prior.sd_mm, prior.sd_deg], 3)  # the organ's rigid motion: mm, degrees
        stats["pose_prior"] = {"omega": float(sP * fP @ fP), "shift_mm": float(np.linalg.norm(moved[:3])),
                               "turn_deg": float(np.linalg.norm(moved[3:]))}
    fE = basis.strain_energy_density(alpha)
    fs.append(np.array([fE]))
    ws.append(np.array([weights.energy]))
    f = np.concatenate(fs)
    w = np.concatenate(ws)
    stats["strain_energy"] = {"f_E_pa": fE, "omega": float(weights.energy * fE ** 2)}
    ev = Evaluation(omega=float(w @ (f * f)), f=f, w=w, J=None, features=stats, timings=tim, correspondence=corr,
                    beta=np.array(beta, float), terms=terms, scales=robust, reusable=reusable,
                    pose_prior=weights.pose_prior)
    return add_jacobian(model, ev, alpha_columns) if jacobian else ev


def points_of(ev: Evaluation, keep: dict, weights: Weights) -> Evaluation:
    """``ev`` restricted to some of its data points: the evaluation ``evaluate`` would make of
    the kept points at the same β, to the bit, without searching or deforming again.

    Every residual row, its Jacobian row, correspondence, normal and per-point distance belongs
    to one point and is computed from it alone, so a subset's are the same rows. What depends
    on the set is made again as ``evaluate`` makes it: w_F / N_F with the kept count, the robust
    factors from the kept points' distances (an outlier cut's median over them), the statistics
    and Ω. The cross-validation's folds start from one evaluation at β = 0 of all the data
    (``support.check_support_pair``), each from its training points' rows.

    Parameters
    ----------
    ev : Evaluation
        with its Jacobian (``add_jacobian``), of data feature → (N, 3) points.
    keep : dict
        feature → (N,) bool, the points kept; a feature with none kept, or absent, is dropped.
        Fiducials are kept whole or not at all (they pair with the model's row by row; the
        cross-validation keeps them in every fold).
    weights : Weights
        the weights ``ev`` was made with.

    Returns
    -------
    Evaluation of the kept points (no ``reusable`` entry: nothing is kept for a warm start).
    """
    J = ev.jacobian
    fs, ws, Js, stats, corr, terms = [], [], [], {}, {}, []
    dists, row_of, counts = {}, {}, {}
    at = 0
    for name, feat, S, q, rows, local in ev.terms:
        block = slice(at, at + len(q))
        at += len(q)
        mask = keep.get(name)
        if mask is None or not mask.any():
            continue
        if feat.kind == "fiducial" and not mask.all():
            # fiducials pair with the model's row by row: a subset evaluated apart would pair anew
            raise ValueError("points_of: fiducials are kept whole or not at all")
        idx = np.flatnonzero(mask)
        on = mask[rows]
        new_rows = (np.cumsum(mask) - 1)[rows[on]]
        c = ev.correspondence[name]
        S_kept = S[idx]
        corr[name] = Correspondence(S_kept, None if c.direction is None else c.direction[idx],
                                    None if c.SBJ is None else c.SBJ[idx],
                                    None if c.S_rest is None else c.S_rest[idx],
                                    None if c.face is None else c.face[idx])
        q_kept = q[on]
        dist = point_distances(ev.f[block][on], new_rows, len(idx))
        wF = weights.features[name] * weights.unit_m ** 2 / len(idx)
        fs.append(ev.f[block][on])
        ws.append(np.full(len(q_kept), wF))
        Js.append(J[block][on])
        dists[name], row_of[name], counts[name] = dist, new_rows, len(idx)
        stats[name] = _stats(dist, wF)
        terms.append((name, feat, S_kept, q_kept, new_rows, local))
    robust = weights.robust_factors(dists, row_of)
    for i, (name, *_rest) in enumerate(terms):
        if name in robust:
            ws[i] = ws[i] * robust[name]
    tail = slice(at, len(ev.f))  # the pose prior's rows and f_E's, which no point owns
    fs.append(ev.f[tail])
    ws.append(ev.w[tail])
    Js.append(J[tail])
    for key in ("pose_prior", "strain_energy"):
        if key in ev.features:
            stats[key] = ev.features[key]
    f, w = np.concatenate(fs), np.concatenate(ws)
    return Evaluation(omega=float(w @ (f * f)), f=f, w=w, J=np.concatenate(Js), features=stats,
                      timings={k: 0.0 for k in ev.timings}, correspondence=corr, beta=ev.beta.copy(), terms=terms,
                      scales=robust, pose_prior=ev.pose_prior)


KEPT_ENDS = 4  # fits' last evaluations kept per model (``keep_end``)


def keep_end(model: RegistrationModel, ev: Evaluation) -> None:
    """Keep ``ev``, a fit's last evaluation, for the fit that starts where it ended (the next
    frame's warm start): ``evaluate`` reuses the most recent evaluation and these. Several are
    kept because other fits run in between (the viewer's next-plane suggestion; the live bench
    runs three variants on one model, frame by frame)."""
    if ev.reusable is None:
        return
    ends = [e for e in model.cache.ends if not np.array_equal(e[0], ev.beta)]
    model.cache.ends = (ev.reusable, *ends[:KEPT_ENDS - 1])


def _at(model: RegistrationModel, beta) -> tuple | None:
    """A kept evaluation at exactly ``beta`` (the most recent, or a fit's end), if any."""
    for e in (model.cache.evaluation, *model.cache.ends):
        if e is not None and np.array_equal(e[0], beta):
            return e
    return None


# the compiled (α columns, pose columns, S·X, U·α, the α columns split among threads), or None
# (``jacobian_compiled``), imported on first use
_jacobian_kernel: list = []
_numpy_jacobian = Before()  # ``numpy_jacobian``


def _alpha_kernel():
    if _numpy_jacobian:
        return None
    if not _jacobian_kernel:
        from .jacobian_compiled import alpha_columns, alpha_columns_split, apply, carried, pose_columns

        _jacobian_kernel.append(None if alpha_columns is None else (alpha_columns, pose_columns, apply, carried,
                                                                    alpha_columns_split))
    return _jacobian_kernel[0]


def _split(points: int) -> bool:
    """Whether a compiled kernel over ``points`` points takes its split build: inside
    ``threads.split_kernels`` and enough points to share (``threads.SPLIT_MIN``)."""
    return points >= SPLIT_MIN and kernel_threads() > 1


_cold_search = Before()  # ``cold_search``
_search_whole = Before()  # ``search_whole``


def search_whole() -> AbstractContextManager[None]:
    """Within it, ``evaluate`` searches a feature's points all again where the kept evaluation
    at the same β had only its first points (the next live frame's contours after the kept
    planes'), as before those points' rows were kept (the benches' "before"); process-wide."""
    return _search_whole.taken()


def cold_search() -> AbstractContextManager[None]:
    """Within it, ``evaluate`` ignores ``warm``: every surface search starts at the hierarchy's
    root, as before the warm start (the benches' "before"); process-wide."""
    return _cold_search.taken()


def numpy_jacobian() -> AbstractContextManager[None]:
    """Within it, ``add_jacobian`` forms the α columns with SciPy and NumPy, as before the
    compiled ones (the benches' "before"); process-wide."""
    return _numpy_jacobian.taken()


def add_jacobian(model: RegistrationModel, ev: Evaluation, alpha_columns: bool = True) -> Evaluation:
    """J = ∂f/∂β (R + 1, 3k + 6) of Table I at ``ev``'s state and correspondences, stored
    in ``ev.J``; each correspondence gains S·B·J_u and S·x0 for the held fast path.

    ``alpha_columns=False`` at α = 0: a fit that holds α (``LMOptions(deform=False)``: the
    cross-validation's rigid folds, the declared rigid stage) uses only the six pose columns,
    so the α columns are left zero and S·B·J_u unmade (the same pose columns, the same LM
    steps: J·Δ over columns whose Δ is zero adds exact zeros); each correspondence gains
    S·x0 alone, which at α = 0 is the held fast path's whole input."""
    if ev.J is not None:
        return ev
    basis, beta = model.basis, ev.beta
    n = basis.Ju.shape[1]
    if not alpha_columns and beta[:n].any():
        raise ValueError("add_jacobian: the α columns can be left out only at α = 0")
    R = rotation(beta[n + 3:n + 6])
    dR = rotation_derivatives(beta[n + 3:n + 6])
    t0 = time.perf_counter()
    kernel = _alpha_kernel()
    J = np.empty((len(ev.f), n + 6))  # filled block by block: the data rows, the prior's, f_E's
    sw = np.sqrt(ev.w)
    # √W·J for LM's JᵀWJ, written by the kernels beside J (the bits of NumPy's J * sw[:, None])
    Js = np.empty_like(J) if kernel is not None else None
    at = 0
    for name, feat, S, q, rows, local in ev.terms:
        if local is None:  # made by the held fast path: the feature's points were never deformed
            local = model.positions(feat, beta)[0]
        Jf = J[at:at + len(q)]
        block = slice(at, at + len(q))
        at += len(q)
        qR = q @ R  # qᵀR, (R, 3)
        c = ev.correspondence[name]
        if not alpha_columns:
            Jf[:, :n] = 0.0
        if kernel is not None:
            assert Js is not None
            Jsf, swf = Js[block], sw[block]
            alpha_kernel = kernel[4] if _split(S.shape[0]) else kernel[0]
            U = None
            if alpha_columns:
                # S·B·J_u kept in single precision for the held fast path; J from it in double
                U = np.empty((S.shape[0], 3, n), np.float32)
                alpha_kernel(S.indptr, S.indices, S.data, feat.BJ, np.ascontiguousarray(qR), rows, U, Jf, swf, Jsf)
            else:
                Jsf[:, :n] = Jf[:, :n] * swf[:, None]
            S_rest = np.empty((S.shape[0], 3))
            kernel[1](S.indptr, S.indices, S.data, feat.rest, local, np.ascontiguousarray(q), dR, rows, S_rest, Jf,
                      swf, Jsf)
            if not c.carries_basis:
                ev.correspondence[name] = Correspondence(c.S, c.direction, U, S_rest, c.face)
            continue
        U = None
        if alpha_columns:
            U = np.asarray(S @ feat.BJ.reshape(len(local), 3 * n)).reshape(-1, 3, n)
            Jf[:, :n] = -np.einsum("ia,iak->ik", qR, U[rows] if len(q) != S.shape[0] else U)
        if not c.carries_basis:
            ev.correspondence[name] = Correspondence(c.S, c.direction, U, S @ feat.rest, c.face)
        Jf[:, n:n + 3] = -q
        xl = (S @ local)[rows]
        for j in range(3):
            Jf[:, n + 3 + j] = -np.einsum("ia,ab,ib->i", q, dR[j], xl)
    data_end = at
    if ev.pose_prior is not None:
        J[at:at + 6] = ev.pose_prior.jacobian(n)
        at += 6
    J[at] = 0.0
    J[at, :n] = (basis.energy @ beta[:n]) / basis.M
    if Js is None:
        Js = J * sw[:, None]
    else:  # the prior's rows and f_E's
        Js[data_end:] = J[data_end:] * sw[data_end:, None]
    ev.J, ev.Js = J, Js
    ev.timings["jacobian"] += time.perf_counter() - t0
    return ev

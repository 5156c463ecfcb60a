"""A registration-error estimate that needs no truth.

Two things the registration knows about a point of the organ:

- d, the distance from its registered position to the nearest data point (the paper's
  Fig. 5d predictor: the error grows away from the data);
- σ, the standard deviation of its registered position under the Levenberg–Marquardt
  (Laplace) covariance at the solution, propagated through the closed-form Jacobian of
  eq. 8, G = ∂x/∂β:
      Σ_β = s · H⁻¹,  H = JᵀWJ + w_E f_E ∇²f_E,   σ² = tr(G Σ_β Gᵀ),
  with s = Ω / (R − p) the reduced χ² of the fit (so that each residual's implied noise
  variance is s / w_i) and H the same matrix the LM step uses (``libr.py``), plus the strain
  energy's curvature over its own posterior spread (``energy_spread``: the quartic energy's
  Laplace curvature vanishes with the deformation, and held σ far from the data by nothing).

The predicted error combines them with a calibration fitted on the study cases of one
liver (direct and transposed deformations) and validated on the other livers' cases
(``navapp study error-estimate``, ``results/error_estimate.md``):
    ê = a + b·d + c·σ + e·d·m   (mm),
m the median of d over the mesh nodes (how sparse the data are: with a complete surface
(CBCT) the nodes far from the data are deep ones the elastic model keeps right, and d
alone was anti-correlated with the error), and a band [ê · q_lo, ê · q_hi] holding the
true error for ``coverage`` of the points of each kind of calibration case (quantiles of
true / ê).

With a declared pose (``prior``) the pose is counted once: σ is the deformation's given the pose
(α's block of H) and the pose's posterior σ_pose (data and the declared prior) joins ê in
quadrature (``estimate_error``); and s is read robustly, each data feature's mean square replaced
by its robust variance (``Information.robust_scale``, where that is the lesser), as the declared
prior reads the noise.
"""

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import chi2

from ..features import SALIENT
from ..geometry.interpolation import interpolation_matrix
from ..geometry.transforms import apply_rigid
from ..threads import limit_threads
from .model import RegistrationModel, deform
from .objective import Weights, evaluate
from .prior import FEATURE_SD_MM, likelihood_scale
from .rotation import rotation, rotation_derivatives


@dataclass(frozen=True)
class Calibration:
    """ê = a + b·d + c·σ + e·d·m (mm) and the band factors (ê·lower, ê·upper) holding the
    true error for ``coverage`` of the calibration points. Defaults: fitted by
    ``navapp study error-estimate --cases STUDY/phantom* --with-cases STUDY_LAP/lap*
    --band-cases TOOL/tool*`` on the cases of one liver (phantom 0): ê on the direct gravity
    cases phantom0-L/N/R and the transposed, paper-difficulty cases lap0-L/N/R (neo-Hookean
    reference), at every data level, on relative errors; the band then widened until it
    holds ``coverage`` at every data level of each kind of deformation, the local tool
    loads tool0-* included.
    Validated on the cases of the two other livers (results/error_estimate.md,
    docs/decisions/error-estimate.md)."""
    a: float = 0.59697  # mm
    b: float = 0.0038633  # mm per mm of distance to the data
    c: float = 5.1995  # per mm of σ
    e: float = 0.00027235  # per mm of m (× d)
    lower: float = 0.10762
    upper: float = 3.7568
    coverage: float = 0.9
    fitted_on: str = ("lap0-L+lap0-N+lap0-R+phantom0-L+phantom0-N+phantom0-R; "
                      "band also on tool0-b+tool0-d+tool0-e+tool0-f+tool0-h")

    def predict(self, d, sigma, m=0.0) -> np.ndarray:
        """ê (mm) from d, σ (mm, same shapes) and m (mm, scalar: median d over the mesh nodes)."""
        d = np.asarray(d)
        return self.a + self.b * d + self.c * np.asarray(sigma) + self.e * d * m


DEFAULT_CALIBRATION = Calibration()


@dataclass
class ErrorEstimate:
    """Predicted registration error at P points (the mesh nodes unless other points were asked for).

    All lengths in mm; positions in the data (tracker) frame.
    """
    predicted_mm: np.ndarray  # (P,) ê
    lower_mm: np.ndarray  # (P,) band
    upper_mm: np.ndarray  # (P,)
    distance_mm: np.ndarray  # (P,) d: registered position → nearest data point
    # (P,) σ: LM covariance propagated to the point; with a declared pose, α's alone given the pose
    sigma_mm: np.ndarray
    spread_mm: float  # m: median over the mesh nodes of their distance to the data
    positions: np.ndarray  # (P, 3) registered positions, tracker frame
    calibration: Calibration = field(default_factory=Calibration)
    noise_scale: float = 0.0  # s, the reduced χ² scaling H⁻¹ (dimensionless, Ω's units)
    # (P,) σ_pose: the RMS displacement at each point under the pose's own posterior (``pose_error``),
    # already joined into ``predicted_mm`` and ``upper_mm``
    pose_sigma_mm: np.ndarray | None = None


@dataclass
class Information:
    """The LM normal matrix at a solution, split by data feature so that a new plane's
    points can be added with the feature weights renormalised (w_F / N_F, eq. 7).

    blocks: feature → (p, p) Σ_rows w_i J_iᵀ J_i with its current count ``counts[feature]``;
    prior: the strain-energy part (JᵀWJ of f_E plus the curvature term), (p, p).
    """
    blocks: dict
    counts: dict
    prior: np.ndarray
    scale: float  # s = Ω / (R − p)
    beta: np.ndarray
    energy_weight: float = 0.0  # w_E of Ω's energy term (Pa⁻²), for ``energy_spread``
    # s with each data feature's mean square replaced by its robust variance, (1.4826 × median
    # |f|)², the reading the declared prior's σ_F already takes (``pipeline._robust_sd``)
    robust_scale: float | None = None

    def matrix(self, extra: dict | None = None) -> np.ndarray:
        """H with ``extra`` (feature → (n_new, (p, p) unnormalised Σ J_iᵀ J_i · w_F·unit²))
        joined: every feature's rows are reweighted by N_F / (N_F + n_new)."""
        H = self.prior.copy()
        extra = extra or {}
        # in a fixed order (the blocks', then the new features'): a set's order follows the process's
        # string hashes, and H summed in it differed in the last bits from one run to the next
        for name in dict.fromkeys([*self.blocks, *extra]):
            N = self.counts.get(name, 0)
            n_new, raw = extra.get(name, (0, None))
            if name in self.blocks:
                H += self.blocks[name] * (N / (N + n_new))
            if raw is not None and n_new:
                H += raw / (N + n_new)
        return H


MAD_SD = 1.4826
"""The normal's standard deviation over its median absolute value: a robust σ from residuals."""


def default_weights() -> Weights:
    """The weights ``pipeline.register`` fits with by default (Huber δ = 1 mm on the salient features)."""
    return Weights(huber_mm={n: 1.0 for n in SALIENT})


def information(model: RegistrationModel, data: dict, beta, weights: Weights | None = None) -> Information:
    """Per-feature normal matrices at β (data in the model frame, feature → (N, 3) mm)."""
    weights = weights or default_weights()
    beta = np.asarray(beta, float)
    n = len(beta) - 6
    ev = evaluate(model, data, beta, weights, jacobian=True)
    blocks, counts, start = {}, {}, 0
    squares = robust = 0.0  # the data rows' Σ w f², and the same with each feature's f² read robustly
    for name, _feat, _S, q, _rows, _local in ev.terms:
        rows = slice(start, start + len(q))
        J, w = ev.jacobian[rows], ev.w[rows]
        blocks[name] = (J.T * w) @ J
        counts[name] = len(data[name])
        start += len(q)
        f = ev.f[rows]
        if len(f):
            squares += float(np.sum(w * f ** 2))
            robust += float(np.sum(w)) * (MAD_SD * float(np.median(np.abs(f)))) ** 2
    JE, wE, fE = ev.jacobian[-1], ev.w[-1], ev.f[-1]
    prior = wE * np.outer(JE, JE)
    prior[:n, :n] += wE * fE * model.basis.energy / model.basis.M
    # the pose prior's rows (``prior``) are no data: Σ_β here is the data's (the prior's share of
    # the error estimate is ``pose_error``)
    dof = max(len(ev.f) - 1 - (6 if ev.pose_prior is not None else 0) - len(beta), 1)
    return Information(blocks, counts, prior, float(ev.omega / dof), beta, float(wE),
                       float(max(ev.omega - squares + robust, 0.0) / dof))


SPREAD_ROUNDS = 50  # most fixed-point rounds of ``energy_spread`` (it settles in 4–8)
SPREAD_TOL = 1e-3  # relative change of tr(Ê Σ_αα) at which it has settled


def energy_spread(model: RegistrationModel, info: Information) -> np.ndarray:
    """The strain energy's curvature over its own posterior spread, beyond the Laplace one (p, p).

    Ω's energy term w_E f_E², f_E = ½ αᵀ Ê α (Ê = energy / M), is quartic in α: its Laplace
    curvature at the fit, w_E (Ê α αᵀ Ê + f_E Ê) (``information``), vanishes with the
    deformation, and where the data do not reach σ is held by nothing. The Gaussian q = N(α, Σ)
    closest to the posterior (variational, KL(q‖p)) has Σ⁻¹ = E_q[∇²(−log p)]: the energy's
    curvature averaged over α ~ q, exactly (its Hessian is a polynomial in α):

        E_q[½∇²(w_E f_E²)] = w_E (Ê (α αᵀ + Σ_αα) Ê + (f_E + ½ tr(Ê Σ_αα)) Ê),

    Σ_αα the α block of s H⁻¹ with H = the data's blocks + that curvature: a fixed point. It
    starts from above, the prior alone without its Ê Σ Ê part (t = ½ tr(Ê Σ_αα) = sqrt(s n / 2 w_E),
    n the rank of Ê), and each round averages the curvature with the last (the map Σ → Σ is
    decreasing, so plain rounds oscillate). Returns the curvature beyond the Laplace one, to add
    to ``info.matrix()``: w_E (Ê Σ_αα Ê + ½ tr(Ê Σ_αα) Ê). Without data it is the quartic prior's
    own spread, finite; where the data fix α it is a small part of H."""
    basis = model.basis
    n = basis.Ju.shape[1]
    p = len(info.beta)
    E = basis.energy / basis.M
    wE = info.energy_weight
    out = np.zeros((p, p))
    if wE <= 0.0 or not np.isfinite(info.scale) or info.scale <= 0.0:
        return out
    rank = int(np.sum(np.linalg.eigvalsh(E) > 1e-10 * max(float(np.abs(E).max()), 1e-300)))
    t = float(np.sqrt(info.scale * rank / (2.0 * wE)))
    extra = wE * t * E
    H0 = info.matrix()
    for _ in range(SPREAD_ROUNDS):
        out[:n, :n] = extra
        S = covariance(info, H0 + out)[:n, :n]
        new = wE * (E @ S @ E + 0.5 * float(np.trace(E @ S)) * E)
        t_new = 0.5 * float(np.trace(E @ S))
        extra = 0.5 * (extra + new)
        if abs(t_new - t) <= SPREAD_TOL * max(t, 1e-300):
            break
        t = t_new
    out[:n, :n] = extra
    return out


def point_jacobian(model: RegistrationModel, beta, B=None, nodes=None) -> tuple[np.ndarray, np.ndarray]:
    """x(β) of eq. 8 and G = ∂x/∂β at points, in the model frame.

    Parameters
    ----------
    B : sparse (P, M), optional
        interpolation matrix of the points (``geometry.interpolation``); None: mesh nodes.
    nodes : (P,) int, optional
        which mesh nodes (without ``B``); None: all of them.

    Returns
    -------
    x : (P, 3) mm
    G : (P, 3, 3k + 6) mm per unit of β (α, τ, θ)
    """
    basis = model.basis
    beta = np.asarray(beta, float)
    n = len(beta) - 6
    if B is not None:
        modes, rest = basis.modes_at(B), np.asarray(B @ basis.nodes)
    else:
        idx = slice(None) if nodes is None else np.asarray(nodes)
        modes, rest = basis.Ju.reshape(basis.M, 3, n)[idx], basis.nodes[idx]
    R = rotation(beta[n + 3:])
    local, x = deform(rest, (modes.reshape(-1, n) @ beta[:n]).reshape(-1, 3), beta, model.centroid)  # eq. 8
    G = np.empty((len(rest), 3, n + 6))
    G[:, :, :n] = np.einsum("ab,pbk->pak", R, modes)
    G[:, :, n:] = pose_columns(local, beta[n + 3:])
    return x, G


def pose_columns(local, theta) -> np.ndarray:
    """∂x/∂(τ, θ) (P, 3, 6) of eq. 8's rigid part x = R(θ) local + τ + c at points whose
    positions about the centroid c (before the rotation) are ``local`` (P, 3) mm: mm per mm
    and per radian."""
    dR = rotation_derivatives(np.asarray(theta, float))
    G = np.empty((len(local), 3, 6))
    G[:, :, :3] = np.eye(3)
    for j in range(3):
        G[:, :, 3 + j] = local @ dR[j].T
    return G


def covariance_factor(info: Information, H=None) -> np.ndarray:
    """L (p, r) with Σ_β = s · H⁻¹ = L Lᵀ. H is inverted on the directions it determines
    (eigenvalues above 1e-10 of the largest, after equilibration: α, τ, θ have very
    different scales); the free ones are combinations of a rigid mode of the basis and
    τ, θ that move no point of the organ (to first order), so they add nothing to σ."""
    H = info.matrix() if H is None else H
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    w, V = np.linalg.eigh(H / np.outer(d, d))
    keep = w > 1e-10 * w.max()
    return np.sqrt(info.scale) * (V[:, keep] / np.sqrt(w[keep])) / d[:, None]


def covariance(info: Information, H=None) -> np.ndarray:
    """Σ_β = s · H⁻¹ (p, p), as ``covariance_factor`` (pseudo-inverse on the free directions)."""
    L = covariance_factor(info, H)
    return L @ L.T


def point_sigma(G, cov=None, factor=None) -> np.ndarray:
    """σ (P,) mm: sqrt(tr(G Σ Gᵀ)) per point, G (P, 3, p); Σ given as ``cov`` (p, p) or as
    a factor L (p, r) with Σ = L Lᵀ (one eigen-decomposition fewer)."""
    if factor is None:
        w, V = np.linalg.eigh(cov)
        factor = V * np.sqrt(np.maximum(w, 0.0))
    GL = G.reshape(-1, G.shape[-1]) @ factor
    return np.sqrt(np.einsum("ij,ij->i", GL, GL).reshape(len(G), 3).sum(1))


def node_positions(model: RegistrationModel, beta) -> np.ndarray:
    """x(β) of eq. 8 at every mesh node (M, 3), model frame.

    J_u α on one BLAS thread: the product (3M × 3k, 60 MB at 18.5k nodes) is large enough for
    OpenBLAS to wake its second thread, which then spins for ~0.1 s after it (the library's
    thread timeout) on the core that the next registration's second thread needs: a fresh
    registration right after transforming points (a study's TRE, the viewer's display) ran its
    first stage with a core short (docs/decisions/speed.md, "The fresh registration's
    independent parts side by side"). ``pipeline.deform_points`` does the same."""
    beta = np.asarray(beta, float)
    n = len(beta) - 6
    with limit_threads(1):
        u = (model.basis.Ju @ beta[:n]).reshape(-1, 3)
    local = model.basis.nodes - model.centroid + u
    return apply_rigid(rotation(beta[n + 3:]), beta[n:n + 3], local) + model.centroid


def data_spread(model: RegistrationModel, beta, data: dict) -> float:
    """m (mm): the median over the mesh nodes of their distance to the nearest data point."""
    return float(np.median(nearest_data_distance(node_positions(model, beta), data)))


def nearest_data_distance(positions, data: dict) -> np.ndarray:
    """d (P,) mm from each position to the nearest point of any data feature (same frame)."""
    pts = [np.asarray(v, float) for v in data.values() if len(v)]
    if not pts:
        return np.full(len(positions), np.inf)
    return cKDTree(np.vstack(pts)).query(positions)[0]


POSE_BAND = float(np.sqrt(chi2.ppf(0.9, 3) / 3))
"""The 90 % quantile of the length of a 3-D normal vector over its RMS (1.44): the band's
upper edge allows this × σ_pose for the pose, as the calibrated band allows 90 % for the rest."""


def pose_covariance(model: RegistrationModel, data: dict, beta, weights: Weights,
                    feature_sd_mm: float = FEATURE_SD_MM) -> np.ndarray:
    """Σ_pose (6, 6): the posterior covariance of τ (mm) and θ (rad) at β, from the data's
    rows and the pose prior's (``weights.pose_prior``, if declared), with α held: H = J_poseᵀ W
    J_pose and Σ = s_P H⁻¹, s_P the scale at which Ω reads as a log-likelihood (``prior``:
    each data feature one observation of σ_F RMS). α is held because the modes can move the
    organ almost rigidly: the marginal would count that freedom twice, once here and once in
    σ; this is the question the rigid stage answers — how well data and prior fix the pose.
    σ_F is the prior's own (``PosePrior.feature_sd_mm``) when one is declared, else
    ``feature_sd_mm``. Directions the data and prior leave free get the organ's size in σ
    (``FREE_POSE_MM``)."""
    n = len(beta) - 6
    ev = evaluate(model, data, np.asarray(beta, float), weights, jacobian=True)
    J = ev.jacobian[:, n:]
    H = (J.T * ev.w) @ J
    prior = weights.pose_prior
    s = prior.scale(weights.unit_m) if prior is not None else likelihood_scale(weights.unit_m, feature_sd_mm)
    # τ in mm and θ in rad: equilibrate before the pseudo-inverse (θ scaled by the organ's radius)
    radius = float(np.sqrt(np.mean(np.sum((model.basis.nodes - model.centroid) ** 2, axis=1))))
    D = np.concatenate([np.ones(3), np.full(3, radius)])
    Hs = H / np.outer(D, D)
    w, V = np.linalg.eigh(Hs)
    floor = s / FREE_POSE_MM ** 2  # a direction nothing fixes: σ of the organ's size
    cov = (V / np.maximum(w, floor)) @ V.T * s
    return cov / np.outer(D, D)


FREE_POSE_MM = 100.0
"""σ (mm) given to a pose direction that neither the data nor a prior fix: the organ's size,
not infinity, so that the band stays a number a surgeon reads as "do not navigate"."""


def estimate_error(reg, points=None, calibration: Calibration | None = None, B=None,
                   weights: Weights | None = None, nodes=None) -> ErrorEstimate:
    """Predicted registration error of a deformable registration, without the truth.

    Parameters
    ----------
    reg : pipeline.Registration
        a deformable registration (``reg.libr`` set); its ``data_model_frame`` is the data.
    points : (P, 3) preoperative points, optional
        where to predict (e.g. targets); None: every mesh node (``reg.model.basis.nodes``),
        whose surface subset (``basis.surface``) colours the liver.
    B : sparse (P, M), optional
        the points' interpolation matrix, when already computed.
    nodes : (P,) int, optional
        mesh-node indices instead of all nodes (without ``points``), e.g. ``basis.surface``
        for a colour map of the liver surface: σ costs time in proportion to the points.

    Returns
    -------
    ErrorEstimate with (P,) arrays in mm and positions in the tracker frame.
    """
    if reg.libr is None:
        raise ValueError("the error estimate needs a deformable registration (reg.libr is None)")
    calibration = calibration or DEFAULT_CALIBRATION
    model, data = reg.model, reg.data_model_frame
    if points is not None and B is None:
        B = interpolation_matrix(model.basis.nodes, model.basis.tets, np.asarray(points, float))
    with limit_threads(1):  # small matrices: threaded BLAS only synchronises (see libr.py)
        info = information(model, data, reg.libr.beta, weights)
        x, G = point_jacobian(model, reg.libr.beta, B, nodes=None if B is not None else nodes)
        # the pose's own uncertainty, where a pose is declared: the calibrated ê was fitted on
        # answers whose pose was right, so it leaves out how far the declared pose may be off.
        # Undeclared it is not joined: on a smooth cap the data leave turns free, and σ_pose put a
        # right answer's predicted error over the organ at 21 mm (docs/decisions/registration.md, "Pose prior")
        pose_sigma = np.zeros(len(x))
        # the strain energy over its own posterior spread, not its Laplace curvature alone, which
        # vanishes with the deformation and left σ far from a partial scan held by nothing
        if reg.pose_prior is not None and info.robust_scale is not None:
            # declared: the noise read as the declared prior reads it (its σ_F, ``_settle_scale``),
            # robustly, so that a dent the basis cannot make — a misfit under a few of the points,
            # not noise — does not scale σ over the whole organ. s from the mean square put ê at 3–6 ×
            # the true error there (tooldraw3_1-g at S: ê 16.6 mm, true 3.0). The lesser of the
            # two: a misfit only adds to the mean square, and where the robust reading is the larger
            # the residuals have no tail to discount (docs/decisions/error-estimate.md, "The residual scale read
            # robustly in the declared error estimate")
            info = replace(info, scale=min(info.scale, info.robust_scale))
        H = info.matrix() + energy_spread(model, info)
        if reg.pose_prior is None:
            sigma = point_sigma(G, factor=covariance_factor(info, H))
        else:
            # declared: the pose is counted once, by its posterior (data and prior, σ_pose below);
            # the calibrated term takes the deformation's σ given the pose (α's block of H). The
            # data-only σ of every β also carried the τ, θ a partial scan leaves weakly fixed,
            # unbounded by the prior and then × c: tooldraw3_0-a at S, σ 5.99 → 4.41 mm given the
            # pose (docs/decisions/error-estimate.md, "The declared pose counted once in the error estimate")
            n = G.shape[-1] - 6
            sigma = point_sigma(G[:, :, :n], factor=covariance_factor(info, H[:n, :n]))
            w = weights or default_weights()
            if w.pose_prior is None:
                w = replace(w, pose_prior=reg.pose_prior)
            cov = pose_covariance(model, data, reg.libr.beta, w)
            pose_sigma = point_sigma(G[:, :, -6:], cov=cov)
    d = nearest_data_distance(x, data)
    m = float(np.median(d)) if B is None and nodes is None else data_spread(model, reg.libr.beta, data)
    base = calibration.predict(d, sigma, m)
    pred, upper = base, base * calibration.upper
    if reg.pose_prior is not None:
        pred = np.sqrt(base ** 2 + pose_sigma ** 2)
        upper = np.sqrt(upper ** 2 + (POSE_BAND * pose_sigma) ** 2)
    return ErrorEstimate(pred, base * calibration.lower, upper, d, sigma, m, reg.rigid.apply(x),
                         calibration, info.scale, pose_sigma)


def surface_estimate(reg, vertices, calibration: Calibration | None = None) -> ErrorEstimate:
    """The estimate on a display surface, e.g. the preoperative liver mesh's vertices
    (V, 3): computed at the mesh's surface nodes (``basis.surface``, a few thousand, so
    interactive) and carried to each vertex from its nearest surface node (rest positions;
    the node map is cached in ``reg.model.cache``). Arrays (V,); ``positions`` are the
    surface nodes' registered positions carried the same way."""
    model = reg.model
    vertices = np.asarray(vertices, float)
    key = (vertices.shape, float(vertices.sum()))
    near = model.cache.surface_map.get(key)
    if near is None:
        near = cKDTree(model.basis.nodes[model.basis.surface]).query(vertices)[1]
        model.cache.surface_map = {**model.cache.surface_map, key: near}
    est = estimate_error(reg, calibration=calibration, nodes=model.basis.surface)
    return ErrorEstimate(est.predicted_mm[near], est.lower_mm[near], est.upper_mm[near], est.distance_mm[near],
                         est.sigma_mm[near], est.spread_mm, est.positions[near], est.calibration, est.noise_scale,
                         None if est.pose_sigma_mm is None else est.pose_sigma_mm[near])


ONCOLOGICAL_MARGIN_MM = 10.0
"""The recommended oncological margin (mm): the paper's clinical goal for accuracy, 5 mm, is
half of it (§IV). An answer whose predicted error over the organ exceeds it cannot place a
resection margin, whatever else its checks say (``OrganError``)."""


CLINICAL_GOAL_MM = ONCOLOGICAL_MARGIN_MM / 2
"""The paper's clinical goal for accuracy (§IV, 5 mm): a rigid answer with a declared pose whose
predicted error over the organ exceeds it is warned about (``PoseEvidence``),
as is a declared deformable one whose pose alone is predicted beyond it (``OrganError.pose_mm``)."""


@dataclass(frozen=True)
class OrganError:
    """The answer's predicted error over the organ: the mean of ê over ``nodes`` sampled mesh
    nodes (``organ_nodes``), mm, against ``bound_mm``; ``warning`` is one line when it exceeds it.

    With a declared pose, ``pose_mm`` is the mean over the same nodes of σ_pose, the part of ê
    that is the pose's own posterior (data and the declared prior): beyond ``pose_bound_mm``, the
    paper's clinical goal, the data do not fix the pose well enough to navigate by, whatever the
    deformation — the rule ``PoseEvidence`` applies to a declared rigid answer, here for a
    deformable one (docs/decisions/error-estimate.md, "The declared pose counted once in the error estimate")."""
    mean_mm: float
    nodes: int
    bound_mm: float = ONCOLOGICAL_MARGIN_MM
    seconds: float = 0.0
    pose_mm: float | None = None
    pose_bound_mm: float = CLINICAL_GOAL_MM

    @property
    def warning(self) -> str | None:
        if self.mean_mm > self.bound_mm:
            return (f"the data do not determine this answer: its predicted error over the organ is "
                    f"{self.mean_mm:.0f} mm (mean), more than the {self.bound_mm:g} mm oncological margin — do not "
                    "navigate by it; add data away from where they were collected")
        if self.pose_mm is not None and self.pose_mm > self.pose_bound_mm:
            return (f"the pose is not determined: the declared pose and the data leave a predicted error over the "
                    f"organ of {self.pose_mm:.1f} mm (mean) from the pose alone, more than the "
                    f"{self.pose_bound_mm:g} mm clinical goal (the whole answer: {self.mean_mm:.1f} mm) — check the "
                    "pose; add data away from where they were collected")
        return None

    def as_dict(self) -> dict:
        return {"mean_mm": round(self.mean_mm, 2), "bound_mm": self.bound_mm, "nodes": self.nodes,
                "seconds": round(self.seconds, 3), "exceeds_bound": self.mean_mm > self.bound_mm,
                **({} if self.pose_mm is None else {"pose_mm": round(self.pose_mm, 2),
                                                    "pose_bound_mm": self.pose_bound_mm})}


@dataclass(frozen=True)
class PoseEvidence:
    """With a declared pose and no supported deformation: is the rigid fit within the prior told
    apart from the given pose, and how good is the pose shown? All means over ``organ_nodes``, mm.

    ``moved_mm``: how far the rigid fit moved the organ from the given pose; ``sigma_mm``: that
    fit's posterior σ_pose (data and prior, ``pose_covariance``) at the rigid stage's robust
    scale (declared wider than the goal: at the deformable answer's settled scale, where the
    rigid fit is refitted, ``pipeline._rigid_at_settled_scale``); ``prior_sigma_mm``: the
    prior's alone (the given pose's own predicted error);
    ``misfit_sigma_mm``: the same posterior σ_pose with the data read at the mean square of the
    rigid fit's own residuals (``misfit_sd_mm``, the likelihood's usual scale estimate, floored
    at the robust one), None when it was not computed.

    One criterion, the posterior's: a move within its own σ is not told apart from the given
    pose, which is then kept (for data in the preoperative frame it is no correction, the answer
    never worse than its reference). The robust scale discounts the points a deformation moved,
    as it must for the fit (a dent must not set the pose); but a deformation the rigid fit cannot
    make is shared out by it as a pose error, and judged at the robust scale that move looks
    like evidence (on 5 of the 16 fitted poses of the declared local-load sets the fitted pose
    was worse than the given one, none told apart by it). So where the given pose is within
    ``bound_mm`` (the clinical goal) — the surgeon's own reference to navigate by — the move is
    judged at the scale of the misfit the rigid model leaves: a move within that σ is not told
    from the misfit and the given pose is kept; a larger one (data the rigid model fits to their
    noise, the misfit small) is the data's, and the fitted pose is shown without a line
    (docs/decisions/registration.md, "A declared rigid move judged at the
    scale of the misfit it leaves"). Declared wider than the goal, the given pose is
    no answer to navigate by: a rigid move beyond its robust σ is shown, and said (the surgeon
    should check it against the given pose). Any answer whose predicted error is beyond the goal
    says so.
    """
    moved_mm: float
    sigma_mm: float
    prior_sigma_mm: float
    bound_mm: float = CLINICAL_GOAL_MM
    misfit_sigma_mm: float | None = None

    @property
    def given_within_goal(self) -> bool:
        """The given pose's own predicted error (the declared prior's) is within the goal."""
        return self.prior_sigma_mm <= self.bound_mm

    @property
    def judged_by_misfit(self) -> bool:
        """The move is judged at the rigid fit's misfit scale (within the goal, when computed)."""
        return self.given_within_goal and self.misfit_sigma_mm is not None

    @property
    def kept_given(self) -> bool:
        if self.judged_by_misfit:
            assert self.misfit_sigma_mm is not None
            return self.moved_mm <= max(self.sigma_mm, self.misfit_sigma_mm)
        return self.moved_mm <= self.sigma_mm

    @property
    def predicted_mm(self) -> float:
        """The shown pose's predicted error over the organ (mm)."""
        return self.prior_sigma_mm if self.kept_given else self.sigma_mm

    @property
    def warning(self) -> str | None:
        beyond = self.predicted_mm > self.bound_mm
        if not beyond and (self.kept_given or self.judged_by_misfit):
            return None
        error = (f"its predicted error over the organ is {self.predicted_mm:.1f} mm (mean), more than the "
                 f"{self.bound_mm:g} mm clinical goal" if beyond else
                 f"its predicted error over the organ is {self.predicted_mm:.1f} mm (mean)")
        if self.kept_given:
            return (f"the pose is not determined: the given pose is shown without deformation (the deformation "
                    f"is not supported by the data), and {error} — add data where the organ moved and away "
                    "from the data")
        return (f"the data moved the organ {self.moved_mm:.1f} mm from the given pose (more than that "
                f"move's own σ, {self.sigma_mm:.1f} mm) and do not support a deformation: that rigid pose is "
                f"shown without deformation, {error} — check it against the given pose; add data where the "
                "organ moved")

    def as_dict(self) -> dict:
        return {"moved_mm": round(self.moved_mm, 3), "sigma_mm": round(self.sigma_mm, 3),
                "prior_sigma_mm": round(self.prior_sigma_mm, 3), "kept_given": self.kept_given,
                "predicted_mm": round(self.predicted_mm, 3), "bound_mm": self.bound_mm,
                **({} if self.misfit_sigma_mm is None else {"misfit_sigma_mm": round(self.misfit_sigma_mm, 3)})}


def misfit_sd_mm(model: RegistrationModel, data: dict, weights: Weights) -> float:
    """The root mean square (mm) of the data's residual rows (``weights`` without the prior: the
    rows ``pipeline._robust_sd`` reads) at the undeformed model in the frame of ``data``: the
    usual estimate of the likelihood's scale, which counts the misfit a deformation leaves where
    the robust one (1.4826 × their median absolute value) discounts it."""
    n = model.basis.Ju.shape[1]
    ev = evaluate(model, data, np.zeros(n + 6), replace(weights, pose_prior=None), jacobian=False)
    f = ev.f[:-1]  # the last row is the strain energy's
    return float(np.sqrt(np.mean(f ** 2))) if len(f) else 0.0


def pose_evidence(model: RegistrationModel, data: dict, pose, prior, weights: Weights) -> PoseEvidence:
    """``PoseEvidence`` of the rigid fit ``pose`` (``RigidResult``, model → data frame; the given
    pose is the identity) within ``prior`` (``PosePrior`` centred, as the rigid stage left it, on
    where the given pose is from ``pose``, at the rigid stage's scale). ``data``: feature → (N, 3)
    mm in the model frame of ``pose`` (``pose.inverse`` of the tracker's). Its
    ``misfit_sigma_mm`` is the posterior σ_pose with ``prior``'s scale σ_F raised to
    ``misfit_sd_mm`` where that is larger."""
    nodes = organ_nodes(model)
    x = model.basis.nodes[nodes]
    zero = np.zeros(model.basis.Ju.shape[1] + 6)
    misfit = replace(prior, feature_sd_mm=max(prior.feature_sd_mm, misfit_sd_mm(model, data, weights)))
    with limit_threads(1):
        _, G = point_jacobian(model, zero, nodes=nodes)
        w = replace(weights, pose_prior=prior)
        sigma = point_sigma(G[:, :, -6:], cov=pose_covariance(model, data, zero, w))
        prior_sigma = point_sigma(G[:, :, -6:], cov=pose_covariance(model, {}, zero, w))
        misfit_sigma = point_sigma(G[:, :, -6:], cov=pose_covariance(model, data, zero, replace(w, pose_prior=misfit)))
    moved = np.linalg.norm(pose.apply(x) - x, axis=1)
    return PoseEvidence(float(moved.mean()), float(sigma.mean()), float(prior_sigma.mean()),
                        misfit_sigma_mm=float(misfit_sigma.mean()))


def declared_spread(model: RegistrationModel, weights: Weights) -> float:
    """The declared pose's own predicted error over the organ, before any data.

    Parameters
    ----------
    model : RegistrationModel
    weights : Weights
        with ``pose_prior`` set (the declared σ_τ, σ_θ; its centre and scale do not enter).

    Returns
    -------
    float
        mm: the mean over ``organ_nodes`` of σ_pose = sqrt(tr(G_pose Σ_P G_poseᵀ)), Σ_P the
        prior's covariance alone (``pose_covariance`` without data) — ``PoseEvidence``'s
        ``prior_sigma_mm`` before any fit. Against ``CLINICAL_GOAL_MM``: whether the given pose,
        as declared, is good enough to navigate by.
    """
    assert weights.pose_prior is not None
    nodes = organ_nodes(model)
    zero = np.zeros(model.basis.Ju.shape[1] + 6)
    with limit_threads(1):
        _, G = point_jacobian(model, zero, nodes=nodes)
        return float(point_sigma(G[:, :, -6:], cov=pose_covariance(model, {}, zero, weights)).mean())


ORGAN_NODES = 1500
"""Mesh nodes (a fixed random sample, ``organ_nodes``) over which "the predicted error over the
organ" is a mean: in ``OrganError`` and in the next plane's ranking (σ costs time per node)."""


def organ_nodes(model: RegistrationModel, count: int = ORGAN_NODES, seed: int = 0) -> np.ndarray:
    """(n,) sorted mesh-node indices, ``count`` of them drawn with ``seed`` (all nodes when fewer)."""
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(model.basis.M, min(count, model.basis.M), replace=False))


def organ_error(reg, calibration: Calibration | None = None, weights: Weights | None = None) -> OrganError:
    """``OrganError`` of a deformable registration (``reg.libr`` set): the mean of ê
    (``estimate_error``) over ``organ_nodes``. ``weights``: the ones the fit used (its robust
    factors: a spike the fit rejected otherwise sets the residual scale — 17 mm predicted over
    the organ beside a true 5.0 mm with one stray vertex on the test scene)."""
    t0 = time.perf_counter()
    nodes = organ_nodes(reg.model)
    est = estimate_error(reg, calibration=calibration, nodes=nodes, weights=weights)
    pose = float(est.pose_sigma_mm.mean()) if reg.pose_prior is not None and est.pose_sigma_mm is not None else None
    return OrganError(float(est.predicted_mm.mean()), len(nodes), seconds=time.perf_counter() - t0, pose_mm=pose)

"""Salient-feature weighted rigid ICP (the rigid initialisation of §II-D).

Point-to-point ICP between the digitised surface data (stylus: anterior, falciform, ridges;
and fiducials) and the model surface (as docs/design.md §1 says; iUS contours and iUS posterior
points join only in the deformable stage: the contours pulled the pose toward the wrong
branches and the posterior points lowered the success rate — docs/decisions/registration.md, "Measured
choices moved out of docstrings"; ``features`` can add them). Each
feature finds closest points on its own model feature only (falciform to the falciform
region, ridges to their ridges), and every point carries its feature's objective weight
w_F / N_F, so a salient feature with few points still steers the fit. Without any surface
data, every feature takes part. The update is the
weighted Kabsch solution. Fiducials, when present, first give a closed-form start.

``multi_start_icp`` runs ICP from several starting poses at once — the tracker
pose, ±15° about each axis through the data centroid, and a principal-axes alignment —
point-to-plane or point-to-point on the model's vertices, and returns the distinct poses
it converged to; the pipeline picks among them by the LIBR objective.
"""

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..features import RIGID, SALIENT
from ..geometry.transforms import apply_inverse, apply_rigid, kabsch, rotvec_matrix
from .model import RegistrationModel
from .objective import Weights, correspond
from .rotation import rotation, rotation_angle


@dataclass
class RigidResult:
    """A rigid pose T(x) = R x + t from the model (preoperative) frame to the data (tracker)
    frame, mm; ``apply`` maps (P, 3) points by T, ``inverse`` by T⁻¹."""

    R: np.ndarray  # (3, 3): model frame → data frame
    t: np.ndarray  # (3,)
    iterations: int
    rms_mm: float
    # a pose the data fix without ICP — the given (tracker) pose, or the trimmed fit from it
    # (``pose.choose_pose``): the deformable fit then keeps it (τ, θ fixed), warm
    # re-registrations included, and falls back to it when the deformation is not supported
    kept: bool = False

    def apply(self, x):
        return apply_rigid(self.R, self.t, x)

    def inverse(self, y):
        return apply_inverse(self.R, self.t, y)


def after(first: RigidResult, then: RigidResult) -> RigidResult:
    """The pose ``first`` ∘ ``then`` (x ↦ first(then(x))), with ``then``'s iterations, RMS and
    ``kept`` (distances are the same in either frame)."""
    return replace(then, R=first.R @ then.R, t=first.R @ then.t + first.t)


def beta_pose(beta, centroid) -> RigidResult:
    """The rigid part of a LIBR state β = (α, τ, θ) (3k + 6,): x ↦ R(θ) (x − x̄0) + τ + x̄0, eq. 8
    without the displacement; ``centroid`` x̄0 (3,) mm. A registration's whole pose is
    ``after(reg.rigid, beta_pose(β, x̄0))``."""
    beta = np.asarray(beta, float)
    n = len(beta) - 6
    R = rotation(beta[n + 3:])
    c = np.asarray(centroid, float)
    return RigidResult(R, c + beta[n:n + 3] - R @ c, 0, 0.0, kept=True)


def pose_params(pose: RigidResult, centroid) -> np.ndarray:
    """τ, θ (6,) (mm, rad) of ``pose`` as eq. 8's rigid part about ``centroid`` x̄0 (3,) mm:
    ``beta_pose``'s inverse. R (x − x̄0) + τ + x̄0 = R x + t gives τ = t − x̄0 + R x̄0; θ is R's
    intrinsic XYZ angles (R = R_x R_y R_z, ``rotation``)."""
    c = np.asarray(centroid, float)
    return np.concatenate([pose.t - c + pose.R @ c, Rotation.from_matrix(pose.R).as_euler("XYZ")])


ICP_POINTS = 400  # per feature: an evenly strided subset is plenty for 6 parameters
TOL_BEFORE_LIBR = 1e-2  # mm: ICP only initialises LIBR
# Huber factors on falciform and ridge points with δ = this × the feature's median residual
# (``_robust_scale``); None: plain weighted ICP (the path before). On the study grid a
# mislabelled stretch of a ridge had pulled the pose 1.3 mm further off (rigid TRE 10.1
# against 8.8 mm) and LIBR never recovered: see docs/decisions/registration.md, "Registration: robust
# initialisation and fit quality"
RIGID_ROBUST = 2.0


def rigid_icp(model: RegistrationModel, data: dict, weights: Weights | None = None, max_iterations=100,
              tol_mm=1e-4, start: "RigidResult | None" = None, features=RIGID,
              multi_start=True, robust: float | None = RIGID_ROBUST) -> RigidResult:
    """Rigid transform taking the model onto ``data`` (feature → (N, 3) mm).

    Each feature is thinned to at most ICP_POINTS points by an even stride (its weight
    w_F / N_F is per point of the subset, so every feature keeps its total weight w_F).
    Stops when the weighted RMS changes by less than ``tol_mm``; the pipeline passes
    ``TOL_BEFORE_LIBR`` when LIBR follows (it refines the rigid pose anyway: β carries τ, θ;
    what that saves and costs: docs/decisions/registration.md). ``start``: the pose
    to begin from; without one, ``multi_start`` begins from the lowest-RMS pose the
    multi-start ICP reaches (``multi_start_icp``; the registration pipeline instead picks
    among those poses by the LIBR objective and passes its choice as ``start``), and
    ``multi_start=False`` from the identity, i.e. the tracker's pose (one ICP, as
    ``RobustOptions.single_icp``). Fiducials (≥ 3) give a closed-form start instead. ``features``: the data
    features that take part when present (``posterior`` can be added).
    """
    weights = weights or Weights()
    R, t = (np.eye(3), np.zeros(3)) if start is None else (start.R, start.t)
    surface = {k: v for k, v in data.items() if k in features}
    data = surface or data
    if not data:
        return RigidResult(R, t, 0, 0.0)
    if "fiducials" in data and len(data["fiducials"]) >= 3 and start is None:
        P = model.features["fiducials"].rest
        R, t = kabsch(P, data["fiducials"], np.ones(len(P)))
    elif start is None and multi_start:
        # the same points and starts as the pipeline's, so the same poses
        best = basin_representatives(multi_start_icp(model, data, start_poses(model, data), weights,
                                                     features=features, robust=robust))[0]
        R, t = best.fitted.R, best.fitted.t
    data = {k: (v[:: -(-len(v) // ICP_POINTS)] if k != "fiducials" else v) for k, v in data.items()}
    prev = np.inf
    rms = 0.0
    it = 0
    trees = {name: cKDTree(model.feature_for(name).rest) for name in data if name != "fiducials"}
    for it in range(1, max_iterations + 1):  # noqa: B007 (``it`` is the count returned)
        Ps, Qs, Ws = [], [], []
        for name, Y in data.items():
            feat = model.feature_for(name)
            Ym = apply_inverse(R, t, Y)  # data in the model frame
            S = correspond(feat, feat.rest, Ym, trees.get(name)).S
            Ps.append(S @ feat.rest)
            Qs.append(Y)
            Ws.append(np.full(len(Y), weights.features[name] / len(Y)))
            if robust and name in SALIENT:
                Ws[-1] = Ws[-1] * _robust_scale(np.linalg.norm(Ym - Ps[-1], axis=-1), robust)
        P, Q, W = np.vstack(Ps), np.vstack(Qs), np.concatenate(Ws)
        R, t = kabsch(P, Q, W)
        rms = float(np.sqrt(np.average(np.sum((apply_rigid(R, t, P) - Q) ** 2, 1), weights=W)))
        if abs(prev - rms) < tol_mm:
            break
        prev = rms
    return RigidResult(R, t, it, rms)


def _robust_scale(dist, k: float) -> np.ndarray:
    """Huber factors with a scale-adaptive δ = k × the feature's median residual (per start,
    along the last axis): a few salient points far beyond the rest of their feature — a
    mislabelled stretch — pull linearly, not quadratically. At the rigid stage every
    residual still carries the organ's deformation, so a fixed δ would not do."""
    delta = k * np.median(dist, axis=-1, keepdims=True) + 1e-9
    return delta / np.maximum(dist, delta)


RIGID_WITH_POSTERIOR = RIGID + ("posterior",)
SCREEN_POINTS = 150  # per feature in the multi-start ICP: 8 starts × all features stay cheap


@dataclass
class Start:
    """One starting pose of the multi-start ICP and where it ended."""
    label: str  # "tracker", "rx+15", …, "principal-axes"
    R0: np.ndarray  # (3, 3) starting pose, model → data
    t0: np.ndarray  # (3,) mm
    result: RigidResult | None = None
    basin: int = -1  # index of the distinct pose it converged to
    omega: float | None = None  # LIBR Ω after the screening iterations, when screened
    chosen: bool = False

    @property
    def fitted(self) -> RigidResult:
        """Where the ICP from this start ended (set by ``multi_start_icp``)."""
        if self.result is None:
            raise ValueError(f"start {self.label!r} has not been run")
        return self.result


def _axis_rotation(axis: int, angle_rad: float) -> np.ndarray:
    theta = np.zeros(3)
    theta[axis] = angle_rad
    from .rotation import rotation

    return rotation(theta)


def _vertex_normals(feat) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) of a surface feature at rest."""
    X, F = feat.rest, feat.cells
    fn = np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]])  # |fn| = 2 × area
    vn = np.zeros_like(X)
    for j in range(3):
        np.add.at(vn, F[:, j], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def _screen_geometry(model: RegistrationModel, name: str):
    """(KD-tree, vertices, vertex normals) of a data feature's model feature, kept on the
    model: the multi-start ICP matches to vertices of the rest geometry, which never changes."""
    feat = model.feature_for(name)
    key = id(feat)
    hit = model.cache.screen.get(key)
    if hit is None:
        normals = _vertex_normals(feat) if feat.kind == "surface" else None
        hit = (cKDTree(feat.rest), feat.rest, normals)
        model.cache.screen = {**model.cache.screen, key: hit}
    return hit


def organ_radius(model: RegistrationModel) -> float:
    """The radius (mm) of the sphere about the model's centroid that holds the liver's surface:
    surface data placed with their centre outside it are not on the organ."""
    return float(np.linalg.norm(model.features["liver"].rest - model.centroid, axis=1).max())


def start_poses(model: RegistrationModel, data: dict, angle_deg=15.0, principal_axes=True) -> list[Start]:
    """The tracker pose, ±``angle_deg`` about each coordinate axis through the data
    centroid (the expected error of a tracker-to-image set-up), and a principal-axes
    alignment of the data with the model vertices they are nearest to."""
    starts = [Start("tracker", np.eye(3), np.zeros(3))]
    if not data:
        return starts
    pts = np.vstack(list(data.values()))
    c = pts.mean(0)
    for axis, name in enumerate("xyz"):
        for sign in (1, -1):
            Q = _axis_rotation(axis, sign * np.radians(angle_deg))
            starts.append(Start(f"r{name}{'+' if sign > 0 else '-'}{angle_deg:g}", Q, c - Q @ c))
    if principal_axes and len(pts) >= 4:
        # data centred outside the sphere around the organ (a tracker frame nothing aligned:
        # the hard case "far"): their nearest model vertices say nothing, so take those of
        # the data moved onto the model's centroid instead. Aligned study data centre
        # within 40 mm of it (radius 130–137 mm), so 40 mm offsets never get here
        shift = model.centroid - c if np.linalg.norm(c - model.centroid) > organ_radius(model) else np.zeros(3)
        near = []
        for name, Y in data.items():
            if name == "fiducials":
                near.append(model.features["fiducials"].rest)
                continue
            tree, X, _ = _screen_geometry(model, name)
            near.append(X[tree.query(Y + shift)[1]])
        P = np.vstack(near)
        cp = P.mean(0)
        _, _, Vd = np.linalg.svd(pts - c, full_matrices=False)
        _, _, Vp = np.linalg.svd(P - cp, full_matrices=False)
        # the axes' signs are arbitrary: of the four proper sign choices take the rotation
        # nearest the tracker pose (the set-up is known to within a few tens of degrees)
        best = (np.inf, np.eye(3))  # (angle from the tracker pose, rotation)
        for s in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
            Rm = Vp.T @ np.diag(s) @ Vd  # data axes → model axes
            if np.linalg.det(Rm) < 0:
                Rm = Vp.T @ np.diag(s) @ np.diag([1, 1, -1]) @ Vd
            angle = rotation_angle(Rm)
            if angle < best[0]:
                best = (angle, Rm)
        Rm = best[1]
        starts.append(Start("principal-axes", Rm.T, c - Rm.T @ cp))
    return starts


def multi_start_icp(model: RegistrationModel, data: dict, starts: list[Start], weights: Weights | None = None,
                    mode="plane", features=RIGID, max_iterations=30, tol_mm=1e-2,
                    points=SCREEN_POINTS, basin_mm=1.5, merge_mm=0.5,
                    robust: float | None = RIGID_ROBUST) -> list[Start]:
    """ICP from every start at once; fills each start's ``result`` and ``basin``.

    Parameters
    ----------
    data : dict
        feature → (N, 3) mm, tracker space.
    starts : list of Start
        starting poses (model → data).
    mode : {"plane", "point"}
        point-to-plane (residual nᵀ(y − x) with the model's vertex normal n: the data
        may slide along the surface, so a partial patch settles in a few iterations) or
        point-to-point. Fiducials are always point-to-point with their own counterparts.
    features : tuple of str
        data features that take part when present (``RIGID_WITH_POSTERIOR`` adds the iUS
        posterior-surface points).
    tol_mm : float
        stop a start once its step moves no data point by more than this (mm).
    basin_mm : float
        two final poses are one basin when they place the data within this mean distance.
    merge_mm : float
        a start whose pose comes within this of another's (same measure) stops and joins
        that start's basin: most starts meet the tracker start's path after a few steps.

    Each step is the weighted Gauss–Newton update of a small rotation ω and translation v
    of the data in the model frame (6 × 6 per start, all starts solved together); points
    match the nearest model *vertex* (4 mm mesh), which is what a start needs — LIBR then
    refines τ and θ against the exact surfaces.
    """
    weights = weights or Weights()
    use = {k: v for k, v in data.items() if k in features} or dict(data)
    use = {k: (v[:: -(-len(v) // points)] if k != "fiducials" else v) for k, v in use.items()}
    S = len(starts)
    R = np.stack([s.R0 for s in starts]).astype(float)
    t = np.stack([s.t0 for s in starts]).astype(float)
    if not use or S == 0:
        for s in starts:
            s.result, s.basin = RigidResult(s.R0, s.t0, 0, 0.0), 0
        return starts
    radius = max(float(np.linalg.norm(np.vstack(list(use.values())) - np.vstack(list(use.values())).mean(0),
                                      axis=1).max()), 1.0)
    probe = np.vstack(list(use.values()))
    centre, reach = probe.mean(0), organ_radius(model)
    active = np.ones(S, bool)
    merged = np.arange(S)  # a start that joined another's path follows that start's basin
    iters = np.zeros(S, int)
    rms = np.zeros(S)
    for _ in range(max_iterations):
        on = np.flatnonzero(active)
        Ra, ta, n_on = R[on], t[on], len(on)
        A = np.zeros((n_on, 6, 6))
        g = np.zeros((n_on, 6))
        sq = np.zeros(n_on)
        wsum = 0.0
        for name, Y in use.items():
            Ym = np.einsum("snk,skj->snj", Y[None] - ta[:, None], Ra)  # (S, N, 3) in the model frame
            wF = weights.features[name] / len(Y)
            if name == "fiducials":
                P = np.broadcast_to(model.features["fiducials"].rest, Ym.shape)
                normals = None
            else:
                tree, X, vn = _screen_geometry(model, name)
                idx = tree.query(Ym.reshape(-1, 3))[1].reshape(n_on, -1)
                P = X[idx]
                normals = vn[idx] if (mode == "plane" and vn is not None) else None
            d = Ym - P
            if normals is not None:
                rows = [(np.cross(Ym, normals), normals, -np.einsum("snj,snj->sn", normals, d))]
            else:  # point-to-point: one row per coordinate axis
                rows = []
                for k in range(3):
                    e = np.zeros(3)
                    e[k] = 1.0
                    rows.append((np.cross(Ym, e), np.broadcast_to(e, Ym.shape), -d[..., k]))
            wN = np.full(d.shape[:2], wF)
            if robust and name in SALIENT:
                size = np.abs(rows[0][2]) if normals is not None else np.linalg.norm(d, axis=-1)
                wN = wN * _robust_scale(size, robust)
            for a_rot, a_tr, b in rows:
                a = np.concatenate([a_rot, a_tr], axis=2)  # (S, N, 6): ∂r/∂(ω, v)
                A += np.einsum("sni,snj->sij", a * wN[..., None], a)
                g += np.einsum("sni,sn->si", a, wN * b)
                sq += np.einsum("sn,sn->s", wN * b, b)
            wsum += weights.features[name]
        rms[on] = np.sqrt(sq / wsum)
        # a little damping: a patch of data may leave a rotation weakly determined
        diag = np.einsum("sii->si", A)
        A_d = A + 1e-6 * np.maximum(diag, 1e-12 * diag.max())[:, :, None] * np.eye(6)
        x = np.linalg.solve(A_d, g[..., None])[..., 0]
        w, v = x[:, :3], x[:, 3:]
        move = np.linalg.norm(w, axis=1) * radius + np.linalg.norm(v, axis=1)
        # data in the model frame move as y_m ↦ Rd y_m + v, i.e. the pose (model → data)
        # becomes x ↦ R Rdᵀ (x − v) + t
        R_new = np.einsum("sij,skj->sik", Ra, rotvec_matrix(w))
        t_new = ta - np.einsum("sij,sj->si", R_new, v)
        # a step that carries the data's centre further out, beyond the organ's sphere, has left
        # the organ: undone, and the start stops there. Point-to-plane steps on a stroke of
        # stylus points slide along the few vertex normals the points match; iterated, a
        # start stood 10⁶ mm off and the searches after it read past their arrays
        # (docs/decisions/live.md, "A start that leaves the organ")
        out_before = np.linalg.norm(np.einsum("sk,skj->sj", centre - ta, Ra) - model.centroid, axis=1)
        out_after = np.linalg.norm(np.einsum("sk,skj->sj", centre - t_new, R_new) - model.centroid, axis=1)
        left = (out_after > reach) & (out_after > out_before)
        R[on] = np.where(left[:, None, None], Ra, R_new)
        t[on] = np.where(left[:, None], ta, t_new)
        iters[on] += ~left
        active[on] = (move >= tol_mm) & ~left
        # starts whose paths have met go on as one: the later one is dropped
        placed = np.einsum("snk,skj->snj", probe[None] - t[:, None], R)
        for i in np.flatnonzero(active):
            for j in range(S):
                if j != i and merged[j] == j and (j < i or not active[j]) and \
                        np.linalg.norm(placed[i] - placed[j], axis=1).mean() < merge_mm:
                    merged[i], active[i] = j, False
                    break
        if not active.any():
            break
    # one basin per cluster of final poses, compared by where they put the data
    placed = np.einsum("snk,skj->snj", probe[None] - t[:, None], R)
    reps: list[int] = []  # the lowest-RMS start of each basin
    roots = [int(r) for r in np.argsort(rms, kind="stable") if merged[r] == r]
    for r in roots:
        same = [b for b, j in enumerate(reps) if np.linalg.norm(placed[r] - placed[j], axis=1).mean() < basin_mm]
        starts[r].basin = same[0] if same else len(reps)
        if not same:
            reps.append(r)
    for k, s in enumerate(starts):
        root = k
        while merged[root] != root:
            root = int(merged[root])
        s.basin = starts[root].basin
        s.result = RigidResult(R[k].copy(), t[k].copy(), int(iters[k]), float(rms[k]))
    return starts


def basin_representatives(starts: list[Start]) -> list[Start]:
    """The lowest-RMS start of each basin, best first."""
    best: dict[int, Start] = {}
    for s in starts:
        if s.basin not in best or s.fitted.rms_mm < best[s.basin].fitted.rms_mm:
            best[s.basin] = s
    return sorted(best.values(), key=lambda s: s.fitted.rms_mm)

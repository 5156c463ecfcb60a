"""The next best ultrasound plane: the candidate probe pose whose plane would most lower the
predicted error (the paper's "future work").

Given a registration and its data, each candidate probe pose is scored by the drop in the
mean predicted error over the organ (``uncertainty``) that its plane would bring:

1. expected features: the registered model (its deformed portal and hepatic surfaces and
   the liver's far wall, as ``simulation.ultrasound`` images them) is cut by the
   candidate's image plane, clipped to the image, and sampled along the section;
2. those points join the data at zero residual: their closest-point Jacobian rows
   (objective.py, Table I) add to the LM normal matrix, with every feature's weight
   renormalised to w_F / N_F (eq. 7) as the registration itself would;
3. the predicted error ê = a + b·d + c·σ + e·d·m is recomputed at a fixed sample of mesh
   nodes with d shortened by the new points (m their median), σ from the new covariance;
4. score = mean(ê now − ê with the plane) in mm; candidates are returned best first.

Candidate poses: unless given, ``count`` contact points on the registered anterior
surface (k-means centres), each with a vertical and a lateral plane pointing into the
liver, in the same conventions as the simulator's probe (``simulation.probe``: columns of
the 4×4 pose are lateral, elevation (plane normal), depth, origin).
"""

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..defaults import FAR_WALL_COS, FAR_WALL_MIN_DEPTH_MM, PROBE_HEIGHT_PX, PROBE_SPACING_MM, PROBE_WIDTH_PX
from ..geometry.interpolation import interpolation_matrix
from ..geometry.planes import plane_section
from ..geometry.transforms import homogeneous, inverse, probe_pose
from ..threads import limit_threads
from .objective import evaluate
from .uncertainty import (
    DEFAULT_CALIBRATION,
    ORGAN_NODES,
    Calibration,
    Information,
    covariance_factor,
    default_weights,
    information,
    nearest_data_distance,
    organ_nodes,
    point_jacobian,
    point_sigma,
)

# the simulator's probe and far-wall rule (``navapp.defaults``: one home for both sides)
IMAGE_WIDTH_MM = PROBE_WIDTH_PX * PROBE_SPACING_MM
IMAGE_DEPTH_MM = PROBE_HEIGHT_PX * PROBE_SPACING_MM
SAMPLE_MM = 1.0  # Jacobian rows taken every 1 mm along a section, weighted as the pixels they stand for


@dataclass
class PlaneCandidate:
    """One candidate probe pose and what it is expected to show.

    pose: (4, 4) ProbeToTracker, tracker frame, mm (columns: lateral, normal, depth, origin);
    score_mm: expected drop of the mean predicted error where it is compared (``Suggestion.over``;
    mm, larger is better);
    features: data feature → (N, 3) expected points, tracker frame (sampled every 1 mm);
    pixels: data feature → expected number of image pixels (the weight the plane carries);
    predicted_mean_mm: mean predicted error with this plane added.
    """
    index: int
    orientation: str
    pose: np.ndarray
    score_mm: float
    features: dict
    pixels: dict
    predicted_mean_mm: float


@dataclass
class Suggestion:
    candidates: list  # PlaneCandidate, best first
    current_mean_mm: float  # mean predicted error now
    seconds: float
    over: str = "the whole organ (sampled mesh nodes)"  # where the predicted error is compared

    @property
    def best(self) -> PlaneCandidate:
        return self.candidates[0]


def anterior_surface_mask(model, preop) -> np.ndarray:
    """(S,) bool over the model's liver-surface points: labelled anterior in ``preop.regions``
    (nearest preoperative vertex); all True when the case has no labels."""
    liver = model.features["liver"]
    if preop is None or preop.regions is None:
        return np.ones(len(liver.rest), bool)
    key = (hash(np.asarray(preop.regions).tobytes()), len(preop.liver.vertices))
    mask = model.cache.anterior.get(key)
    if mask is None:
        _, near = cKDTree(np.asarray(preop.liver.vertices)).query(liver.rest)
        mask = np.asarray(preop.regions)[near] == 0
        model.cache.anterior = {**model.cache.anterior, key: mask}
    return mask


def _vertex_normals(X, faces):
    fn = np.cross(X[faces[:, 1]] - X[faces[:, 0]], X[faces[:, 2]] - X[faces[:, 0]])
    vn = np.zeros_like(X)
    for j in range(3):
        np.add.at(vn, faces[:, j], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def kmeans_centres(P, count, iterations=30) -> np.ndarray:
    """``count`` k-means centres of points P (N, 3), from a farthest-point start (deterministic).
    Written here rather than sklearn's KMeans: that took 1–5 s on this busy 2-core machine
    (its OpenMP threads contend) for what 30 Lloyd steps on ~2k points do in milliseconds."""
    count = min(count, len(P))
    idx = [int(np.argmin(np.linalg.norm(P - P.mean(0), axis=1)))]
    dist = np.linalg.norm(P - P[idx[0]], axis=1)
    for _ in range(count - 1):
        idx.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(P - P[idx[-1]], axis=1))
    C = P[idx].copy()
    for _ in range(iterations):
        lab = cKDTree(C).query(P)[1]
        new = np.array([P[lab == j].mean(0) if np.any(lab == j) else C[j] for j in range(count)])
        if np.allclose(new, C):
            break
        C = new
    return C


def candidate_poses(reg, anterior, count=8) -> list[tuple[str, np.ndarray]]:
    """2·``count`` probe poses on the registered anterior surface (tracker frame): k-means
    contact points, each with a vertical (lateral axis along z) and a lateral (along x) plane."""
    model = reg.model
    feat = model.features["liver"]
    _, X = model.positions(feat, reg.libr.beta)
    X = reg.rigid.apply(X)
    N = _vertex_normals(X, feat.cells)
    ant = np.flatnonzero(anterior)
    if len(ant) == 0:
        raise ValueError("no anterior surface to place the probe on (empty mask)")
    centres = kmeans_centres(X[ant], count)
    centres = centres[np.argsort(centres[:, 0])]
    out = []
    for orientation, lateral in (("vertical", np.array([0.0, 0.0, 1.0])), ("lateral", np.array([1.0, 0.0, 0.0]))):
        for c in centres:
            i = ant[np.argmin(np.linalg.norm(X[ant] - c, axis=1))]
            out.append((orientation, probe_pose(X[i], lateral, -N[i])))
    return out


def _clip(seg, origin, lateral, depth):
    """Segments (S, 2, 3) with both ends inside the image window."""
    rel = seg - origin
    u, v = rel @ lateral, rel @ depth
    ok = (np.abs(u) <= IMAGE_WIDTH_MM / 2) & (v >= 0) & (v <= IMAGE_DEPTH_MM)
    return seg[ok.all(1)]


def _sample(seg):
    """Points every ``SAMPLE_MM`` along segments, and the pixel count they stand for."""
    if len(seg) == 0:
        return np.zeros((0, 3)), 0
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    cum = np.concatenate([[0.0], np.cumsum(length)])
    s = np.arange(SAMPLE_MM / 2, cum[-1], SAMPLE_MM)
    if len(s) == 0:
        s = np.array([cum[-1] / 2])
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    t = ((s - cum[i]) / np.maximum(length[i], 1e-12))[:, None]
    return seg[i, 0] * (1 - t) + seg[i, 1] * t, round(cum[-1] / PROBE_SPACING_MM)


IMAGED = (("portal", "portal_contour"), ("hepatic", "hepatic_contour"), ("liver", "posterior"))


def deformed_surfaces(model, beta) -> dict:
    """Model feature → its points deformed by β (model frame), for the surfaces a plane images."""
    return {m: model.positions(model.features[m], beta)[1] for m, _ in IMAGED if m in model.features}


def expected_features(model, beta, pose_model, deformed=None) -> tuple[dict, dict]:
    """Points (model frame) the plane ``pose_model`` (4×4, model frame) would show on the
    model deformed by β: portal/hepatic contours and the liver's far wall. Returns
    (feature → (N, 3) points sampled every 1 mm, feature → expected pixel count).
    ``deformed``: ``deformed_surfaces(model, beta)`` when already computed."""
    origin, lateral, normal, depth = pose_model[:3, 3], pose_model[:3, 0], pose_model[:3, 1], pose_model[:3, 2]
    deformed = deformed_surfaces(model, beta) if deformed is None else deformed
    feats, pixels = {}, {}
    for model_name, data_name in IMAGED:
        if model_name not in deformed:
            continue
        feat, X = model.features[model_name], deformed[model_name]
        if model_name == "liver":
            seg, faces = plane_section(X, feat.cells, origin, normal, return_faces=True)
            tri = X[feat.cells[faces]]
            fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
            deep = np.einsum("sij,j->si", seg - origin, depth).min(1) > FAR_WALL_MIN_DEPTH_MM
            keep = (fn @ depth > FAR_WALL_COS) & deep
            seg = seg[keep]
        else:
            seg = plane_section(X, feat.cells, origin, normal)
        pts, npx = _sample(_clip(seg, origin, lateral, depth))
        if len(pts):
            feats[data_name], pixels[data_name] = pts, npx
    return feats, pixels


def _extra_blocks(model, beta, feats, pixels, weights) -> dict:
    """feature → (pixel count, unnormalised Σ w_F·unit² J_iᵀJ_i over the plane's pixels)."""
    if not feats:
        return {}
    ev = evaluate(model, feats, beta, weights, jacobian=True)
    out, start = {}, 0
    for name, _feat, _S, q, _rows, _local in ev.terms:
        rows = slice(start, start + len(q))
        J, w = ev.jacobian[rows], ev.w[rows]
        out[name] = (pixels[name], ((J.T * w) @ J) * pixels[name])  # w = w_F·unit²/n_samples
        start += len(q)
    return out


def suggest_planes(reg, anterior=None, preop=None, poses=None, calibration: Calibration | None = None,
                   count=8, seed=0, eval_nodes=ORGAN_NODES, weights=None, points=None,
                   points_name: str = "the targets") -> Suggestion:
    """Rank candidate probe poses by the expected drop of the mean predicted error.

    Parameters
    ----------
    reg : pipeline.Registration
        the current deformable registration (``reg.libr`` set) and its data.
    anterior : (S,) bool, optional
        the model's liver-surface points where the probe may be placed; default from
        ``preop`` (``anterior_surface_mask``), else the whole surface.
    poses : list of (orientation, (4, 4) pose) in the tracker frame, optional
        the candidates; default ``candidate_poses`` (2·``count`` poses).
    calibration : the error model (default ``uncertainty.DEFAULT_CALIBRATION``).
    eval_nodes, seed : the mean predicted error is taken over ``eval_nodes`` mesh nodes
        drawn with ``seed`` (all nodes when fewer).
    points : (P, 3) mm, optional
        preoperative (model-frame) points where the surgeon needs the error low, e.g. the
        tumours' centres: the mean predicted error is compared there instead of over the
        organ (a plane that helps the organ on average may pass 50 mm from every tumour).
        ``points_name`` says what they are, in ``Suggestion.over``.

    Returns
    -------
    Suggestion: candidates best first (poses and expected features in the tracker frame).
    """
    t0 = time.perf_counter()
    if reg.libr is None:
        raise ValueError("suggesting a plane needs a deformable registration (reg.libr is None)")
    calibration = calibration or DEFAULT_CALIBRATION
    weights = weights or default_weights()
    model, data, beta = reg.model, reg.data_model_frame, reg.libr.beta
    if poses is None:
        if anterior is None:
            anterior = anterior_surface_mask(model, preop)
        poses = candidate_poses(reg, anterior, count)
    with limit_threads(1):  # small matrices: threaded BLAS only synchronises (see libr.py)
        info: Information = information(model, data, beta, weights)
        if points is not None and len(points):
            basis = model.basis
            x, G = point_jacobian(model, beta, B=interpolation_matrix(basis.nodes, basis.tets,
                                                                      np.asarray(points, float)))
            over = points_name
        else:
            sample = organ_nodes(model, eval_nodes, seed)
            x, G = point_jacobian(model, beta, nodes=sample)
            over = Suggestion.over
        deformed = deformed_surfaces(model, beta)
        d0 = nearest_data_distance(x, data)
        e0 = calibration.predict(d0, point_sigma(G, factor=covariance_factor(info)), np.median(d0))
        # rigid map model → tracker, to bring the candidate poses into the model frame
        Tinv = inverse(homogeneous(reg.rigid.R, reg.rigid.t))
        out = []
        for i, (orientation, pose) in enumerate(poses):
            pose_model = Tinv @ np.asarray(pose, float)
            feats, pixels = expected_features(model, beta, pose_model, deformed)
            if feats:
                H = info.matrix(_extra_blocks(model, beta, feats, pixels, weights))
                d1 = np.minimum(d0, nearest_data_distance(x, feats))
                e1 = calibration.predict(d1, point_sigma(G, factor=covariance_factor(info, H)), np.median(d1))
            else:
                e1 = e0
            out.append(PlaneCandidate(i, orientation, np.asarray(pose, float), float(e0.mean() - e1.mean()),
                                      {k: reg.rigid.apply(v) for k, v in feats.items()}, pixels, float(e1.mean())))
    out.sort(key=lambda c: -c.score_mm)
    return Suggestion(out, float(e0.mean()), time.perf_counter() - t0, over)

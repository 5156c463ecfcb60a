"""Per-point residuals of a registration: how far each data point stays from the registered
model, worst first, so that a wrong click can be found and removed.

The residual is Table I's f (point–surface distance for surface features, distance to the
centerline for centerline points, to the fiducial for fiducials) at the registration's
answer (the deformable state, or the rigid pose alone when that is the answer), in the
model frame. ``rejected`` says the fit gave the point no weight (``objective.Rejection``).
"""

from dataclasses import dataclass

import numpy as np

from .objective import Weights, evaluate, point_distances
from .pipeline import Registration


@dataclass(frozen=True)
class PointResidual:
    """One data point's residual at the answer."""

    feature: str  # data feature (``navapp.features``)
    index: int  # row of the point in the feature's data (``Registration.data_model_frame[feature]``)
    residual_mm: float
    rejected: bool  # beyond the outlier cut: weight 0 in the fit


def answer_beta(reg: Registration) -> np.ndarray:
    """β of the answer shown: the LIBR state when deformed, else zero (the rigid pose alone:
    the data in ``data_model_frame`` already carry the rigid T⁻¹)."""
    if reg.libr is not None and reg.deformed:
        return np.asarray(reg.libr.beta, float)
    return np.zeros(reg.model.basis.Ju.shape[1] + 6)


def point_residuals(reg: Registration, weights: Weights | None = None) -> list[PointResidual]:
    """Every data point's residual at ``reg``'s answer, worst first. ``weights``: the ones
    the fit used (their rejection cut decides ``rejected``; default: none rejected)."""
    data = {k: v for k, v in reg.data_model_frame.items() if len(v)}
    if not data:
        return []
    ev = evaluate(reg.model, data, answer_beta(reg), weights or Weights(), jacobian=False)
    out = []
    start = 0
    for name, _feat, _S, q, rows, _local in ev.terms:
        r = ev.f[start:start + len(q)]
        start += len(q)
        n = len(data[name])
        f = point_distances(r, rows, n)
        scale = (ev.scales or {}).get(name)
        kept = np.ones(n, bool) if scale is None else np.bincount(rows, scale, minlength=n) > 0
        out += [PointResidual(name, i, float(f[i]), not kept[i]) for i in range(n)]
    out.sort(key=lambda p: -p.residual_mm)
    return out


def point_residual_at(reg: Registration, feature: str, points: np.ndarray) -> np.ndarray:
    """(N,) residual f (mm) of ``points`` (N, 3), model frame, as data of ``feature`` at ``reg``'s
    answer: how far a point left out of the fit lies from the registered model."""
    pts = np.asarray(points, float).reshape(-1, 3)
    ev = evaluate(reg.model, {feature: pts}, answer_beta(reg), Weights(), jacobian=False)
    _name, _feat, _S, q, rows, _local = ev.terms[0]
    return point_distances(ev.f[:len(q)], rows, len(pts))

"""Peer methods on the same cases and data, for comparison with LIBR.

- rigid ICP: ``registration.rigid.rigid_icp`` alone (the "rigid" rows of the studies);
- Coherent Point Drift (Myronenko & Song 2010, the ``pycpd`` package): the preoperative
  liver surface (its vertices, subsampled) is the moving Gaussian-mixture point set, the
  intraoperative *surface* data the fixed set (CPD has no notion of vessel contours or
  centerlines, so those are left out); the surface displacement is carried inside the liver
  by thin-plate-spline interpolation (``scipy.interpolate.RBFInterpolator``).

Choices, written down because the peer's paper leaves them to the user: CPD starts from the
rigid ICP pose (as LIBR does); β = 30 mm (Gaussian kernel width of the displacement field,
about a lobe's half-width), λ = 3 (smoothness), outlier weight w = 0.1 (partial coverage),
at most 60 EM iterations, 800 moving points.
"""

import time
from dataclasses import dataclass

import numpy as np

from ..features import LIVER_SURFACE
from ..registration.model import RegistrationModel, usable_data
from ..registration.rigid import rigid_icp

CPD_BETA_MM = 30.0
CPD_LAMBDA = 3.0
CPD_W = 0.1
CPD_ITERATIONS = 60
CPD_POINTS = 800  # its M × M kernel solve per EM iteration dominates: 1,500 points took 15–50 s per case


@dataclass
class PeerResult:
    method: str
    moved: np.ndarray  # (T, 3) the registered positions of the query points, mm
    seconds: float


def cpd_register(model: RegistrationModel, data: dict, points: np.ndarray, seed=0) -> PeerResult:
    """Register with rigid ICP then deformable CPD; returns where ``points`` (T, 3),
    preoperative positions in the model frame, end up (tracker space, mm)."""
    from pycpd import DeformableRegistration
    from scipy.interpolate import RBFInterpolator

    t0 = time.perf_counter()
    data = usable_data(model, data)
    rigid = rigid_icp(model, data)
    surf = np.vstack([v for k, v in data.items() if k in LIVER_SURFACE])  # CPD matches points on the liver surface only
    rest = model.features["liver"].rest
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(rest), min(CPD_POINTS, len(rest)), replace=False)
    moving = rigid.apply(rest[pick])
    # pycpd: X is the fixed set (data), Y the moving one (the model's GMM centroids)
    reg = DeformableRegistration(X=surf, Y=moving, alpha=CPD_LAMBDA, beta=CPD_BETA_MM, w=CPD_W,
                                 max_iterations=CPD_ITERATIONS, tolerance=1e-4)
    moved, _ = reg.register()
    disp = RBFInterpolator(rest[pick], moved - rigid.apply(rest[pick]), kernel="thin_plate_spline", smoothing=1.0)
    out = rigid.apply(points) + disp(np.asarray(points, float))
    return PeerResult("CPD", out, time.perf_counter() - t0)


def icp_register(model: RegistrationModel, data: dict, points: np.ndarray) -> PeerResult:
    t0 = time.perf_counter()
    rigid = rigid_icp(model, usable_data(model, data))
    return PeerResult("rigid ICP", rigid.apply(points), time.perf_counter() - t0)

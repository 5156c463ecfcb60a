"""What sets σ far from a partial scan (issue 46, item 4): the strain-energy term's curvature.

Ω's energy term is w_E f_E², f_E the mean strain-energy density, itself quadratic in α, so its
Laplace curvature w_E (J_Eᵀ J_E + f_E E / M) vanishes as the deformation does. On the test
suite's 12 mm, k = 12 phantom-0 model, a 7 % anterior patch with 0.5 mm noise and no deformation,
the pose declared (1.5 mm / 1.5°): σ given the pose (mean over the nodes, mm) with the energy's
block of H as it is, and × 10, × 100.

    python notes/scripts/energy_curvature_probe.py CACHE_DIR
"""

import sys
import warnings
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.anatomy.meshing import cached_tetmesh
from navapp.anatomy.phantom import make_phantom
from navapp.mechanics.basis import BasisSettings, load_or_compute_basis
from navapp.registration.model import build_model
from navapp.registration.objective import evaluate
from navapp.registration.pipeline import register
from navapp.registration.prior import PosePrior
from navapp.registration.uncertainty import (
    covariance_factor,
    default_weights,
    information,
    point_jacobian,
    point_sigma,
)

progress.QUIET = True
warnings.simplefilter("ignore")
cache = Path(sys.argv[1])
phantom = make_phantom(0)
mesh, _ = cached_tetmesh(phantom.liver, 12.0, cache)
basis, _ = load_or_compute_basis(mesh, BasisSettings(k=12), cache_root=cache)
rng = np.random.default_rng(5)
model = build_model(basis, phantom, fiducials=basis.nodes[rng.choice(basis.M, 6, replace=False)])
rest = model.features["liver"].rest
scan = rest[np.linalg.norm(rest - rest[np.argmax(rest[:, 1])], axis=1) < 40.0]
data = {"anterior": scan + np.random.default_rng(1).normal(0, 0.5, scan.shape)}
reg = register(model, data, pose_prior=PosePrior(1.5, 1.5))
n = basis.Ju.shape[1]
info = information(reg.model, reg.data_model_frame, reg.libr.beta)
_, G = point_jacobian(reg.model, reg.libr.beta)
H = info.matrix()
for k in (1, 10, 100):
    Hk = H + (k - 1) * info.prior
    sigma = point_sigma(G[:, :, :n], factor=covariance_factor(info, Hk[:n, :n])).mean()
    print(f"energy curvature x {k}: sigma given the pose {sigma:.2f} mm")
ev = evaluate(reg.model, reg.data_model_frame, reg.libr.beta, default_weights(), jacobian=False)
print(f"f_E {ev.f[-1]:.3g} Pa, patch {len(scan) / len(rest):.0%} of the surface")

"""The trimmed fit (``pose.trimmed_pose``) on short stylus lines (issue 48, item 5): N random
lines of 6-13 points 0.5-2 mm apart from a liver surface vertex, with 0-3 points near each
vessel, on phantom 0 at 12 mm (k = 12, the suite's small model), from the identity. Prints each
line whose pose ends 1,000 mm or more away (or raises), and the count.

    python notes/scripts/trimmed_fit_lines.py SEED N [CACHE]
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

from navapp.anatomy.meshing import cached_tetmesh
from navapp.anatomy.phantom import make_phantom
from navapp.mechanics.basis import BasisSettings, load_or_compute_basis
from navapp.registration.model import build_model
from navapp.registration.pose import trimmed_pose
from navapp.registration.rigid import RigidResult

seed, count = int(sys.argv[1]), int(sys.argv[2])
cache = Path(sys.argv[3]) if len(sys.argv) > 3 else Path(tempfile.mkdtemp())
ph = make_phantom(0)
mesh, _ = cached_tetmesh(ph.liver, 12.0, cache)
basis, _ = load_or_compute_basis(mesh, BasisSettings(k=12), cache_root=cache)
fid = basis.nodes[np.random.default_rng(5).choice(basis.M, 6, replace=False)]
model = build_model(basis, ph, fiducials=fid)
liver, portal, hepatic = (model.features[n].rest for n in ("liver", "portal", "hepatic"))
rng = np.random.default_rng(seed)
start = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
far = 0
for it in range(count):
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    n, step = int(rng.integers(6, 14)), rng.uniform(0.5, 2.0)
    data = {"anterior": liver[rng.integers(len(liver))] + np.outer(np.arange(n) * step, d)}
    if rng.random() < 0.8:
        data["portal_contour"] = portal[rng.choice(len(portal), int(rng.integers(1, 4)))] + rng.normal(0, 1, (1, 3))
    if rng.random() < 0.8:
        data["hepatic_contour"] = hepatic[rng.choice(len(hepatic), int(rng.integers(1, 3)))] + rng.normal(0, 1, (1, 3))
    try:
        pose, moved = trimmed_pose(model, data, start)
        t = float(np.linalg.norm(pose.t))
    except Exception as e:  # noqa: BLE001 - a probe: every failure is counted
        t, moved = float("nan"), repr(e)
    if not t < 1e3:
        far += 1
        print("line", it, "pose", t, "mm off, moved", moved, {k: len(v) for k, v in data.items()}, flush=True)
print("far or raised", far)

"""Issue 47, session 34: the λ the held-out choice takes on dents of the 12 mm phantom (posterior held,
the tests' _dent), against the node error of the forces fitted to all the data at every λ.

    python notes/scripts/forces_lambda_dents.py   (from the repository root)
"""
import sys
import tempfile

import numpy as np

sys.path.insert(0, "tests")
from pathlib import Path

from test_forces import _dent

from navapp.anatomy.meshing import cached_tetmesh
from navapp.anatomy.phantom import make_phantom
from navapp.mechanics.basis import BasisSettings, compute_basis
from navapp.registration.forces import SurfaceForces, choose_deformation

ph = make_phantom(0)
mesh, _ = cached_tetmesh(ph.liver, 12.0, Path(tempfile.mkdtemp()))
basis = compute_basis(mesh, BasisSettings(k=12, supports="posterior"))
sf = SurfaceForces(basis)
for radius, depth, noise in [(25., 15., 0.5), (20., 40., 1.0), (20., 40., 2.0), (25., 15., 2.0), (15., 30., 1.0)]:
    u_true, pts = _dent(basis, mesh, radius, depth, noise)
    c = choose_deformation(sf, None, {"anterior": pts}, None, None)
    errs = {}
    for lam in c.forces_mm:
        pf = sf.responses(pts)
        wf = sf.fit_weights(pf, lam)
        u = sf.field(pf, wf)
        errs[lam] = round(float(np.linalg.norm(u - u_true, axis=1).mean()), 3)
    print(radius, depth, noise, "chosen", c.energy_weight,
          "mean", {k: round(v, 3) for k, v in c.forces_mm.items()},
          "blocks", {k: [round(x, 2) for x in v] for k, v in c.forces_blocks_mm.items()}, "node err", errs, flush=True)

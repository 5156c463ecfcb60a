"""Issue 47: how much the surface-force fits with a force at every point (tests/test_forces.py's
dents on the 12 mm phantom: 15 mm deep under a 25 mm tool, λ = 0.1, and the 4 cm dent with
noise, λ = 0.01) depend on rounding: each fit with the factorisation's nested-dissection
ordering and with SuperLU's minimum-degree ordering, for the data as they are and moved by
10⁻⁹ mm and 2 × 10⁻⁹ mm (a change no measurement could see). The "before" in
notes/forces_rounding.txt is commit c459ce2 (a face's own normal at an edge or vertex); "after"
the distance field's gradient there.

    python notes/scripts/forces_rounding.py
"""
import tempfile
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla

from navapp.anatomy.meshing import cached_tetmesh
from navapp.anatomy.phantom import make_phantom
from navapp.mechanics.basis import BasisSettings, compute_basis
from navapp.mechanics.fem import Material, stiffness
from navapp.mechanics.sparse import Factorisation
from navapp.registration.forces import ForceOptions, SurfaceForces
from navapp.simulation.truth import Loading, Supports, Tool, ToolLoad, solve_linear

ph = make_phantom(0)
mesh, _ = cached_tetmesh(ph.liver, 12.0, Path(tempfile.mkdtemp()))
hb = compute_basis(mesh, BasisSettings(k=12, supports="posterior"))
s = hb.nodes[hb.surface]
top = s[np.argmax(s[:, 1])]
scan = hb.surface[s[:, 1] > np.percentile(s[:, 1], 60)]
cases = {}
for name, radius, depth, noise, lam in (("15 mm dent", 25.0, 15.0, 0.0, 0.1), ("4 cm dent", 20.0, 20.0, 0.5, 1e-2)):
    tool = Tool(tuple(top), (0.0, -1.0, 0.0), radius, depth, ToolLoad.DISPLACEMENT)
    u = solve_linear(mesh, Loading(gravity=0.0, supports=Supports.POSTERIOR, tool=tool), Material()).reshape(-1, 3)
    pts = hb.nodes[scan] + u[scan]
    if noise:
        pts = pts + np.random.default_rng(3).normal(scale=noise / np.sqrt(3), size=pts.shape)
    cases[name] = (u, pts, lam)
sf = SurfaceForces(hb)
K = stiffness(hb.nodes, hb.tets, hb.material).tocsr()[sf.free][:, sf.free]
nd = sf.F  # the default: PARDISO where installed, else SuperLU with nested dissection
mmd = Factorisation.__new__(Factorisation)  # the factorisation as it was before nested dissection
mmd.n, mmd.kind, mmd._p = K.shape[0], "superlu", np.arange(K.shape[0])
mmd._lu = spla.splu(K.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
for name, (u, pts, lam) in cases.items():
    mean = np.linalg.norm(u, axis=1).mean()
    first = None
    for label, F in ((f"default ({nd.kind})", nd), ("SuperLU minimum degree", mmd)):
        sf.F = F
        for shift in (0.0, 1e-9, 2e-9):
            fit = sf.fit(pts + shift, ForceOptions(energy_weight=lam, sites=len(pts)))
            first = fit.u if first is None else first
            err = np.linalg.norm(fit.u - u, axis=1).mean()
            moved = np.abs(fit.u - first).max()
            print(f"{name}, {label}, data moved {shift:g} mm: rms {fit.rms_mm:.6f} mm, node error {err:.6f} of "
                  f"{mean:.3f} mm, {fit.iterations} iterations, max |u - first fit's| {moved:.1e} mm", flush=True)

"""Issue 47: the forces' solve-bound part alone, for timing whole processes side by side: factorise a
case's supported stiffness (its scene's supports) and compute the 150 force sites' responses of
its S data; prints a checksum of the responses.

    python notes/scripts/forces_factorise_bench.py CASE_DIR
"""
import sys
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_supports
from navapp.registration.forces import SurfaceForces, surface_points
from navapp.registration.pipeline import prepare
from navapp.simulation.levels import data_level

case_dir = Path(sys.argv[1])
case = read_case(case_dir)
model, _ = prepare(case, **declared_supports(case))
sf = SurfaceForces(model.basis)
pf = sf.responses(surface_points(data_level(case_dir, "S", case=case)))
print(float(abs(pf.Xs).sum()))

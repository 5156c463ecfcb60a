"""Issue 47, session 43: libr-forces rows at S with the forces' pose prior weighted 1/K of today's
(σ_F²/K; the basis's fit and the rigid stage untouched); ``forces_pose_evidence`` keeps σ_F as
today. Rows as loads_rerun_method.py writes them, level S only.

    python notes/scripts/forces_prior_rows.py K OUT.csv CASE_DIR..."""
import sys
from dataclasses import replace
from pathlib import Path
import navapp.evaluation.loads as loads
import navapp.registration.forces as forces
from navapp.evaluation.distribute import ResultsCSV

K = float(sys.argv[1])
_of = forces.PoseTerm.of.__func__
_ev = forces.forces_pose_evidence
forces.PoseTerm.of = classmethod(lambda cls, prior, centroid: replace(_of(cls, prior, centroid),
                                                                      weight=prior.feature_sd_mm ** 2 / K))
forces.forces_pose_evidence = lambda f, pf, fit, pose, nodes: _ev(f, pf, fit, replace(pose, weight=pose.weight * K), nodes)
import navapp.registration.pipeline as pipeline  # noqa: E402  (PoseTerm imported by name there: patched class)
loads.LOAD_LEVELS = ("S",)
out = Path(sys.argv[2])
for case in sys.argv[3:]:
    rows = loads.run_case(case, ("libr-forces",))
    with ResultsCSV(out, loads.COLUMNS) as w:
        w.write(rows)
    print(case, [(r["level"], r["tre_mean_mm"], r["answer"], r["warned"]) for r in rows], flush=True)

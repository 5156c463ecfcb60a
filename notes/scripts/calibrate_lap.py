"""Difficulty of the nine transposed cases at given loads: rigid TRE and true displacement only.

    python notes/scripts/calibrate_lap.py OUT_DIR [--E PA] [--pressure PA] [--tilt DEG] [--head-up DEG]
                                                  [--linear] [--cases lap0-L,lap1-N,...]
    python notes/scripts/calibrate_lap.py CASES_DIR --existing  # cases simulated already (loads: the scenes')

Each lap scene (navapp/scenes/lap*.toml) with the given loads overriding its own, no iUS
planes (the rigid level sees only the stylus data, drawn before the planes), simulated into
OUT_DIR/<case> and registered rigidly. One JSON line per case, then the averages. Only
what the issue allows the loads to be chosen on: no S / S + n / CBCT registration runs.
"""

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.evaluation.table2 import run_chunk
from navapp.simulation.scene import load_scene, study_scenes
from navapp.simulation.simulate import simulate
from navapp.simulation.sources.ius import IusSpec

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("out", type=Path)
ap.add_argument("--E", type=float)
ap.add_argument("--pressure", type=float)
ap.add_argument("--tilt", type=float)
ap.add_argument("--head-up", type=float)
ap.add_argument("--linear", action="store_true", help="linear reference (default: neo-Hookean, large = true)")
ap.add_argument("--cases", help="comma-separated scene names (default: all nine)")
ap.add_argument("--existing", action="store_true",
                help="OUT_DIR already holds the simulated cases (truth/report.json): rigid registration only")
args = ap.parse_args()
progress.QUIET = True
over = {"truth_E_pa": args.E, "pressure_pa": args.pressure, "gravity_tilt_deg": args.tilt,
        "head_up_deg": args.head_up, "large": not args.linear}
want = None if args.cases is None else set(args.cases.split(","))
rows = []
for path in study_scenes("lap"):
    if want is not None and path.stem not in want:
        continue
    scene = load_scene(path)
    scene = dataclasses.replace(scene, sources={**scene.sources, "ius": IusSpec(planes=0)},
                                **{k: v for k, v in over.items() if v is not None})
    if args.existing:
        report = json.loads((args.out / path.stem / "truth" / "report.json").read_text())
    else:
        report = simulate(scene, args.out / path.stem)
    rigid = run_chunk(args.out / path.stem, [("rigid", ())])[0]
    row = {"case": path.stem, "E_pa": scene.truth_E_pa, "pressure_pa": scene.pressure_pa,
           "tilt_deg": scene.gravity_tilt_deg, "head_up_deg": scene.head_up_deg, "large": scene.large,
           "rigid_tre_mm": rigid["tre_mean_mm"], "displacement_mm": report["displacement_mm"],
           "seconds_truth": report["seconds"]["truth"]}
    rows.append(row)
    print(json.dumps(row), flush=True)
tre = np.array([r["rigid_tre_mm"] for r in rows])
mean = np.array([r["displacement_mm"]["mean"] for r in rows])
mx = np.array([r["displacement_mm"]["max"] for r in rows])
sd = float(tre.std(ddof=1)) if len(tre) > 1 else 0.0
print(json.dumps({"cases": len(rows), "rigid_tre_mm": {"mean": round(float(tre.mean()), 2), "sd": round(sd, 2)},
                  "displacement_mean_mm": [round(float(mean.min()), 1), round(float(mean.mean()), 1),
                                           round(float(mean.max()), 1)],
                  "displacement_max_mm": [round(float(mx.min()), 1), round(float(mx.max()), 1)]}))

"""Simulate the nine study scenes (3 phantoms × L/N/R) and print one JSON line each.

    python scripts/simulate_study.py OUT_DIR
"""

import json
import sys
from pathlib import Path

from navapp import progress
from navapp.simulation.scene import load_scene, study_scenes
from navapp.simulation.simulate import simulate

progress.QUIET = True
out = Path(sys.argv[1] if len(sys.argv) > 1 else "study-cases")
scenes = study_scenes()
for path in scenes:
    r = simulate(load_scene(path), out / path.stem)
    pts = [sum(p.values()) for p in r["planes"]]
    print(json.dumps({"case": r["scene"], "displacement_mm": r["displacement_mm"],
                      "stylus_coverage": r["stylus"]["coverage_of_anterior"], "stylus_points": r["stylus"]["points"],
                      "points_per_plane": {"min": min(pts), "median": sorted(pts)[len(pts) // 2], "max": max(pts)},
                      "seconds": r["seconds"]}), flush=True)

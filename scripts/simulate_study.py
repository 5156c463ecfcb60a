"""Simulate a set of nine study scenes (3 phantoms × L/N/R) and print one JSON line each.

    python scripts/simulate_study.py OUT_DIR [--set direct|lap]

``direct`` (default): each liver deformed by its own elastic model under gravity
(navapp/scenes/phantom*-*.toml). ``lap``: laparoscopic loading of reference phantom 3,
transposed onto phantoms 0–2 (navapp/scenes/lap*-*.toml, simulation/transpose.py).
"""

import argparse
import json
from pathlib import Path

from navapp import progress
from navapp.simulation.scene import SCENE_SETS, load_scene, study_scenes
from navapp.simulation.simulate import simulate

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("out", nargs="?", type=Path, default=Path("study-cases"), help="folder for the nine case folders")
ap.add_argument("--set", dest="which", choices=sorted(SCENE_SETS), default="direct", help="which scene set")
ap.add_argument("--resume", action="store_true", help="skip cases whose truth/report.json exists")
args = ap.parse_args()
progress.QUIET = True
for path in study_scenes(args.which):
    if args.resume and (args.out / path.stem / "truth" / "report.json").exists():
        continue
    r = simulate(load_scene(path), args.out / path.stem)
    pts = [sum(p.values()) for p in r["planes"]]
    line = {"case": r["scene"], "displacement_mm": r["displacement_mm"],
            "stylus_coverage": r["stylus"]["coverage_of_anterior"], "stylus_points": r["stylus"]["points"],
            "points_per_plane": {"min": min(pts), "median": sorted(pts)[len(pts) // 2], "max": max(pts)},
            "seconds": r["seconds"]}
    if "transposed" in r:
        line["transposed"] = r["transposed"]
    print(json.dumps(line), flush=True)

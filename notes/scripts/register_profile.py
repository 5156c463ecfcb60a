"""Profile one fresh guarded registration on the demo (stylus + 3 planes), cached model.

python notes/scripts/register_profile.py [--repeats N] [--cprofile FILE]
Prints per repeat the CPU and wall seconds, reg.seconds and the TRE; with --cprofile the
last repeat is profiled and the top cumulative entries printed.
"""
import argparse
import cProfile
import json
import pstats
import time

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.defaults import EDGE_MM, K
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import simulated_case_dir

progress.QUIET = True
ap = argparse.ArgumentParser()
ap.add_argument("--repeats", type=int, default=3)
ap.add_argument("--cprofile")
a = ap.parse_args()
folder = simulated_case_dir(demo_scene())
case = read_case(folder)
data = data_level(folder, "S+planes", planes=range(3), case=case)
model, _ = prepare(case, EDGE_MM, K)
x0, x1 = case.need_truth().tre_points(model.basis.nodes)
for i in range(a.repeats):
    prof = cProfile.Profile() if a.cprofile and i == a.repeats - 1 else None
    c, t = time.process_time(), time.perf_counter()
    if prof:
        prof.enable()
    r = register(model, data)
    if prof:
        prof.disable()
    print(json.dumps({"cpu": round(time.process_time() - c, 3), "wall": round(time.perf_counter() - t, 3),
                      "stages": {k: round(v, 3) for k, v in r.seconds.items()},
                      "tre": round(mean_tre(r.transform(x0), x1), 4)}), flush=True)
    if prof:
        prof.dump_stats(a.cprofile)
        pstats.Stats(prof).sort_stats("cumulative").print_stats(60)

"""Profile fresh guarded registrations of a simulated case (stylus + 3 planes), cached model.

python notes/scripts/register_case_profile.py CASE_DIR [REPEATS]
(CASE_DIR from ``navapp simulate navapp/scenes/phantom0-L.toml --out CASE_DIR``.) Prints per
repeat one JSON line: CPU and wall seconds, the main thread's CPU and wall less its run-queue wait
("wall_own", from Linux's /proc schedstat: the registration's wall without other processes'
work), the load, the stages (CPU, wall) and the TRE. Session 40 ran it alternated with the
reference commit on PYTHONPATH (notes/register_fresh_s40_phantom0L.jsonl).
"""
import json
import os
import sys
import threading
import time

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.defaults import EDGE_MM, K
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level

progress.QUIET = True
folder = sys.argv[1]
case = read_case(folder)
data = data_level(folder, "S+planes", planes=range(3), case=case)
model, _ = prepare(case, EDGE_MM, K)
x0, x1 = case.need_truth().tre_points(model.basis.nodes)


def schedstat():
    """(CPU s, run-queue wait s) of this thread so far."""
    a = open(f"/proc/self/task/{threading.get_native_id()}/schedstat").read().split()
    return int(a[0]) / 1e9, int(a[1]) / 1e9


for _ in range(int(sys.argv[2]) if len(sys.argv) > 2 else 3):
    c, t, s0 = time.process_time(), time.perf_counter(), schedstat()
    r = register(model, data)
    cpu, wall, s1 = time.process_time() - c, time.perf_counter() - t, schedstat()
    print(json.dumps({"nodes": model.basis.M, "cpu": round(cpu, 3), "wall": round(wall, 3),
                      "main_cpu": round(s1[0] - s0[0], 3), "wall_own": round(wall - (s1[1] - s0[1]), 3),
                      "load": os.getloadavg()[0],
                      "stages": {k: [round(v.cpu, 3), round(v.wall, 3)] for k, v in r.stages.items()},
                      "tre": round(mean_tre(r.transform(x0), x1), 4)}), flush=True)

"""Profile one fresh guarded registration on the demo (stylus + 3 planes), cached model.

python notes/scripts/register_profile.py [--repeats N] [--cprofile FILE]
Prints per repeat the CPU and wall seconds, reg.seconds and the TRE; with --cprofile the
last repeat is profiled and the top cumulative entries printed. Also, from Linux's
/proc/self/task/*/schedstat: the main thread's CPU ("main_cpu") and the seconds it waited,
runnable, for a core ("runq": other processes' work on a shared machine), so that
wall − runq is the registration's wall time without them ("wall_own"); none off Linux.
"""
import argparse
import cProfile
import json
import os
import pstats
import threading
import time

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.defaults import EDGE_MM, K
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import simulated_case_dir


def main_thread_schedstat():
    """(CPU s, run-queue wait s) of this thread so far, or None off Linux."""
    try:
        with open(f"/proc/self/task/{threading.get_native_id()}/schedstat") as f:
            cpu, wait = f.read().split()[:2]
    except OSError:
        return None
    return int(cpu) / 1e9, int(wait) / 1e9


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
    c, t, s0 = time.process_time(), time.perf_counter(), main_thread_schedstat()
    if prof:
        prof.enable()
    r = register(model, data)
    if prof:
        prof.disable()
    cpu, wall, s1 = time.process_time() - c, time.perf_counter() - t, main_thread_schedstat()
    own = {} if s0 is None or s1 is None else {"main_cpu": round(s1[0] - s0[0], 3), "runq": round(s1[1] - s0[1], 3),
                                              "wall_own": round(wall - (s1[1] - s0[1]), 3)}
    print(json.dumps({"cpu": round(cpu, 3), "wall": round(wall, 3), **own,
                      "load": float(os.getloadavg()[0]),
                      "stages": {k: round(v, 3) for k, v in r.seconds.items()},
                      "tre": round(mean_tre(r.transform(x0), x1), 4)}), flush=True)
    if prof:
        prof.dump_stats(a.cprofile)
        pstats.Stats(prof).sort_stats("cumulative").print_stats(60)

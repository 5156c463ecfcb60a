"""The demo's cross-validation alone, folds one after another (``sequential_folds``) and on two
threads, alternated in one process: per run the wall, the process's CPU, and per thread from
Linux's /proc schedstat the CPU and the run-queue wait; the main thread's "sleep" (wall − CPU −
run-queue wait) is its wait for the GIL and for the helper.

python notes/scripts/folds_threads_probe.py [ROUNDS]
"""
import os
import sys
import threading
import time

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.defaults import EDGE_MM, K
from navapp.registration import support as S
from navapp.registration.libr import LMOptions
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import simulated_case_dir


def sched():
    """thread id → (CPU s, run-queue wait s) of every thread of this process."""
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            a = open(f"/proc/self/task/{tid}/schedstat").read().split()
        except OSError:
            continue
        out[int(tid)] = (int(a[0]) / 1e9, int(a[1]) / 1e9)
    return out


progress.QUIET = True
folder = simulated_case_dir(demo_scene())
case = read_case(folder)
data = data_level(folder, "S+planes", planes=range(3), case=case)
model, _ = prepare(case, EDGE_MM, K)
local = register(model, data).data_model_frame
main = threading.get_native_id()
blocks = {}
for rep in range(int(sys.argv[1]) if len(sys.argv) > 1 else 4):
    for v in ("sequential", "threads") if rep % 2 == 0 else ("threads", "sequential"):
        a, c, t = sched(), time.process_time(), time.perf_counter()
        if v == "sequential":
            with S.sequential_folds():
                s = S.check_support(model, local, LMOptions())
        else:
            s = S.check_support(model, local, LMOptions())
        wall, cpu, b = time.perf_counter() - t, time.process_time() - c, sched()
        d = {k: (b[k][0] - a.get(k, (0, 0))[0], b[k][1] - a.get(k, (0, 0))[1]) for k in b}
        m = d[main]
        helper = sum(x[0] for k, x in d.items() if k != main)
        blocks[v] = [(x.rigid_mm, x.deformable_mm) for x in s.blocks]
        print(f"{v:>10} wall {wall:.3f} cpu {cpu:.3f} main: cpu {m[0]:.3f} run-queue {m[1]:.3f} "
              f"sleep {wall - m[0] - m[1]:.3f}; other threads' cpu {helper:.3f}; load {os.getloadavg()[0]:.1f}")
print("the same blocks to the bit:", blocks["sequential"] == blocks["threads"])

"""OLD=checkout NEW=checkout python notes/scripts/precompute49_s40_alt.py SURFACE.npz EDGE PAIRS OUT.jsonl: old and new alternated (not niced), whole process wall and CPU (with the mesher workers), the mesh's and Ju's md5."""
import json, resource, subprocess, sys, time, os
from pathlib import Path
surf, edge, pairs, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
tree = {"old": os.environ["OLD"], "new": os.environ["NEW"]}  # two checkouts of navapp
with open(out, "a") as fh:
    for i in range(pairs):
        for v in (("old", "new") if i % 2 == 0 else ("new", "old")):
            u0 = resource.getrusage(resource.RUSAGE_CHILDREN); t = time.perf_counter()
            r = subprocess.run([sys.executable, str(Path(__file__).with_name("precompute49_s40_one.py")), surf, edge], capture_output=True, text=True,
                               env=dict(os.environ, PYTHONPATH=tree[v]))
            wall = time.perf_counter() - t; u1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            row = json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 else {"error": r.stderr[-300:]}
            row.update(variant=v, pair=i, process_wall=round(wall, 2), process_cpu=round(u1.ru_utime + u1.ru_stime - u0.ru_utime - u0.ru_stime, 2),
                       load=os.getloadavg()[0])
            fh.write(json.dumps(row) + "\n"); fh.flush()

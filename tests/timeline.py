"""Where the suite's time goes: each test's start, end and CPU seconds (its worker process
and that process's children, Chromium and the served viewers included), one JSON line per
test in ``$NAVAPP_TIMELINE.<worker>.jsonl`` when ``NAVAPP_TIMELINE`` is set (``conftest``).
CPU seconds, not wall seconds, say what a test costs on a shared, loaded machine.

``python tests/timeline.py PREFIX`` summarises a run: per worker its span, the seconds its
tests ran and their CPU; the modules and tests by CPU seconds.
"""

import collections
import glob
import json
import os
import sys
import time

import psutil
import pytest


def tree_cpu(proc: psutil.Process) -> float:
    """CPU seconds of this process, its ended children, and its children still running."""
    t = os.times()
    total = t.user + t.system + t.children_user + t.children_system
    try:
        children = proc.children(recursive=True)
    except psutil.Error:
        children = []
    for c in children:
        try:
            ct = c.cpu_times()
            total += ct.user + ct.system
        except psutil.Error:
            pass
    return total


class Recorder:
    def __init__(self, prefix: str):
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        self.path = f"{prefix}.{worker}.jsonl"
        self.worker = worker
        self.proc = psutil.Process()

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item, nextitem):
        t0, c0 = time.time(), tree_cpu(self.proc)
        yield
        t1, c1 = time.time(), tree_cpu(self.proc)
        with open(self.path, "a") as f:
            f.write(json.dumps({"id": item.nodeid, "worker": self.worker, "start": t0, "end": t1,
                                "cpu": round(c1 - c0, 3)}) + "\n")


def summary(prefix: str, top: int = 30) -> str:
    rows = [json.loads(line) for path in glob.glob(f"{prefix}.*.jsonl") for line in open(path)]
    if not rows:
        return f"no timeline at {prefix}.*.jsonl"
    t0 = min(r["start"] for r in rows)
    out = []
    by_worker = collections.defaultdict(list)
    for r in rows:
        by_worker[r["worker"]].append(r)
    for w, rs in sorted(by_worker.items()):
        ran = sum(r["end"] - r["start"] for r in rs)
        end = max(r["end"] for r in rs) - t0
        out.append(f"{w}: {len(rs)} tests, ended at {end:.0f} s, tests ran {ran:.0f} s, "
                   f"{sum(r['cpu'] for r in rs):.0f} CPU s")
    mods = collections.defaultdict(lambda: [0.0, 0.0, 0])
    for r in rows:
        m = mods[r["id"].split("::")[0]]
        m[0] += r["cpu"]
        m[1] += r["end"] - r["start"]
        m[2] += 1
    out.append("\nmodules by CPU seconds (CPU, wall, tests)")
    out += [f"{c:8.1f} {w:8.1f} {n:4d}  {m}" for m, (c, w, n) in sorted(mods.items(), key=lambda x: -x[1][0])[:top]]
    out.append("\ntests by CPU seconds (CPU, wall)")
    for r in sorted(rows, key=lambda r: -r["cpu"])[:top]:
        out.append(f"{r['cpu']:8.1f} {r['end'] - r['start']:8.1f}  {r['id']}")
    return "\n".join(out)


if __name__ == "__main__":
    print(summary(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 30))

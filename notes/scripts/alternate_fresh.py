"""Alternate an old and a new tree's fresh registrations of one case, process by process.

python notes/scripts/alternate_fresh.py run OLD_TREE NEW_TREE CASE_DIR OUT.jsonl --until HH:MM [--one-core]
python notes/scripts/alternate_fresh.py report OUT.jsonl [--quiet 0.1]

Each pair runs ``notes/scripts/register_case_profile.py CASE_DIR 3`` once from each tree (its own
directory on PYTHONPATH; the order swapped every pair) and appends its three JSON lines to OUT,
tagged old / new with the pair number, the load at the start and how many cores other processes
kept busy over the second before the pair (``busy_before``, from /proc/stat: a pair after ~0 is a
quiet one). ``--one-core`` runs both under ``taskset -c 0``. Session 41 ran it with 728fbca (a
detached worktree) against its branch (notes/register_fresh_s41_phantom0L*.jsonl). ``report``
prints, over the second and third registration of each process (of the pairs whose
``busy_before`` is under ``--quiet``, if given), the medians old and new and the median of the
pairs' new ÷ old ratios of wall, CPU, the main thread's CPU and ``wall_own``, and the load.
"""

import argparse
import json
import os
import statistics
import subprocess
import time
from pathlib import Path


def busy_cores(seconds: float = 1.0) -> float:
    """Cores busy (0–2 here) over ``seconds``, by /proc/stat's idle and iowait ticks."""
    def snap() -> tuple[int, int]:
        ticks = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return sum(ticks), ticks[3] + ticks[4]

    t0, i0 = snap()
    time.sleep(seconds)
    t1, i1 = snap()
    return (os.cpu_count() or 1) * (1 - (i1 - i0) / max(t1 - t0, 1))


def report(path: str, quiet: float | None) -> None:
    rows = [json.loads(line) for line in open(path)]
    runs: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        runs.setdefault((r["tag"], r["pair"]), []).append(r)
    pairs = [p for p in sorted({p for _, p in runs})
             if len(runs.get(("old", p), [])) == len(runs.get(("new", p), [])) == 3
             and (quiet is None or runs[("old", p)][0]["busy_before"] < quiet)]
    print(f"{len(pairs)} pairs")
    for key in ("wall", "cpu", "main_cpu", "wall_own"):
        med = {tag: statistics.median(x["r"][key] for p in pairs for x in runs[(tag, p)][1:]) for tag in ("old", "new")}
        ratios = [statistics.median(x["r"][key] for x in runs[("new", p)][1:]) /
                  statistics.median(x["r"][key] for x in runs[("old", p)][1:]) for p in pairs]
        print(f"{key:9s} old {med['old']:.3f}  new {med['new']:.3f}  pair ratio median {statistics.median(ratios):.3f} "
              f"({min(ratios):.3f}–{max(ratios):.3f})")
    loads = [x["r"]["load"] for p in pairs for tag in ("old", "new") for x in runs[(tag, p)][1:]]
    print(f"load {min(loads):.2f}–{max(loads):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    rep = sub.add_parser("report")
    rep.add_argument("out")
    rep.add_argument("--quiet", type=float, default=None, help="only pairs after fewer busy cores than this")
    run = sub.add_parser("run")
    run.add_argument("old")
    run.add_argument("new")
    run.add_argument("case")
    run.add_argument("out")
    run.add_argument("--until", required=True, help="stop starting pairs at this UTC time (HH:MM)")
    run.add_argument("--one-core", action="store_true", help="both under taskset -c 0")
    args = ap.parse_args()
    if args.command == "report":
        report(args.out, args.quiet)
        return
    trees = [(Path(args.old).resolve(), "old"), (Path(args.new).resolve(), "new")]
    pre = ["taskset", "-c", "0"] if args.one_core else []
    pair = 0
    while time.strftime("%H:%M", time.gmtime()) < args.until:
        pair += 1
        busy = busy_cores()
        for tree, tag in trees if pair % 2 else trees[::-1]:
            load = float(Path("/proc/loadavg").read_text().split()[0])
            done = subprocess.run([*pre, "python", "notes/scripts/register_case_profile.py", args.case, "3"], cwd=tree,
                                 env={**os.environ, "PYTHONPATH": str(tree)},
                                 capture_output=True, text=True, check=True)
            with open(args.out, "a") as f:
                for line in done.stdout.splitlines():
                    f.write(json.dumps({"tag": tag, "pair": pair, "busy_before": round(busy, 2), "load_start": load,
                                        "r": json.loads(line)}) + "\n")


if __name__ == "__main__":
    main()

"""Summary of ``notes/scripts/local_modes_probe.py``'s lines by case set and level, for each rule
that keeps the extended basis: always, or when the cross-validation's held-out RMS of the
deformable fit drops by more than a margin. The tool set's ratio is to its no-correction
mean in results/loads.csv.

    python notes/scripts/local_modes_summary.py notes/local_modes_probe.jsonl [notes/local_modes_folds.jsonl]

With the second file (``local_modes_folds.py``), the rule reads its held-out RMS, where the
sources were placed inside each fold, instead of the first probe's.
"""

import csv
import json
import statistics as st
import sys

HELD_OUT = ("tooltest", "tooldraw")


def sets(rows):
    yield "tool", [r for r in rows if r["case"].startswith("tool") and not r["case"].startswith(HELD_OUT)]
    yield "direct", [r for r in rows if r["case"].startswith("phantom")]
    yield "lap", [r for r in rows if r["case"].startswith("lap")]
    yield "held-out", [r for r in rows if r["case"].startswith(HELD_OUT)]


def pick(r, margin):
    """(TRE, warned, extended used) of one registration under the rule."""
    if "tre2" not in r:
        return r["tre"], r["warned"], False
    h, h2 = r.get("held_out"), r.get("held_out2")
    if margin is None or (h and h2 and h2[0] < (1 - margin) * h[0]):
        return r["tre2"], r["warned2"], True
    return r["tre"], r["warned"], False


def main(path, folds_path=None):
    rows = [json.loads(line) for line in open(path)]
    if folds_path:
        folds = {(f["case"], f["level"]): f["folds"] for f in map(json.loads, open(folds_path))}
        for r in rows:
            r["held_out"], r["held_out2"] = [[v] for v in folds[(r["case"], r["level"])]]
    with open("results/loads.csv") as fh:
        identity = [float(r["tre_mean_mm"]) for r in csv.DictReader(fh) if r["method"] == "identity"]
    none_mm = st.mean(identity)
    for margin in (None, 0.0, 0.05, 0.10):
        print("rule:", "always" if margin is None else f"held-out deformable RMS lower by more than {margin:.0%}")
        for name, group in sets(rows):
            for level in ("S", "S+all"):
                g = [r for r in group if r["level"] == level]
                if not g:
                    continue
                a = st.mean(r["tre"] for r in g)
                b = st.mean(pick(r, margin)[0] for r in g)
                ratio = f" ({a / none_mm:.3f} -> {b / none_mm:.3f} x no correction)" if name == "tool" else ""
                worse = [(r["case"], r["tre"], pick(r, margin)[0]) for r in g if pick(r, margin)[0] > r["tre"] + 0.1]
                better = sum(pick(r, margin)[0] < r["tre"] - 0.1 for r in g)
                print(f"  {name:8s} {level:6s} n={len(g):2d} mean {a:.3f} -> {b:.3f}{ratio}; extended used on "
                      f"{sum(pick(r, margin)[2] for r in g)}; warned {sum(r['warned'] for r in g)} -> "
                      f"{sum(pick(r, margin)[1] for r in g)}; better {better}, worse {len(worse)} {worse}")


if __name__ == "__main__":
    main(*sys.argv[1:3])

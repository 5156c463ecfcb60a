"""Issue 47, session 41: one method's rows of the local-load study against no correction and
against earlier rows of the same method (``loads_rerun_method.py``'s CSVs).

    python notes/scripts/forces_rows_compare.py IDENTITY.csv AFTER.csv [BEFORE.csv] [METHOD]

IDENTITY.csv holds the cases' ``identity`` rows (a study's results file); per level: the set's
mean TRE, × no correction, the answers worse than no correction and whether each is warned,
and per case the change from BEFORE.csv (flagged where it is worse by more than 0.05 mm)."""
import csv
import sys


def rows(path):
    with open(path) as fh:
        return {(r["case"], r["level"], r["method"]): r for r in csv.DictReader(fh)}


ident, after = rows(sys.argv[1]), rows(sys.argv[2])
before = rows(sys.argv[3]) if len(sys.argv) > 3 else {}
method = sys.argv[4] if len(sys.argv) > 4 else "libr-forces"
for level in ("S", "S+all"):
    cases = sorted(c for (c, lv, m) in after if lv == level and m == method)
    if not cases:
        continue
    a = [float(after[(c, level, method)]["tre_mean_mm"]) for c in cases]
    i = [float(ident[(c, level, "identity")]["tre_mean_mm"]) for c in cases]
    worse = [(c, x, y, after[(c, level, method)]["warned"]) for c, x, y in zip(cases, a, i, strict=True) if x > y]
    line = (f"{level:5s} n={len(cases)} mean {sum(a) / len(a):.3f} mm, no correction {sum(i) / len(i):.3f}, "
            f"x {sum(a) / sum(i):.3f}; worse than no correction {len(worse)}: "
            + ", ".join(f"{c} {x:.3f} > {y:.3f} warned={w}" for c, x, y, w in worse))
    b = [float(before[(c, level, method)]["tre_mean_mm"]) for c in cases if (c, level, method) in before]
    if before and len(b) == len(cases):
        line += f" | before: mean {sum(b) / len(b):.3f}, x {sum(b) / sum(i):.3f}"
    print(line)
    for c, x in zip(cases, a, strict=True):
        r, was = after[(c, level, method)], before.get((c, level, method))
        change = "" if was is None else (f"before {float(was['tre_mean_mm']):.3f} ({was['answer']}, warned "
                                         f"{was['warned']}) {x - float(was['tre_mean_mm']):+.3f}")
        flag = " <- worse by > 0.05" if was is not None and x - float(was["tre_mean_mm"]) > 0.05 else ""
        print(f"  {c:16s} {x:.3f} {r['answer']:10s} warned {r['warned']:5s} "
              f"no correction {float(ident[(c, level, 'identity')]['tre_mean_mm']):.3f} {change}{flag}")

"""Which wrong-supports answers are worse than the undeclared one without a line, under the
warning rules of session 38, from the probe's rows (``wrong_supports_probe.py``'s JSONL):
"A (in code)" as the rows were warned, "A|SE1" also warning a held deformation whose held-out
gain over the free basis's fits is within one paired standard error (``HeldCheck.undecided``),
"A|SE2" within two. Worse: by more than 0.1 mm mean TRE.

    python notes/scripts/wrong_supports_rules.py notes/wrong_supports_s38_after.jsonl
"""
import json, sys, math
from collections import defaultdict
rows = [json.loads(l) for l in open(sys.argv[1])]
by = defaultdict(dict)
for r in rows:
    by[(r["case"], r["level"])][r["supports"]] = r
def se_rule(r, k=1.0):
    h = r.get("held_check")
    if not (r["deformed"] and h and not h["replaced"] and not h["contradicted"]):
        return False
    g, s = h.get("gain_mm"), h.get("gain_se_mm")
    if g is None or (isinstance(g, float) and math.isnan(g)):
        return False
    return not g > k * s
def A(r):
    h = r.get("held_check")
    return bool(h and h.get("rests_on_supports"))
def worse(k, how): return by[k][how]["tre"] > by[k]["none"]["tre"] + 0.1
for name, rule in [("A (in code)", lambda r: False), ("A|SE1", lambda r: se_rule(r)), ("A|SE2", lambda r: se_rule(r, 2.0))]:
    for level in ("S", "S+all"):
        ks = [k for k in by if k[1] == level and len(by[k]) == 3]
        out = []
        for how in ("right", "wrong"):
            silent = [k[0] for k in ks if worse(k, how) and not by[k][how]["warnings"] and not rule(by[k][how])]
            warned = sum(1 for k in ks if by[k][how]["warnings"] or rule(by[k][how]))
            byA = sum(1 for k in ks if A(by[k][how]))
            mean = sum(by[k][how]["tre"] for k in ks) / len(ks)
            out.append(f"{how}: mean {mean:.3f} silent {len(silent)} warned {warned} (A {byA}) {silent}")
        und = sum(by[k]["none"]["tre"] for k in ks) / len(ks)
        print(name, level, len(ks), f"undeclared {und:.3f} warned {sum(1 for k in ks if by[k]['none']['warnings'])}", " | ".join(out))

"""Issue 47, session 34: the least held-out λ against the one-standard-error rule, read off one run.

    NAVAPP_FORCES_BY_LAMBDA=1 python notes/scripts/forces_study.py OUT.jsonl CASE_DIR...
    python notes/scripts/forces_lambda_rules.py OUT.jsonl

The run chose by the rule (``forces.one_standard_error``); the old choice is rebuilt from the
same rows: the λ of least held-out RMS, the answer of least held-out RMS among no deformation,
the basis and the forces there (a tie to no deformation), and its TRE from ``forces_by_lambda``
(the forces fitted to all the data at that λ; the fit is deterministic, session 33)."""
import json
import statistics
import sys

rows = [json.loads(line) for line in open(sys.argv[1])]
total = {"identity": 0.0, "least": 0.0, "rule": 0.0}
worse_least, worse_rule = [], []
for r in rows:
    held = {float(k): v for k, v in r["heldout_forces_mm"].items()}
    lam = min(held, key=lambda k: held[k])
    scores = {"none": r["heldout_none_mm"], "forces": held[lam]}
    if r["heldout_basis_mm"] is not None:
        scores["basis"] = r["heldout_basis_mm"]
    answer = min(scores, key=lambda a: (scores[a], a != "none"))
    by_lam = {float(k): v for k, v in r["forces_by_lambda"].items()}
    least = {"none": r["none"], "basis": r["basis"], "forces": by_lam[lam]}[answer]
    total["identity"] += r["identity"]
    total["least"] += least
    total["rule"] += r["shown"]
    if least > r["identity"]:
        worse_least.append(r["case"])
    if r["shown"] > r["identity"]:
        worse_rule.append(r["case"])
    print(r["case"], "identity", r["identity"], "| least:", answer, f"{lam:g}", least,
          "| rule:", r["answer"], f"{r['energy_weight']:g}", r["shown"], "|", r["seconds_total"], "s")
n = len(rows)
print(n, "cases, mean TRE mm:", {k: round(v / n, 3) for k, v in total.items()},
      "× no correction: least", round(total["least"] / total["identity"], 3),
      "rule", round(total["rule"] / total["identity"], 3))
print("worse than no correction: least", worse_least, "rule", worse_rule)
print("median seconds", statistics.median(r["seconds_total"] for r in rows))

"""The band's rule, before and after session 28, with each liver in turn as the calibration
liver: held-out (set, level) cells under the nominal 90 %.

    python notes/scripts/band_rule_compare.py COLLECTED SET=CASE_DIR... [--band-only SET]

COLLECTED holds one pickle per case, ``<set>__<case>.pkl``, each the list of
``error_estimate.Sample`` that ``error_estimate.collect_case(case_dir)`` returns. The rule
before: per set, quantiles over 2000 sampled nodes per registration (all levels pooled);
after: ``fit_band``, per set and level.
"""
import argparse
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np

from navapp.evaluation.error_estimate import (
    NOMINAL,
    _band_quantiles,
    _fit_rows,
    band_coverage,
    fit_calibration,
    liver_rotation,
)


def per_set_rule(collected, liver, band_only):
    """The rule before session 28 (``fit_band`` then): per set, all levels pooled."""
    shown = {k: [s for s in v if s.deformed] for k, v in collected.items()}
    fit_on = [s for k, v in shown.items() if k not in band_only for s in v if s.liver == liver]
    cal = fit_calibration(fit_on, name="")
    rng = np.random.default_rng(0)
    lo, hi = cal.lower, cal.upper
    for v in shown.values():
        mine = [s for s in v if s.liver == liver]
        if mine:
            D, S, E, Mm, _ = _fit_rows(mine, rng)
            q = _band_quantiles(cal, D, S, E, Mm, NOMINAL)
            lo, hi = min(lo, q[0]), max(hi, q[1])
    return replace(cal, lower=lo, upper=hi)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("collected", type=Path)
    ap.add_argument("sets", nargs="+", help="SET=CASE_DIR (one per case)")
    ap.add_argument("--band-only", action="append", default=[])
    a = ap.parse_args()
    collected: dict = {}
    for item in a.sets:
        label, case = item.split("=", 1)
        collected.setdefault(label, []).extend(
            pickle.loads((a.collected / f"{label}__{Path(case).name}.pkl").read_bytes()))
    band_only = tuple(a.band_only)
    after = liver_rotation(collected, band_only)
    for name in dict.fromkeys(c.calibrated_on for c in after):
        liver = next(s.liver for v in collected.values() for s in v if s.case == name)
        old = per_set_rule(collected, liver, band_only)
        cells = [c for c in after if c.calibrated_on == name]
        print(f"calibrated on the liver of {name}: before [{old.lower:.3f}, {old.upper:.3f}], "
              f"after [{cells[0].lower:.3f}, {cells[0].upper:.3f}]")
        for c in cells:
            ss = [s for s in collected[c.set] if s.deformed and s.liver != liver and s.level == c.level]
            e = np.concatenate([s.err for s in ss])
            p = np.concatenate([old.predict(s.d, s.sigma, np.median(s.d)) for s in ss])
            before = band_coverage(e, p, old.lower, old.upper)
            flag = "  <- under 90 %" if min(before, c.coverage) < NOMINAL else ""
            print(f"  {c.set:18s} {c.level:6s} {c.registrations:3d} registrations: before {before:6.1%}, "
                  f"after {c.coverage:6.1%}{flag}")


if __name__ == "__main__":
    main()

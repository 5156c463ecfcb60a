"""The robustness study's quick design registered with and without the guards against local
loads (methods "unguarded" and "default"), on the cases given: one draw, offsets 0°, 15° and
20°, three label conditions. Rows go to the CSV given (resumable, as the study's own).

    python notes/scripts/robustness_guards.py notes/robustness_guards_quick.csv study-cases/phantom*
"""

import sys
from pathlib import Path

from navapp import progress
from navapp.evaluation.robustness import OFFSETS, run_robustness

progress.QUIET = True
quick = tuple(o for o in OFFSETS if o[0] in (0.0, 15.0, 20.0))  # the offsets of ``study robustness --quick``
cases = [Path(c) for c in sys.argv[2:]]
print(run_robustness(cases, Path(sys.argv[1]), methods=("unguarded", "default"), draws=1, workers=1, offsets=quick))

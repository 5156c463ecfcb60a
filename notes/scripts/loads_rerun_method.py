"""Rerun one method's rows of the local-load study and write its report, without running the
methods a results file never had (``navapp study loads`` runs every method missing from it, and
the study CSVs have no ``libr-forces`` rows: those take minutes per case). Remove the method's
rows of the cases first; this appends the new ones (``loads.run_case`` with that method alone)
and writes loads.md / loads.png as the study command does.

    python notes/scripts/loads_rerun_method.py METHOD RESULTS.csv REPORT_DIR CASE...
    python notes/scripts/loads_rerun_method.py libr-declared results/loads.csv results /work/cases/tool*
"""

import sys
from pathlib import Path

from navapp.evaluation.distribute import ResultsCSV
from navapp.evaluation.loads import COLUMNS, run_case, write_report

method, results, report = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
for case in sys.argv[4:]:
    rows = run_case(case, (method,))
    with ResultsCSV(results, COLUMNS) as out:
        out.write(rows)
    print(case, [(r["level"], r["tre_mean_mm"], r["warned"]) for r in rows], flush=True)
write_report(results, report)

"""The maintained tools in scripts/ run, and the reports they made are what they make now."""

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _run(*args, cwd=ROOT):
    out = subprocess.run([sys.executable, *map(str, args)], cwd=cwd, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_table2_lap_report_reproduces_the_committed_sections(tmp_path):
    """``python scripts/table2_lap_report.py CSV OUT_MD`` on the committed results CSV writes the
    transposed-case sections that results/table2.md holds, word for word."""
    csv = tmp_path / "table2_lap.csv"
    shutil.copy(ROOT / "results/table2_lap.csv", csv)
    _run(ROOT / "scripts/table2_lap_report.py", csv, tmp_path / "sections.md")
    sections = (tmp_path / "sections.md").read_text().strip()
    assert sections.startswith("### Quick design on all nine cases")
    assert sections in (ROOT / "results/table2.md").read_text()
    assert (tmp_path / "table2_lap_by_level.png").stat().st_size > 10_000


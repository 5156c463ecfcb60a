"""The maintained tools in scripts/ run, and the reports they made are what they make now."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

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



SCRIPTS = sorted((ROOT / "scripts").glob("*.py"))


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_every_maintained_tool_starts_and_says_its_usage_without_writing_anything(script, tmp_path):
    """Each tool in scripts/ imports what it uses from today's navapp (a renamed function
    fails here, not on the day someone needs the tool) and answers ``--help`` with its usage:
    ``--help`` is not taken for a path (render_phantoms.py rendered into a folder named
    "--help", table2_lapnh_report.py rewrote results/table2_lapnh.md from it)."""
    out = _run(script, "--help", cwd=tmp_path)
    assert out.startswith("usage:"), out[:300]
    assert not list(tmp_path.iterdir())


def test_every_maintained_tool_is_named_by_the_docs():
    """A tool in scripts/ is one the docs tell a reader to run (README, docs/, the reports in
    results/); a one-off probe or migration goes to notes/scripts/ with its output in notes/."""
    pages = [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "results").rglob("*.md")]
    text = "\n".join(p.read_text() for p in pages)
    assert SCRIPTS and [s.name for s in SCRIPTS if f"scripts/{s.name}" not in text] == []


def test_make_tool_scenes_writes_the_committed_study_scenes(tmp_path):
    """``python scripts/make_tool_scenes.py`` makes the 24 local-load scenes in
    navapp/scenes byte for byte (written elsewhere here with ``--out``)."""
    _run(ROOT / "scripts/make_tool_scenes.py", "--out", tmp_path)
    made = sorted(p.name for p in tmp_path.glob("*.toml"))
    assert made == sorted(p.name for p in (ROOT / "navapp/scenes").glob("tool[0-9]-?.toml")) and len(made) == 24
    for name in made:
        assert (tmp_path / name).read_text() == (ROOT / "navapp/scenes" / name).read_text(), name


def test_table2_lapnh_report_reproduces_the_committed_report(tmp_path):
    """``python scripts/table2_lapnh_report.py CASES CSV LINEAR_CSV OUT_MD`` on the committed
    CSVs writes results/table2_lapnh.md word for word, up to the hand-written "What it shows"
    that follows what it writes. The nine cases' folders are not in the
    repository: their report.json values are read back from the committed table (it prints
    them to 0.1 mm, so these give the same lines)."""
    committed = (ROOT / "results/table2_lapnh.md").read_text()
    cases = tmp_path / "cases"
    rows = [line.strip("|").split("|") for line in committed.splitlines() if line.startswith("| lap")
            and line.count("|") == 6]
    assert len(rows) == 9
    for name, mean, peak, residual, supports in rows:
        s_mean, s_max = supports.split("/")
        report = {"displacement_mm": {"mean": float(mean), "max": float(peak)},
                  "transposed": {"correspondence_residual_mm": float(residual),
                                 "support_displacement_mm": {"mean": float(s_mean), "max": float(s_max)}}}
        (cases / name.strip() / "truth").mkdir(parents=True)
        (cases / name.strip() / "truth" / "report.json").write_text(json.dumps(report))
    out = tmp_path / "out" / "table2_lapnh.md"
    out.parent.mkdir()
    _run(ROOT / "scripts/table2_lapnh_report.py", cases, ROOT / "results/table2_lapnh.csv",
         ROOT / "results/table2_lap.csv", out)
    made = out.read_text()
    assert committed.startswith(made) and committed[len(made):].startswith("\n### What it shows")
    assert (out.parent / "table2_lapnh_by_level.png").stat().st_size > 10_000

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


def test_the_warning_rate_tool_reads_a_registrations_warnings_as_they_are(small_model):
    """scripts/warning_rate.py counts each answer's warnings by kind. Its ``kind`` still split
    a line of text after warnings became ``FitWarning`` (issue 51), so every run stopped with an
    AttributeError at the first warned answer (session 41)."""
    import importlib.util
    import warnings

    from navapp.registration.pipeline import register

    spec = importlib.util.spec_from_file_location("warning_rate", ROOT / "scripts/warning_rate.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    patch = small_model.features["liver"].rest[:40] + 0.5  # a patch: its pose is in doubt
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reg = register(small_model, {"anterior": patch})
    assert reg.warnings
    assert {tool.kind(w) for w in reg.warnings} == {w.kind.value for w in reg.warnings}


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


def test_wrong_supports_report_reproduces_the_committed_report(tmp_path):
    """``python scripts/wrong_supports.py report ROWS --before ROWS`` on the committed rows in
    notes/ writes results/wrong_supports.md word for word, up to its hand-written "What it shows"
    (kept when the report is rewritten in place)."""
    committed = (ROOT / "results/wrong_supports.md").read_text()
    out = tmp_path / "wrong_supports.md"
    _run(ROOT / "scripts/wrong_supports.py", "report", "notes/wrong_supports_s40_after.jsonl",
         "--before", "notes/wrong_supports_s39_after.jsonl", "--out", out)
    made = out.read_text()
    assert committed.startswith(made) and committed[len(made):].startswith("\n### What it shows")
    assert "| right | S + all | 2.334 | 0 → 0 | 31 → 31 |" in made and "changed on 9 of the 216" in made
    shutil.copy(ROOT / "results/wrong_supports.md", out)
    _run(ROOT / "scripts/wrong_supports.py", "report", "notes/wrong_supports_s40_after.jsonl",
         "--before", "notes/wrong_supports_s39_after.jsonl", "--out", out)
    assert out.read_text() == committed


def _refused(args, cwd, problem):
    out = subprocess.run([sys.executable, str(ROOT / "scripts/wrong_supports.py"), *map(str, args)], cwd=cwd,
                         capture_output=True, text=True)
    assert out.returncode != 0 and problem in out.stderr and out.stderr.count("\n") == 1, out.stderr[-2000:]


def test_wrong_supports_refuses_a_missing_case_or_rows_file_in_one_line(tmp_path):
    (tmp_path / "nocase").mkdir()
    _refused(["run", tmp_path / "rows.jsonl", tmp_path / "absent"], tmp_path, "not a case folder")
    _refused(["run", tmp_path / "rows.jsonl", tmp_path / "nocase"], tmp_path, "not a case folder")
    _refused(["report", tmp_path / "absent.jsonl"], tmp_path, "no such rows file")
    (tmp_path / "bad.jsonl").write_text('{"case": "x"}\n')
    _refused(["report", tmp_path / "bad.jsonl"], tmp_path, "bad.jsonl:1: not a row")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.jsonl", "nocase"]


TINY_TOOL_SCENE = """name = "tooltiny"
seed = 1
[anatomy]
phantom = 0
[deformation]
gravity = false
supports = "ligaments"
release = "N"
mesh_edge_mm = 10.0
truth_E_pa = 5000
[tool]
site = "anterior"
at = [-19.5, 55.5, 53.0]
radius_mm = 10
depth_mm = 15
load = "pressure"
[stylus]
pattern = "patch"
points = 200
coverage = 0.3
at = [-19.2, 69.6, 42.3]
[ius]
planes = 4
"""


@pytest.fixture(scope="module")
def tiny_tool_case(tmp_path_factory, cache_root):
    """TINY_TOOL_SCENE simulated: phantom 0 held at its ligaments, a tool pressed 15 mm, 10 mm truth mesh."""
    from navapp.simulation.scene import load_scene
    from navapp.simulation.simulate import simulate

    root = tmp_path_factory.mktemp("tooltiny")
    (root / "tooltiny.toml").write_text(TINY_TOOL_SCENE)
    case = root / "cases" / "tooltiny"
    simulate(load_scene(root / "tooltiny.toml"), case, cache_root)
    return case


def _wrong_supports_run(rows_file, case, cache_root, *more):
    import os

    env = {**os.environ, "NAVAPP_CACHE": str(cache_root)}
    return subprocess.run([sys.executable, str(ROOT / "scripts/wrong_supports.py"), "run", str(rows_file), str(case),
                           "--edge", "12", "--k", "12", *more], cwd=ROOT, env=env, capture_output=True, text=True)


def test_wrong_supports_runs_a_small_tool_case_and_reports_it(tmp_path, tiny_tool_case, cache_root):
    """``run`` on one small local-load case (phantom 0 held at its ligaments, a tool pressed
    15 mm, 10 mm truth mesh; registered on a 12 mm mesh, k = 12): six rows, the undeclared,
    right (ligaments) and wrong (posterior) bases at S and S+all; run again, nothing is
    appended; ``report`` tables them."""
    case = tiny_tool_case
    rows_file = tmp_path / "rows.jsonl"
    for added in (6, 0):
        out = _wrong_supports_run(rows_file, case, cache_root)
        assert out.returncode == 0, out.stderr[-3000:]
        assert json.loads(out.stdout)["rows_added"] == added
    rows = [json.loads(line) for line in rows_file.read_text().splitlines()]
    assert [(r["level"], r["supports"], r["held"]) for r in rows] == [
        (level, how, held) for level in ("S", "S+all")
        for how, held in (("none", None), ("right", "ligaments"), ("wrong", "posterior"))]
    assert all(r["case"] == "tooltiny" and r["scene"] == "ligaments" and 0 < r["tre"] < 10 for r in rows)
    assert len({r["identity"] for r in rows}) == 1 and all("held_check" in r for r in rows if r["held"])
    md = tmp_path / "report" / "wrong_supports.md"
    _run(ROOT / "scripts/wrong_supports.py", "report", rows_file, "--out", md)
    text = md.read_text()
    assert text.startswith("# Declared supports that are wrong") and "1 local-load case (tooltiny … tooltiny)" in text
    means = {(r["supports"], r["level"]): r["tre"] for r in rows}
    for how, name in (("none", "undeclared"), ("right", "right"), ("wrong", "wrong")):
        warned = sum(1 for r in rows if r["supports"] == how and r["level"] == "S+all" and r["warnings"])
        assert f"| {name} | S + all | {means[how, 'S+all']:.3f} | " in text
        assert text.split(f"| {name} | S + all | ", 1)[1].split("\n", 1)[0].endswith(f" | {warned} |")


def test_wrong_supports_runs_the_declared_statements_with_surface_forces(tmp_path, tiny_tool_case, cache_root):
    """``run --forces`` registers the right and wrong statements as the loads study's
    libr-forces does (``register(surface_forces=True)``): their rows say which of no
    deformation, the held basis and the forces was shown, with the choice's held-out figures;
    the undeclared rows are the same registration as without ``--forces``. A rows file of one
    kind refuses the other in one line; ``report`` says the statements had the forces."""
    plain, forced = tmp_path / "plain.jsonl", tmp_path / "forces.jsonl"
    for rows_file, more in ((plain, ()), (forced, ("--forces",))):
        out = _wrong_supports_run(rows_file, tiny_tool_case, cache_root, *more)
        assert out.returncode == 0, out.stderr[-3000:]
        assert json.loads(out.stdout)["rows_added"] == 6
    for rows_file, more in ((plain, ("--forces",)), (forced, ())):
        out = _wrong_supports_run(rows_file, tiny_tool_case, cache_root, *more)
        assert out.returncode != 0 and "surface forces" in out.stderr and out.stderr.count("\n") == 1, out.stderr
    rows = [json.loads(line) for line in forced.read_text().splitlines()]
    before = {(r["level"], r["supports"]): r for r in map(json.loads, plain.read_text().splitlines())}
    assert all(r["forces"] is True for r in rows)
    for r in rows:
        if r["supports"] == "none":
            assert "surface_forces" not in r and r["tre"] == before[r["level"], "none"]["tre"]
        else:
            sf = r["surface_forces"]
            assert r["answer"] == sf["answer"] in ("none", "basis", "forces")
            assert set(sf["heldout_forces_mm"]) and sf["heldout_free_mm"] is not None
    md = tmp_path / "wrong_supports.md"
    _run(ROOT / "scripts/wrong_supports.py", "report", forced, "--out", md)
    text = md.read_text()
    assert "registered with surface forces" in text and "CASE… --forces" in text
    _run(ROOT / "scripts/wrong_supports.py", "report", plain, "--out", md)
    assert "surface forces" not in md.read_text()

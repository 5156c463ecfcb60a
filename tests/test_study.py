"""The Table II runner: design size, resumability, report; the README's other study commands."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from navapp.evaluation.report import markdown
from navapp.evaluation.table2 import read_results, run_table2, scenarios


def test_design_has_the_papers_counts():
    s = scenarios()
    count = {lv: sum(1 for level, _ in s if level == lv) for lv in ("S+1", "S+2", "S+3")}
    assert count == {"S+1": 16, "S+2": 120, "S+3": 560}
    assert len(s) == 1 + 1 + 16 + 120 + 560 + 1 + 1 + 1  # 701 per case, 6,309 for nine
    assert len(set(s)) == len(s)


@pytest.fixture(scope="module")
def quick_case(tmp_path_factory, cache_root):
    """A small simulated case (phantom 0, 16 planes) registered on a 12 mm mesh, k = 12."""
    from navapp.simulation.scene import parse_scene
    from navapp.simulation.simulate import simulate

    scene = parse_scene({"name": "q", "anatomy": {"phantom": 0},
                         "deformation": {"release": "L", "mesh_edge_mm": 10.0}, "ius": {"planes": 16}})
    case = tmp_path_factory.mktemp("study") / "q"
    simulate(scene, case, cache_root)
    return case


@pytest.fixture(scope="module")
def local_rows(quick_case, tmp_path_factory):
    """The quick design run on local processes: (CSV path, rows)."""
    csv = tmp_path_factory.mktemp("local") / "t2.csv"
    n = run_table2([quick_case], csv, workers=1, quick=True, edge=12.0, k=12)
    rows = read_results(csv)
    assert n == len(rows)
    return csv, rows


def test_quick_run_is_resumable_and_reported(quick_case, local_rows):
    case = quick_case
    csv, rows = local_rows
    assert len(rows) == 11
    assert all(np.isfinite(float(r["tre_mean_mm"])) for r in rows)
    assert run_table2([case], csv, workers=1, quick=True, edge=12.0, k=12) == 0  # everything done: nothing reruns
    assert len(read_results(csv)) == 11
    md = markdown(rows)
    assert "paper (Table II)" in md and "| q |" in md
    # rows equal registering each scenario on its own (the chunk shares one ICP over the
    # S and S + planes scenarios, which is exact: ICP sees only the stylus features)
    from navapp.anatomy.caseio import read_case
    from navapp.geometry.tre import mean_tre
    from navapp.registration.pipeline import prepare, register
    from navapp.simulation.levels import data_level

    c = read_case(case)
    model, _ = prepare(c, 12.0, 12)
    for r in rows:
        if r["level"].startswith("S+"):
            planes = tuple(int(p) for p in r["planes"].split("-"))
            reg = register(model, data_level(case, "S+planes", planes=planes, case=c))
            x0, x1 = c.need_truth().tre_points(model.basis.nodes)
            assert np.isclose(mean_tre(reg.transform(x0), x1),
                              float(r["tre_mean_mm"]), atol=1e-4)


def test_an_unreachable_dask_scheduler_is_one_line(monkeypatch):
    pytest.importorskip("distributed", reason="the study extra (pip install -e '.[study]') is not installed")
    import socket

    from navapp.errors import NavappError
    from navapp.evaluation import distribute, table2

    with socket.socket() as s:  # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    from distributed import Client

    monkeypatch.setattr(distribute, "DASK_CONNECT_S", 2)
    timeouts = []

    def client(address, timeout=None):  # distributed's Client, its connect timeout recorded
        timeouts.append(timeout)
        return Client(address, timeout=timeout)

    with pytest.raises(NavappError) as e:
        table2.dask_client(f"tcp://127.0.0.1:{port}", client_class=client)
    assert timeouts == ["2s"]  # bounded by DASK_CONNECT_S, not distributed's default
    msg = str(e.value)
    assert "\n" not in msg and f"127.0.0.1:{port}" in msg and "no Dask scheduler answers" in msg


NO_DASK = "Dask distributed is not installed (pip install -e '.[test]')"


def _same_rows(a, b):
    """Rows equal up to order and wall time (seconds differ from run to run)."""
    def key(r):
        return (r["case"], r["level"], r["planes"])

    def strip(r):
        return {k: v for k, v in r.items() if k != "seconds"}

    return [strip(r) for r in sorted(a, key=key)] == [strip(r) for r in sorted(b, key=key)]


def _study_cli(monkeypatch, case, tmp, *extra, chunk=6):
    """`navapp study table2 --quick --edge 12 --k 12` on ``case`` (the CLI's defaults are the
    4 mm, k = 45 model), the scenarios still to run in chunks of ``chunk`` (6: the 11 in two,
    so that two workers both get one). Returns (exit code, CSV path)."""
    import functools

    from navapp import cli
    from navapp.evaluation import table2

    monkeypatch.setattr(table2, "run_table2", functools.partial(table2.run_table2, chunk=chunk))
    csv = tmp / "t2.csv"
    code = cli.main(["--quiet", "study", "table2", "--quick", "--cases", str(case), "--results", str(csv),
                     "--report", str(tmp / "report"), "--edge", "12", "--k", "12", *extra])
    return code, csv


@pytest.mark.integration  # a two-worker Dask cluster: 861 s on a loaded machine; CI runs it
def test_dask_scheduler_matches_the_local_run(quick_case, local_rows, tmp_path, monkeypatch):
    """`navapp study table2 --quick --scheduler ADDRESS` against a real Dask cluster (two
    worker processes): it finishes and every row equals the local run's (TRE, iterations,
    stop reason; only the wall time differs)."""
    distributed = pytest.importorskip("distributed", reason=NO_DASK)
    # the cluster computes four S + planes rows (two chunks of two, one per worker) and the
    # run resumes the other seven from the local run's CSV: the S + all, CBCT and iCT rows
    # took 10-19 s each at load 4, a chunk holding them a minute, and the suite's time is short
    csv_lines = local_rows[0].read_text().splitlines(keepends=True)
    header, body = csv_lines[0], csv_lines[1:]
    rows = read_results(local_rows[0])
    fresh = [i for i, r in enumerate(rows) if r["level"].startswith("S+") and r["level"] != "S+all"][:4]
    assert len(fresh) == 4
    (tmp_path / "t2.csv").write_text(header + "".join(line for i, line in enumerate(body) if i not in fresh))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  host="127.0.0.1") as cluster:
        code, csv = _study_cli(monkeypatch, quick_case, tmp_path, "--scheduler", cluster.scheduler_address,
                               chunk=2)
        assert code == 0
        with distributed.Client(cluster) as client:  # both workers were there to take chunks
            assert len(client.scheduler_info()["workers"]) == 2
    rows = read_results(csv)
    assert len(rows) == len(local_rows[1]) == 11
    assert _same_rows(rows, local_rows[1])


def test_an_unreachable_scheduler_from_the_command_line_is_one_line(quick_case, tmp_path, monkeypatch, capsys):
    pytest.importorskip("distributed", reason=NO_DASK)
    import socket

    from navapp.evaluation import distribute

    with socket.socket() as s:  # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(distribute, "DASK_CONNECT_S", 2)
    code, _ = _study_cli(monkeypatch, quick_case, tmp_path, "--scheduler", f"tcp://127.0.0.1:{port}")
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert "\n" not in err and "Traceback" not in err
    assert err.startswith(f"navapp: error: --scheduler tcp://127.0.0.1:{port}: no Dask scheduler answers")


def test_quiet_is_scoped(monkeypatch):
    """progress.quiet() hides bars inside its block only, nests, and restores on error;
    run_chunk (which also runs in the caller's process, to warm caches) no longer leaves
    progress.QUIET set behind it."""
    from navapp import progress
    from navapp.evaluation import table2
    from navapp.evaluation.table2 import run_chunk

    monkeypatch.setattr(progress, "QUIET", False)
    assert not progress.is_quiet()
    with progress.quiet():
        assert progress.is_quiet() and progress.bar(3, "x").disable
        with progress.quiet(False):
            assert not progress.is_quiet()
        assert progress.is_quiet()
    assert not progress.is_quiet() and not progress.bar(3, "x").disable
    seen = []

    def failing_read(path):
        seen.append(progress.is_quiet())
        raise RuntimeError("stop here")

    monkeypatch.setattr(table2, "read_case", failing_read)
    with pytest.raises(RuntimeError, match="stop here"):
        run_chunk("no-such-case", [])
    assert seen == [True]
    assert progress.QUIET is False and not progress.is_quiet()


# ---------------------------------------------------------------- the README's other study commands


def _run(argv, capsys):
    """``navapp --quiet ARGV`` in this process: (exit code, the last stdout line as JSON or
    None, stderr)."""
    import json

    from navapp.cli import main

    code = main(["--quiet", *argv])
    out, err = capsys.readouterr()
    lines = out.strip().splitlines()
    return code, (json.loads(lines[-1]) if lines else None), err


SMALL = ["--edge", "12", "--k", "12"]


def test_study_robustness_command(quick_case, tmp_path, capsys):
    """``navapp study robustness --quick --cases CASE --edge 12 --k 12``: the quick design
    (0°, 15°, 20° × three label conditions × one draw × two methods), every row a finite
    TRE, the report and its plot; a second run resumes with nothing to do."""
    import csv as csvmod

    argv = ["study", "robustness", "--quick", "--cases", str(quick_case), "--report", str(tmp_path / "r"), *SMALL]
    code, summary, err = _run(argv, capsys)
    assert code == 0, err
    rows = list(csvmod.DictReader((tmp_path / "r" / "robustness.csv").open()))
    assert summary["registrations_run"] == len(rows) == 3 * 3 * 2
    assert {r["method"] for r in rows} == {"single-icp", "default"}
    assert {float(r["angle_deg"]) for r in rows} == {0.0, 15.0, 20.0}
    assert {r["condition"] for r in rows} == {"clean", "shifted", "mislabelled"}
    assert all(0 < float(r["tre_mm"]) < 100 and float(r["seconds"]) > 0 for r in rows)
    clean = [float(r["tre_mm"]) for r in rows if r["condition"] == "clean" and float(r["angle_deg"]) == 0]
    assert max(clean) < 10  # from the true pose, clean data: a real fit, not a lost one
    assert summary["report"] == str(tmp_path / "r" / "robustness.md")
    assert (tmp_path / "r" / "robustness.png").stat().st_size > 0
    assert "single-icp" in Path(summary["report"]).read_text()
    code, again, err = _run(argv, capsys)
    assert code == 0 and again["registrations_run"] == 0, err


def test_study_next_plane_command(quick_case, local_rows, tmp_path, capsys):
    """``navapp study next-plane --cases CASE --results TABLE2.csv --edge 12 --k 12``: three
    greedy suggestions from S per criterion, each step adding one new recorded plane,
    ranked against the case's Table II rows; the report with its speed line."""
    import csv as csvmod

    csv, _ = local_rows
    code, summary, err = _run(["study", "next-plane", "--cases", str(quick_case), "--results", str(csv),
                               "--report", str(tmp_path / "r"), *SMALL], capsys)
    assert code == 0, err
    assert summary == {"report": str(tmp_path / "r" / "next_plane.md")}
    rows = list(csvmod.DictReader((tmp_path / "r" / "next_plane.csv").open()))
    assert len(rows) == 3 * 3 and {r["criterion"] for r in rows} == {"ê (default)", "d only", "σ only"}
    for crit in {r["criterion"] for r in rows}:
        steps = [r for r in rows if r["criterion"] == crit]
        assert [r["level"] for r in steps] == ["S+1", "S+2", "S+3"]
        planes = [set(r["planes"].split("-")) for r in steps]
        assert [len(p) for p in planes] == [1, 2, 3] and planes[0] < planes[1] < planes[2]
        assert all(0 < float(r["tre_mean_mm"]) < 20 for r in steps)
    md = Path(summary["report"]).read_text()
    assert "Speed: one suggestion over" in md
    # without Table II rows to rank against: one line
    code, _, err = _run(["study", "next-plane", "--cases", str(quick_case), "--results", str(tmp_path / "none.csv"),
                         "--report", str(tmp_path / "r2"), *SMALL], capsys)
    assert code == 2 and err.count("\n") == 1 and "no Table II results" in err


@pytest.fixture(scope="module")
def second_liver_case(tmp_path_factory, cache_root):
    """Phantom 1 simulated like ``quick_case`` (a second liver: error-estimate validates on it)."""
    from navapp.simulation.scene import parse_scene
    from navapp.simulation.simulate import simulate

    scene = parse_scene({"name": "q1", "anatomy": {"phantom": 1},
                         "deformation": {"release": "L", "mesh_edge_mm": 12.0}, "ius": {"planes": 16}})
    case = tmp_path_factory.mktemp("study1") / "q1"
    simulate(scene, case, cache_root)
    return case


def test_study_error_estimate_command(quick_case, second_liver_case, tmp_path, capsys):
    """``navapp study error-estimate --quick --cases A B --edge 12 --k 12`` (one plane
    combination per level: 6 registrations a case, not 12): ê calibrated on the
    first case's liver, judged on the other's; the printed calibration is the one in the
    CSV, its band brackets 1 (ê is a scale), coverage is a fraction. One liver alone is one
    line."""
    import csv as csvmod

    code, summary, err = _run(["study", "error-estimate", "--quick", "--cases", str(quick_case),
                               str(second_liver_case), "--report", str(tmp_path / "r"), *SMALL], capsys)
    assert code == 0, err
    cal = summary["calibration"]
    assert all(np.isfinite(cal[k]) for k in ("a", "b", "c", "e", "lower", "upper"))
    assert 0 < cal["lower"] < 1 < cal["upper"]
    rows = list(csvmod.DictReader((tmp_path / "r" / "error_estimate.csv").open()))
    assert rows and all(0 <= float(r["coverage"]) <= 1 for r in rows)
    assert all(float(r["upper"]) == pytest.approx(cal["upper"], rel=1e-5) for r in rows)
    assert "q1" in Path(summary["report"]).read_text()
    code, _, err = _run(["study", "error-estimate", "--quick", "--cases", str(quick_case), "--report",
                         str(tmp_path / "r1"), *SMALL], capsys)
    assert code == 2 and err.count("\n") == 1 and "at least two livers" in err


def test_rendering_leaves_matplotlib_global_state_alone(tmp_path):
    """Importing the figure modules used to switch every caller's backend to Agg; now they
    draw on their own Figure objects and the PNG is still written."""
    code = f"""
import matplotlib
matplotlib.use("svg")
from navapp.evaluation import render, report, cost_report, robustness_report
from navapp.anatomy.model import PreopModel
import trimesh
m = PreopModel(liver=trimesh.creation.icosphere(subdivisions=2, radius=60.0), name="ball")
render.phantom_figure(m, {str(tmp_path / 'ball.png')!r})
import matplotlib.pyplot as plt
print(matplotlib.get_backend(), len(plt.get_fignums()))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["svg", "0"]
    from skimage.io import imread

    img = imread(tmp_path / "ball.png")
    assert img.shape[0] > 100 and img.std() > 0


def test_fixed_planes_of_a_level():
    """"S+all" is every plane, the levels without planes none; "S+n" names a count, not the planes:
    asking it for them is an error, not S alone (report.distance_plot had read any level but
    "S+all" as no planes)."""
    from navapp.simulation.levels import LEVELS, SOURCE_LEVELS, fixed_planes

    assert fixed_planes("S+all", 4) == (0, 1, 2, 3)
    planeless = ("rigid", "S", *SOURCE_LEVELS, "CBCT", "iCT")  # a source level ("S+laparoscope") has none
    assert {lv: fixed_planes(lv, 4) for lv in planeless} == dict.fromkeys(planeless, ())
    for level in LEVELS:
        if level.startswith("S+") and level != "S+all" and level not in SOURCE_LEVELS:
            with pytest.raises(ValueError, match="how many planes"):
                fixed_planes(level, 4)

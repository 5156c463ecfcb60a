"""The documented commands (README.md, docs/commands.md, the Python block of docs/api.md) run as
a user runs them, in a fresh folder, with their output checked
(small meshes where the command takes them, so that the suite stays within its budget). One case
folder, made by ``navapp demo``, serves the commands that read a case."""

import json
from pathlib import Path

import numpy as np
import pytest

from navapp.cli import main

QUICK = ["--edge", "12", "--k", "12"]


def last_json(out: str) -> dict:
    return json.loads(out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """``navapp demo`` in a fresh folder, default ``--out``: it simulated the demo scene and then
    ended in a traceback (``'Namespace' object has no attribute 'local_modes'``) when it handed
    the case to ``register`` with a Namespace written out by hand."""
    import contextlib
    import io
    import os

    folder = tmp_path_factory.mktemp("readme")
    out, err = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["--quiet", "demo", "--truth-edge", "12", *QUICK])
    finally:
        os.chdir(cwd)
    return folder, code, out.getvalue(), err.getvalue()


def test_demo_simulates_and_registers(demo_run):
    folder, code, out, err = demo_run
    assert code == 0, err
    brief = last_json(out)
    case = folder / "navapp-demo"
    assert brief["case"] == "demo" and brief["out"] == "navapp-demo/registration"
    assert brief["tre_deformable"] < brief["tre_rigid"]
    assert set(brief["target_centroid_error_mm"]) == {"tumour1", "tumour2"}
    assert "navapp: demo case simulated into navapp-demo" in err
    result = json.loads((case / "registration/result.json").read_text())
    assert result["k"] == 12 and result["mesher"]["edge_mm"] == 12.0
    assert np.isfinite(result["omega"])
    for name in ("case.toml", "preop/liver.ply", "truth/field.npz", "registration/liver.ply",
                 "registration/targets.csv"):
        assert (case / name).is_file(), name


@pytest.fixture
def in_demo_folder(demo_run, monkeypatch):
    folder, code, _, _ = demo_run
    assert code == 0
    monkeypatch.chdir(folder)
    return folder


def test_mesh_and_precompute(in_demo_folder, capsys):
    """``navapp mesh CASE [--edge]``, ``navapp precompute CASE [--edge] [--k]``."""
    assert main(["--quiet", "mesh", "navapp-demo", "--edge", "12"]) == 0
    mesh = last_json(capsys.readouterr().out)
    assert mesh["nodes"] > 500 and mesh["method"].split()[0] in ("gmsh", "ftetwild") and mesh["inverted"] == 0
    assert main(["--quiet", "precompute", "navapp-demo", *QUICK]) == 0
    pre = last_json(capsys.readouterr().out)
    # the demo registered at these settings: the basis comes from the cache
    assert pre["k"] == 12 and pre["edge_mm"] == 12.0 and pre["from_cache"] is True
    assert pre["nodes"] == mesh["nodes"] and pre["surface_nodes"] < pre["nodes"]


def test_register_options(in_demo_folder, capsys):
    """``navapp register CASE [--out DIR] [--k] [--no-deform] [--local-modes] [--json]``."""
    assert main(["--quiet", "register", "navapp-demo", "--out", "rigid", "--no-deform", "--json", *QUICK]) == 0
    rigid = last_json(capsys.readouterr().out)
    assert rigid["out"] == "rigid" and "iterations" not in rigid and "tre_rigid" in rigid
    assert (in_demo_folder / "rigid/result.json").is_file() and (in_demo_folder / "rigid/liver.ply").is_file()
    # without --json: the whole summary, indented (the demo's registration, again)
    assert main(["--quiet", "register", "navapp-demo", "--out", "again", *QUICK]) == 0
    io = capsys.readouterr()
    full = json.loads(io.out)
    assert "registered demo: results in again" in io.err
    assert full["tre_deformable"]["mean_mm"] < full["tre_rigid"]["mean_mm"]


API_PAGE = Path(__file__).resolve().parent.parent / "docs" / "api.md"  # the Python API page


def test_python_api_block(in_demo_folder, capsys):
    """The Python API page's block (once the README's), run on the demo's case folder at the quick settings (the
    block's own defaults, a 4 mm mesh and k = 45, take minutes; its last line simulates a
    study scene at 3.5 mm, which ``navapp demo`` already stands for)."""
    text = API_PAGE.read_text()
    block = text.split("```python\n", 1)[1].split("```", 1)[0]
    for old, new in (('"my-case"', '"navapp-demo"'), ("navapp.prepare(case)", "navapp.prepare(case, edge=12, k=12)"),
                     ('navapp.simulate(scene, "phantom0-L")', "assert scene.name == 'phantom0-L'")):
        assert old in block, old  # the block still reads as this test expects
        block = block.replace(old, new)
    exec(compile(block, str(API_PAGE), "exec"), {})
    stop, mean = capsys.readouterr().out.split()
    assert stop in ("converged", "stationary", "max_iterations") and 0 < float(mean) < 10


def test_phantom(tmp_path, monkeypatch, capsys):
    """``navapp phantom --liver N --out DIR``."""
    monkeypatch.chdir(tmp_path)
    assert main(["--quiet", "phantom", "--liver", "1", "--out", "p1"]) == 0
    out = last_json(capsys.readouterr().out)
    assert out["phantom"] == 1 and out["out"] == "p1" and 600 < out["volume_ml"] < 4000
    assert out["portal_branches"] > 1 and out["hepatic_branches"] > 1
    for name in ("liver.ply", "portal.ply", "hepatic.ply", "regions.csv"):
        assert (tmp_path / "p1/preop" / name).is_file(), name


def test_replay_plays_a_scene_to_a_client(tmp_path):
    """``navapp replay SCENE --port P --rate 25 --latency-ms 0 --seconds S``, as a process (it
    handles Ctrl-C): a tracking client receives the stylus it plays (a scene on a coarse truth
    mesh, two planes, to stay quick)."""
    import socket
    import subprocess
    import sys
    import time

    from conftest import free_port

    import navapp
    from navapp.tracking.client import TrackingClient
    from navapp.tracking.config import TrackingConfig

    text = (navapp.scene_dir() / "demo.toml").read_text().replace("mesh_edge_mm = 3.5", "mesh_edge_mm = 12.0")
    (tmp_path / "scene.toml").write_text(text.replace("planes = 16", "planes = 2"))
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "navapp", "--quiet", "replay", "scene.toml", "--port", str(port),
                             "--rate", "25", "--latency-ms", "0", "--seconds", "6"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    got = None
    try:
        deadline = time.monotonic() + 300  # the scene is simulated first
        while proc.poll() is None and time.monotonic() < deadline:
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.2)
        client = TrackingClient(TrackingConfig(port=port)).start()
        try:
            deadline = time.monotonic() + 5
            while client.latest_stylus is None and time.monotonic() < deadline:
                time.sleep(0.1)
            got = client.latest_stylus
        finally:
            client.stop()
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert got is not None, err
    assert f"replaying demo on 127.0.0.1:{port} as PLUS would" in err
    assert json.loads(out.strip().splitlines()[-1])["port"] == port


SMALL_BENCH = ["--truth-edge", "12", "--edges", "12", "--ks", "12"]


def test_bench_register(capsys):
    """``navapp bench register`` on the demo scene simulated at 12 mm (``--truth-edge``), a
    12 mm, k = 12 model, one repeat: its timings and TREs are there and sane (the deformable
    fit beats the rigid one, adding a plane warm-started takes fewer iterations than none)."""
    assert main(["--quiet", "bench", "register", "--repeats", "1", "--planes", "2", *SMALL_BENCH]) == 0
    out = last_json(capsys.readouterr().out)
    assert out["k"] == 12 and out["planes"] == 2 and 500 < out["nodes"] < 3000
    assert out["points"]["anterior"] > 0 and out["median_seconds"] > 0 and out["iterations"] >= 1
    assert out["stop_reason"] in ("converged", "stationary", "max_iterations")
    assert out["per_iteration_ms"] and all(v >= 0 for v in out["per_iteration_ms"].values())
    tre = out["tre_mm"]
    assert 0 < tre["deformable"] < tre["rigid"] < 30
    one = out["add_one_plane"]
    assert one["warm_median_seconds"] > 0 and one["cold_seconds"] > 0 and 0 < one["tre_warm_mm"] < 30
    # before and after side by side: the searches begun at the root, and the folds one after
    # another, give the same registration
    ba = out["before_after"]
    assert set(ba) == {"before", "cold_search", "sequential_folds", "after"} and \
        all(v["median_cpu_seconds"] > 0 for v in ba.values())
    assert ba["cold_search"]["tre_mm"] == ba["sequential_folds"]["tre_mm"] == ba["after"]["tre_mm"]


def test_bench_live(capsys):
    """``navapp bench live --frames 4`` at the same small settings: every variant re-registered
    each frame that showed a structure, with a per-update time and a TRE after the last frame."""
    assert main(["--quiet", "bench", "live", "--frames", "4", "--planes", "2", *SMALL_BENCH]) == 0
    out = last_json(capsys.readouterr().out)
    assert out["k"] == 12 and out["kept_planes"] == 2 and 1 <= out["updates"] <= 4
    assert out["segmentation_ms_median"] > 0 and out["cold_start_s"] > 0
    for name in ("default", "converged_one_thread", "converged_as_installed"):
        v = out[name]
        assert 0 < v["min_ms"] <= v["median_ms"] <= v["max_ms"], name
        assert v["iterations_median"] >= 1 and 0 < v["tre_after_last_frame_mm"] < 30, name
        assert 0 <= v["within_one_frame_at_30hz"] <= 1
    assert out["default"]["iterations_median"] == 1  # the viewer's one LM iteration per frame
    assert out["one_thread_over_installed"]["median_of_ratios"] > 0
    warm = out["before_after_warm_search"]  # the same frames with every search begun at the root
    assert warm["variants"] == ["default_cold_search", "default"] and warm["before_over_after_median"] > 0
    assert warm["tre_after_last_frame_mm"][0] == warm["tre_after_last_frame_mm"][1]
    kept = out["before_after_kept_points"]  # the same frames with a feature the frame adds to searched whole
    assert kept["variants"] == ["default_search_whole", "default"] and kept["before_over_after_median"] > 0
    assert kept["tre_after_last_frame_mm"][0] == kept["tre_after_last_frame_mm"][1]
    for key, after in (("before_after_second_core", "default"), ("before_after_always_split", "default_always_split")):
        pair = out[key]  # one thread against the kernels split between two: the same fits
        assert pair["variants"] == ["default_one_thread", after] and pair["before_over_after_median"] > 0
        assert pair["tre_after_last_frame_mm"][0] == pair["tre_after_last_frame_mm"][1]
    assert out["default_one_thread"]["split_share"] == 0.0 and 0 <= out["default"]["split_share"] <= 1


def test_bench_precompute(capsys):
    """``navapp bench precompute --edges 12 --ks 12``: one pair of rows, before session 40's
    precompute and after, each from a fresh process and a cold cache, with its stage times,
    peak memory and a warm reload faster than the cold build; then both side by side."""
    assert main(["--quiet", "bench", "precompute", "--edges", "12", "--ks", "12"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    rows = [json.loads(x) for x in lines if x.startswith('{"variant"')]
    assert sorted(r["variant"] for r in rows) == ["after", "before"] and rows[0]["variant"] == "before"
    for row in rows:
        assert row["edge_mm"] == 12.0 and row["k"] == 12 and row["relax"] == "local"
        assert 500 < row["nodes"] < 3000 and row["surface_nodes"] < row["nodes"]
        assert 600 < row["volume_ml"] < 4000 and row["peak_memory_mb"] > 0
        assert row["seconds"]["mesh"] > 0 and row["total_seconds"] >= row["seconds"]["mesh"]
        assert 0 < row["cache_load_seconds"]["total"] < row["total_seconds"]
        assert row["process_cpu_seconds"] > 0 and row["process_seconds"] >= row["total_seconds"]
        assert "basis_file" not in row and "mesh_file" not in row  # the temporary cache is removed
        assert row["solver"] in ("pardiso", "superlu") and row["mesher"].startswith(("gmsh", "ftetwild"))
    assert rows[0]["nodes"] == rows[1]["nodes"]  # phantom 0 is meshed the same way before and after
    assert any(x.startswith("stage") and "before" in x and "after" in x for x in lines)
    summary = json.loads(lines[-1])["before_after"]
    assert summary["runs"] == 1 and set(summary["median_seconds"]) == {"before", "after"}
    assert summary["median_seconds"]["after"]["process cpu"] == rows[1]["process_cpu_seconds"]
    assert summary["after_over_before_median"]["process_cpu_seconds"] > 0


def test_bench_import(capsys):
    """``navapp bench import --repeats 1 --routes stl``: the STL route alone (the CT grid's five
    other routes take minutes: the full command is the benchmark's, run by hand), a child
    process per import with its own peak memory and the import's stage times."""
    assert main(["--quiet", "bench", "import", "--repeats", "1", "--routes", "stl"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    assert lines[0]["bench"] == "import" and "no CT grid" in lines[0]["case"] and lines[0]["write_s"] > 0
    assert [x["route"] for x in lines[1:]] == ["stl"]
    row = lines[1]
    assert row["wall_s_median"] > 0 and len(row["wall_s"]) == 1 and 50 < row["peak_mb_max"] < 4000
    assert {"read", "cleanup", "centerlines", "total"} <= set(row["stages_s"])
    assert 0 < row["stages_s"]["total"] <= row["wall_s_median"]
